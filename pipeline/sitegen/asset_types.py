"""The asset layer's data types: meshes in one stated model frame, photographic textures, attribution.

MODEL frame (every `Model`, real or procedural):
  - metres; right-handed; z up;
  - the model's FRONT faces -y (the seat opening of a chair, the picture of a poster, the face of an exit
    sign, the side of a door or window that Sweet Home 3D calls its front); its back is at +y;
  - width along x, depth along y, height along z;
  - origin at the centre of the footprint on the floor: x and y of the bounding box centred on 0, z = 0 at
    the bottom. `Model.size` = (width, depth, height) is exactly the bounding box, equal to the Sweet Home 3D
    catalog's width/depth/height (cm / 100).
  Seen in a plan view with x right and y up, the front points down the page, as in Sweet Home 3D's plan.
  A model turned by yaw about z faces heading yaw - pi/2 (`geometry.map_from_object` uses this).
  `Model.elevation` is the catalog's default height of the bottom above the floor (exit signs 2.25 m,
  windows ~0.9 m, posters 1.5 m); the mesh itself always starts at z = 0.

Meshes are non-indexed triangle soups (vertex count a multiple of 3), counter-clockwise seen from outside.
UVs follow the OBJ/OpenGL convention: (0, 0) is the bottom-left of the texture image, v up; textures are
(H, W, 3) uint8 arrays stored as decoded (row 0 = top of the picture) and are meant to repeat.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import SitelocError

CLASSES: tuple[str, ...] = (
    "door", "window", "chair", "fire_extinguisher", "poster", "trash_bin", "plant", "exit_sign",
)
FURNITURE = "furniture"  # AssetLibrary.models key of the undetected furniture (Model.cls == "")
FURNITURE_KINDS: tuple[str, ...] = ("desk", "table", "cabinet", "sofa", "water_cooler", "whiteboard")
TEXTURE_ROLES: tuple[str, ...] = ("floor", "wall", "ceiling", "poster")

# SPDX ids of what may be used. Sweet Home 3D's own models and textures (eTeks) are offered under GPL-2+ or
# CC-BY-3.0 at the user's choice (catalog `license=GNU GPL / CC-BY 3.0`, frame.mtl header); we use CC-BY-3.0.
CC0 = "CC0-1.0"
CC_BY = "CC-BY-3.0"
CC_BY_US = "CC-BY-3.0-US"
ALLOWED_LICENSES: frozenset[str] = frozenset({CC0, CC_BY, CC_BY_US})


class AssetsUnavailableError(SitelocError):
    """Real assets are missing or broken and the caller asked for no procedural fallback."""


@dataclass(frozen=True, eq=False)
class MeshPart:
    """One material of a model: a triangle soup in the MODEL frame.

    `texture` None means flat `colour`; with a texture, `colour` is the MTL diffuse (renderers usually
    multiply or ignore it). `opacity` is the MTL `d` (window glass ~0.2-0.5; 1.0 = opaque): a renderer
    without blending may draw it opaque. `role` tags a part callers may restyle: "picture" is a poster's
    image (swap its texture for another poster picture), "" otherwise.
    """

    positions: np.ndarray  # (N, 3) float32, metres, MODEL frame
    normals: np.ndarray  # (N, 3) float32, unit length
    uvs: np.ndarray  # (N, 2) float32, OBJ/OpenGL convention
    texture: np.ndarray | None  # (H, W, 3) uint8
    colour: tuple[float, float, float]
    opacity: float = 1.0
    role: str = ""

    @property
    def n_triangles(self) -> int:
        return len(self.positions) // 3


@dataclass(frozen=True, eq=False)
class Model:
    """A piece of furniture or fixture, ready to place (see the MODEL frame above)."""

    key: str  # stable id: "<catalog>/<model folder>", e.g. "BlendSwap-CC-0/fireExtinguisher"
    cls: str  # one of CLASSES, or "" for undetected furniture
    name: str  # catalog name, e.g. "Extinguisher"
    creator: str
    license: str  # SPDX id, one of ALLOWED_LICENSES
    source: str  # Debian package + archive + file, e.g. "sweethome3d-furniture: BlendSwap-CC-0.sh3f/..."
    size: tuple[float, float, float]  # (width, depth, height) metres = bounding box
    parts: tuple[MeshPart, ...]
    procedural: bool
    kind: str = ""  # finer than cls: "door" / "door_exterior", "desk" / "table" / "cabinet" / ...
    elevation: float = 0.0  # catalog default height of the model's bottom above the floor, metres
    wall_span_y: tuple[float, float] | None = None  # doors/windows: y interval (MODEL frame) the wall fills

    @property
    def n_triangles(self) -> int:
        return sum(p.n_triangles for p in self.parts)


@dataclass(frozen=True)
class TextureInfo:
    """Where a role texture came from, and its real-world tile size when the catalog gives one."""

    role: str
    name: str
    creator: str
    license: str
    source: str
    tile_size_m: tuple[float, float] | None  # (width, height) of one repeat, metres
    procedural: bool = False


@dataclass
class AssetLibrary:
    """Models by class (plus FURNITURE), textures by role, and what they owe to whom."""

    models: dict[str, list[Model]]
    textures: dict[str, list[np.ndarray]]
    texture_info: dict[str, list[TextureInfo]]
    attribution: list[dict[str, str]]
    procedural: bool  # True when anything had to be generated instead of loaded
    missing: list[str] = field(default_factory=list)  # what was missing and why, one line each
    stats: dict[str, float] = field(default_factory=dict)  # converted / from_cache / skipped counts, seconds

    def model_for(self, cls: str, kind: str = "", variant: int = 0) -> Model:
        """The `variant`-th model (wrapping) for an object of class `cls` ("" = furniture) and `kind`.

        Models of the exact kind are preferred ("door_exterior" among the doors, "desk" among the
        furniture); otherwise any model of the class, so a missing kind never breaks a scene."""
        pool = self.models.get(cls or FURNITURE) or []
        if not pool:
            raise KeyError(f"no models for class {cls!r}")
        exact = [m for m in pool if m.kind == (kind or cls)]
        chosen = exact or pool
        return chosen[variant % len(chosen)]
