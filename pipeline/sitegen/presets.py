"""Reference-site presets (`configs/sites/*.yaml`) validated into typed objects.

A preset describes a building and how it is captured: floor size and corridor grid, room sizes, object
densities, identity cues, camera, laser, capture stops, runs and the rendering. `tiny` is for tests,
`office` is the demo default (about 40 x 30 m, with the cues of a real building), `twins` the same floor
without them (repetitive on purpose), `paper` mimics the seed paper's 80 x 80 m floor, with cues.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from pipeline.config import CONFIG_DIR, OdometryNoise, Strict, format_validation_error
from pipeline.errors import ConfigError
from pipeline.io.site import DEFAULT_CLASSES
from pipeline.sitegen.camera_effects import CameraEffects

SITES_DIR = CONFIG_DIR / "sites"


class FloorPlan(Strict):
    size: tuple[float, float] = Field((40.0, 30.0), description="building width (x) and height (y), m")
    corridors_x: int = Field(2, ge=2, description="vertical corridor lines (>= 2 makes loops)")
    corridors_y: int = Field(2, ge=2, description="horizontal corridor lines")
    corridor_width: float = Field(2.0, gt=0.8)
    band_depth: float = Field(6.0, gt=1.5, description="depth of the room band along the outer walls")
    room_widths: tuple[float, ...] = Field((3.6, 4.2, 4.8), min_length=1, description="standard room widths")
    min_room_depth: float = Field(2.2, gt=1.0)
    max_room_depth: float = Field(7.0, gt=1.5)
    wall_height: float = Field(2.8, gt=2.2)
    wall_thickness: float = Field(0.15, gt=0.02)
    door_width: float = Field(0.95, gt=0.6)
    jitter: float = Field(0.25, ge=0, description="random shift of corridor lines, m (breaks exact symmetry)")

    @model_validator(mode="after")
    def _fits(self) -> FloorPlan:
        w, h = self.size
        for n, extent in ((self.corridors_x, w), (self.corridors_y, h)):
            need = 2 * self.band_depth + n * self.corridor_width + (n - 1) * self.min_room_depth
            if need > extent:
                raise ValueError(f"{n} corridors of {self.corridor_width} m, {self.band_depth} m bands and "
                                 f"{self.min_room_depth} m inner rooms need {need:.2f} m but the floor has {extent} m: "
                                 "enlarge floor.size or reduce band_depth / corridor_width")
        return self


class Furnishing(Strict):
    """Densities of the objects; the eight detector classes and undetected furniture."""

    classes: tuple[str, ...] = DEFAULT_CLASSES
    meeting_room_share: float = Field(0.2, ge=0, le=1)
    second_door_share: float = Field(0.3, ge=0, le=1, description="rooms with an extra closed door")
    posters_per_room: tuple[int, int] = (0, 2)
    corridor_poster_spacing: float = Field(5.0, gt=0.5)
    extinguisher_spacing: float = Field(14.0, gt=1.0)
    exit_sign_spacing: float = Field(16.0, gt=1.0)
    plants_per_room: tuple[int, int] = (0, 1)
    window_spacing: float = Field(2.6, gt=1.0)
    poster_pictures: int = Field(12, ge=1, description="distinct poster pictures (repeated across the site)")


class IdentitySpec(Strict):
    """Identity cues of real buildings (`pipeline.sitegen.identity`); all off gives the plain repetitive floor."""

    wings: int = Field(1, ge=1, le=8, description="zones of the floor, lettered A, B, ... (room numbers, colours)")
    wing_colours: bool = Field(False, description="corridor walls in their wing's colour, rooms lightly tinted")
    wing_floor_materials: int = Field(3, ge=1, description="floor textures the wings' corridors cycle through")
    accent_wall_share: float = Field(0.25, ge=0, le=1, description="rooms painted in a colour of their own")
    room_plates: bool = Field(False, description="a number plate (and a name) beside every room door")
    plate_names_share: float = Field(0.6, ge=0, le=1, description="offices whose plate also carries a name")
    unique_pictures: bool = Field(False, description="every poster its own picture (else furnishing.poster_pictures "
                                  "pictures repeat)")
    notice_boards: bool = Field(False, description="notice boards near junctions and along corridors")
    notice_board_spacing: float = Field(14.0, gt=1.0, description="metres between notice boards along a corridor")
    escape_plans: bool = Field(False, description="fire-escape plans of this floor near junctions")
    signs: bool = Field(False, description="directory signs naming the wings each way, near junctions")
    room_types: bool = Field(False, description="a kitchen, a lounge and a storage room per wing, each furnished "
                             "its own way")
    desk_clutter: bool = Field(False, description="monitors, books and papers on desks")
    outside_views: bool = Field(False, description="window panes show each facade's own outside view")
    painted_walls: bool = Field(False, description="walls in smooth paint instead of the library's roughcast and "
                                "brick: rooms in their tint, corridors light above a dado in their wing's colour")
    dado_height: float = Field(1.0, ge=0, le=2.0, description="painted corridors: height of the wing-coloured dado, "
                               "m (0: none)")
    room_boards: bool = Field(False, description="a pinboard of its own above the desks of every office and "
                              "meeting room")


EFFECT_BASES = ("off", "realistic")


def _merged(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def camera_effects_of(value) -> CameraEffects:
    """`camera.effects` as written in a preset: absent or `off` (every effect off, JPEG 92: the frames synth wrote
    before camera effects), `realistic` (every effect on, `CameraEffects`' defaults), or a mapping of keys laid
    over the base its `base` key names (default `off`), so `camera.effects.noise.enabled=true` turns on the noise
    alone and `camera.effects.base=realistic` + `camera.effects.noise.enabled=false` all but the noise."""
    if isinstance(value, CameraEffects):
        return value
    if isinstance(value, str):
        value = {"base": value}
    if not isinstance(value, dict):
        raise ValueError(f"expected off, realistic or a mapping of effect keys, got {value!r}")
    over = dict(value)
    base = over.pop("base", "off")
    if base not in EFFECT_BASES:
        raise ValueError(f"base must be one of {', '.join(EFFECT_BASES)}, got {base!r}")
    start = CameraEffects.off() if base == "off" else CameraEffects()
    return CameraEffects.model_validate(_merged(start.model_dump(), over))


class CameraSpec(Strict):
    width: int = Field(640, ge=32)
    height: int = Field(480, ge=24)
    hfov_deg: float = Field(70.0, gt=10, lt=170)
    height_m: float = Field(1.2, gt=0.1, description="camera height above the floor")
    views: int = Field(6, ge=1)
    effects: CameraEffects = Field(default_factory=CameraEffects.off, description="camera realism (`pipeline."
                                   "sitegen.camera_effects`): off, realistic, or keys over a base (see "
                                   "`camera_effects_of`); default off")

    @field_validator("effects", mode="before")
    @classmethod
    def _effects(cls, value):
        return camera_effects_of(value)


class LaserSpec(Strict):
    beams: int = Field(1081, ge=2)
    fov_deg: float = Field(270.0, gt=0, le=360)
    range_max: float = Field(30.0, gt=0)
    noise_sigma: float = Field(0.01, ge=0)
    dropout: float = Field(0.01, ge=0, lt=1)
    people: int = Field(4, ge=0, description="unmapped people walking around during runs")
    moved_chairs_share: float = Field(0.15, ge=0, le=1, description="chairs displaced between mapping and runs")


class StopSpec(Strict):
    spacing: float = Field(2.0, gt=0.3)
    clearance: float = Field(0.45, gt=0)
    jitter: float = Field(0.3, ge=0)


class RunSpec(Strict):
    mapping_runs: int = Field(2, ge=0)
    query_runs: int = Field(3, ge=0)
    steps_per_run: int = Field(200, ge=2)
    mapping_steps: int | None = Field(None, ge=2, description="steps of each mapping run [default: steps_per_run]; "
                                      "the sequence database covers what the mapping runs drive past")
    step_m: float = Field(0.4, gt=0.05)
    kidnaps_per_query_run: int = Field(1, ge=0)
    odometry_noise: OdometryNoise = OdometryNoise()


class RenderSpec(Strict):
    exposure_range: tuple[float, float] = (0.8, 1.2)
    ambient_range: tuple[float, float] = (0.25, 0.45)
    light_spacing: float = Field(4.0, gt=0.5, description="ceiling lights every this many metres")
    min_box_area_px: float = Field(100.0, ge=0, description="smallest visible object area that gets a box")
    min_visible_share: float = Field(0.25, ge=0, le=1, description="smallest visible share of the object's area")


class SitePreset(Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    floor: FloorPlan = FloorPlan()
    furnishing: Furnishing = Furnishing()
    camera: CameraSpec = CameraSpec()
    laser: LaserSpec = LaserSpec()
    stops: StopSpec = StopSpec()
    runs: RunSpec = RunSpec()
    render: RenderSpec = RenderSpec()
    identity: IdentitySpec = IdentitySpec()
    map_resolution: float = Field(0.05, gt=0, le=0.5)


def load_site_preset(name_or_path: str | Path, overrides: dict | None = None) -> SitePreset:
    """A preset by name (`configs/sites/<name>.yaml`) or path; unknown keys and bad values name the key."""
    return load_preset(name_or_path, overrides, SitePreset, SITES_DIR)


def load_preset(name_or_path: str | Path, overrides: dict | None, model: type, directory: Path):
    """A preset of `model` by name (`directory/<name>.yaml`) or path, with dotted-key overrides."""
    path = Path(name_or_path)
    if not (path.suffix in (".yaml", ".yml") or path.exists()):
        path = directory / f"{name_or_path}.yaml"
        if not path.is_file():
            known = ", ".join(sorted(p.stem for p in directory.glob("*.yaml")))
            raise ConfigError(f"unknown site preset '{name_or_path}' (presets in {directory}: {known})")
    if not path.is_file():
        raise ConfigError(f"{path}: site preset not found")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    raw.setdefault("name", path.stem)
    for key, value in (overrides or {}).items():
        node = raw
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{path}: override '{key}': '{part}' is a value, not a section")
        node[parts[-1]] = value
    try:
        return model.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(format_validation_error(str(path), err, model)) from None
