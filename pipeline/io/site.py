"""`site.yaml`: what a capture directory says about its site (camera, rig, laser, object classes)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, ValidationError, model_validator

from pipeline.errors import InputError, Problem
from pipeline.io.text_files import read_text

DEFAULT_CLASSES = ("door", "window", "chair", "fire_extinguisher", "poster", "trash_bin", "plant", "exit_sign")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Distortion(_Strict):
    """Lens distortion of the images: ROS's plumb_bob, OpenCV's 5-coefficient radial-tangential model.

    coeffs are (k1, k2, p1, p2, k3) in that order (CameraInfo's D, OpenCV's distCoeffs), on normalised
    coordinates ((u - cx) / fx, (v - cy) / fy) of the camera's fx, fy, cx, cy."""

    model: Literal["plumb_bob"] = "plumb_bob"
    coeffs: tuple[FiniteFloat, ...] = Field(min_length=5, max_length=5, description="k1, k2, p1, p2, k3")


class Camera(_Strict):
    """Intrinsics of the capture camera, in pixels: pinhole, or pinhole plus `distortion` when given."""

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    distortion: Distortion | None = None


class Rig(_Strict):
    """Yaw of each view's camera relative to the robot base, in degrees (CCW). View i uses entry i."""

    yaw_offsets_deg: tuple[float, ...] = Field((0.0, 60.0, 120.0, 180.0, 240.0, 300.0), min_length=1)

    @property
    def yaw_offsets(self) -> tuple[float, ...]:
        return tuple(math.radians(v) for v in self.yaw_offsets_deg)


class LaserMount(_Strict):
    """base_from_laser: where the laser sits on the robot."""

    x: float = 0.0
    y: float = 0.0
    yaw_deg: float = 0.0


class Laser(_Strict):
    """A planar laser: `beams` rays evenly from angle_min to angle_max inclusive."""

    angle_min_deg: float = -135.0
    angle_max_deg: float = 135.0
    beams: int = Field(1081, ge=2)
    range_max: float = Field(30.0, gt=0)
    mount: LaserMount = LaserMount()

    @model_validator(mode="after")
    def _order(self) -> Laser:
        if self.angle_max_deg <= self.angle_min_deg:
            raise ValueError("angle_max_deg must be above angle_min_deg")
        return self

    @property
    def angle_min(self) -> float:
        return math.radians(self.angle_min_deg)

    @property
    def angle_increment(self) -> float:
        return math.radians(self.angle_max_deg - self.angle_min_deg) / (self.beams - 1)


class Extrinsic(_Strict):
    """parent_from_child in 3-D: translation in metres and a unit quaternion (x, y, z, w)."""

    xyz: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]

    @model_validator(mode="after")
    def _unit(self) -> Extrinsic:
        norm = math.sqrt(sum(q * q for q in self.quat_xyzw))
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"quat_xyzw must be a unit quaternion (its norm is {norm:.4f})")
        return self


class Extrinsics(_Strict):
    """The sensors' 3-D mounts as a recording's tf_static gave them (`siteloc ingest-bag`); optional.

    base_from_camera is the camera's optical frame (z forward, x right, y down), as ROS names it."""

    base_from_camera: Extrinsic | None = None
    base_from_laser: Extrinsic | None = None


class Site(_Strict):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    camera: Camera | None = None  # None: a laser-only site (runs of a robot without a camera, no captures)
    rig: Rig = Rig()
    laser: Laser = Laser()
    classes: tuple[str, ...] = Field(DEFAULT_CLASSES, min_length=1)
    extrinsics: Extrinsics | None = None

    @model_validator(mode="after")
    def _unique_classes(self) -> Site:
        if len(set(self.classes)) != len(self.classes):
            raise ValueError("classes must be unique")
        return self

    def class_id(self, name: str) -> int:
        """Detector label of a class: 1-based, 0 is background."""
        return self.classes.index(name) + 1


def validation_problems(path: Path, err: ValidationError) -> list[Problem]:
    out = []
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or None
        msg = "unknown key" if e["type"] == "extra_forbidden" else f"{e['msg']} (got {e.get('input')!r})"
        if e["type"] == "missing":
            msg = "required key is missing"
        out.append(Problem(str(path), msg, key=key))
    return out


def read_site(path: Path) -> Site:
    """Read and validate site.yaml; every problem is reported with its key."""
    path = Path(path)
    if not path.is_file():
        raise InputError(
            f"{path}: site description missing",
            [Problem(str(path), "file is missing", fix="write a site.yaml (see docs/capture-format.md)")],
        )
    try:
        raw = yaml.safe_load(read_text(path, what="site description"))
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML", [Problem(str(path), str(exc))]) from None
    try:
        return Site.model_validate(raw if raw is not None else {})
    except ValidationError as err:
        raise InputError(f"{path}: invalid site description", validation_problems(path, err)) from None


def write_site(path: Path, site: Site) -> Path:
    from pipeline.io.atomic import write_text_atomic

    return write_text_atomic(path, yaml.safe_dump(site.model_dump(mode="json", exclude_none=True), sort_keys=False))
