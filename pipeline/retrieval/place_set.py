"""A place set: database and query images with the ground truth of which show the same place.

Read from `place_set.yaml` (docs/data-formats.md#place-sets) in one of three layouts: two folders
(`database`, `queries`), one folder split by position (`images` with `database: 1-40`), or posed images
(`poses`: a CSV of image, x, y, theta_deg and role). Ground truth is a rule (`aligned`: query i shows
database i-k..i+k; `distance_m` / `angle_deg` between poses), a match matrix (an image such as
RTAB-Map's `samples_GT.bmp`, a plain `.npy` or a CSV of 0/1), or a CSV of matching name pairs. Images
are taken in natural name order (`2.jpg` before `10.jpg`). Nothing is unpickled: a `.npy` of Python
objects (VPR-Bench's `ground_truth_new.npy`) is refused with the rule to write instead.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pipeline.errors import InputError, Problem
from pipeline.io.site import validation_problems
from pipeline.io.text_files import read_text

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp")
FILE_NAME = "place_set.yaml"


class Positives(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    aligned: int | None = Field(None, ge=0)
    matrix: str | None = None
    pairs: str | None = None
    distance_m: float | None = Field(None, gt=0)
    angle_deg: float | None = Field(None, gt=0, le=180)

    @model_validator(mode="after")
    def _one_rule(self):
        rules = [k for k in ("aligned", "matrix", "pairs", "distance_m") if getattr(self, k) is not None]
        if len(rules) != 1:
            raise ValueError(f"give exactly one of aligned, matrix, pairs or distance_m (got {rules or 'none'})")
        if self.angle_deg is not None and self.distance_m is None:
            raise ValueError("angle_deg goes with distance_m")
        return self


class PlaceSetFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str | None = None
    root: str | None = None  # where the paths below start (default: the yaml's folder); relative to the yaml
    images: str | None = None
    database: str | None = None
    queries: str | None = None
    poses: str | None = None
    positives: Positives


@dataclass
class PlaceSet:
    name: str
    root: Path
    database: list[Path]
    queries: list[Path]
    positive: np.ndarray  # (Q, D) bool
    database_poses: np.ndarray | None = None  # (D, 3) x, y, theta (radians) when the set is posed
    query_poses: np.ndarray | None = None

    @property
    def queries_with_positives(self) -> int:
        return int(self.positive.any(axis=1).sum())


def natural_key(name: str) -> list:
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def _fail(where, message: str, fix: str = "") -> InputError:
    return InputError(f"{where}: not a usable place set", [Problem(str(where), message, fix=fix)])


def images_in(folder: Path, exclude: set[Path] = frozenset()) -> list[Path]:
    """The images of a folder in natural name order; `exclude`: files that are not views (a match matrix
    saved as an image beside them)."""
    if not folder.is_dir():
        raise _fail(folder, "no such folder", "name a folder of images relative to place_set.yaml")
    skip = {p.resolve() for p in exclude}
    found = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                    and p.resolve() not in skip), key=lambda p: natural_key(p.name))
    if not found:
        raise _fail(folder, f"holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return found


def positions(text: str, n: int, where: str) -> np.ndarray:
    """'1-40, 45, 50-52' (1-based, inclusive) as 0-based indices into n images."""
    out: list[int] = []
    for part in str(text).replace(" ", "").split(","):
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if m is None:
            raise _fail(where, f"'{part}' is not a position or a range such as 1-40",
                        "positions count from 1 in natural name order")
        a, b = int(m.group(1)), int(m.group(2) or m.group(1))
        if not 1 <= a <= b <= n:
            raise _fail(where, f"{part} is outside 1-{n} (the folder holds {n} images)")
        out.extend(range(a - 1, b))
    if len(set(out)) != len(out):
        raise _fail(where, "an image is named twice")
    return np.asarray(out, dtype=np.int64)


def read_matrix(path: Path) -> np.ndarray:
    """A 0/1 match matrix from an image (nonzero = match), a plain .npy, or a CSV of numbers."""
    if not path.is_file():
        raise _fail(path, "no such file")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            m = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise _fail(path, f"cannot be read without unpickling ({exc})",
                        "write the ground truth as a numeric (Q, D) matrix, a CSV of query,database pairs, or a "
                        "rule (for VPR-Bench's traversals: positives: {aligned: K})") from None
    elif suffix == ".csv":
        try:
            m = np.loadtxt(path, delimiter=",", ndmin=2)
        except ValueError as exc:
            raise _fail(path, f"not a CSV of numbers: {exc}") from None
    else:
        from pipeline.io.images import ImageError, open_image

        try:
            m = np.asarray(open_image(path, rgb=False).convert("L"))
        except ImageError as exc:
            raise _fail(path, exc.message) from None
    if m.ndim != 2 or m.dtype.kind not in "biuf":
        raise _fail(path, f"a {m.dtype} array of shape {m.shape}, not a 2-D numeric matrix")
    return np.asarray(m) != 0


def _pairs(path: Path, database: list[Path], queries: list[Path]) -> np.ndarray:
    index_q = {p.name: i for i, p in enumerate(queries)}
    index_d = {p.name: j for j, p in enumerate(database)}
    out = np.zeros((len(queries), len(database)), bool)
    with open(path, newline="", encoding="utf-8") as fh:
        for row_no, row in enumerate(csv.DictReader(fh), start=2):
            if set(row) != {"query", "database"}:
                raise _fail(f"{path} line 1", f"columns {sorted(row)}, expected query,database")
            q, d = index_q.get(row["query"]), index_d.get(row["database"])
            if q is None or d is None:
                missing = row["query"] if q is None else row["database"]
                raise _fail(f"{path} line {row_no}", f"no {'query' if q is None else 'database'} image {missing!r}")
            out[q, d] = True
    return out


def _poses(path: Path, root: Path) -> tuple[list[Path], np.ndarray, list[str]]:
    names, poses, roles = [], [], []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        need = {"image", "x", "y", "theta_deg", "role"}
        if reader.fieldnames is None or not need <= set(reader.fieldnames):
            raise _fail(f"{path} line 1", f"columns {reader.fieldnames}, expected image,x,y,theta_deg,role")
        for row_no, row in enumerate(reader, start=2):
            try:
                pose = [float(row["x"]), float(row["y"]), math.radians(float(row["theta_deg"]))]
            except ValueError:
                raise _fail(f"{path} line {row_no}", "x, y and theta_deg must be numbers") from None
            if not all(map(math.isfinite, pose)):
                raise _fail(f"{path} line {row_no}", "x, y and theta_deg must be finite")
            if row["role"] not in ("database", "query"):
                raise _fail(f"{path} line {row_no}", f"role {row['role']!r} is neither database nor query")
            image = root / row["image"]
            if not image.is_file():
                raise _fail(f"{path} line {row_no}", f"no image {row['image']} under {root}")
            names.append(image)
            poses.append(pose)
            roles.append(row["role"])
    if len({p.resolve() for p in names}) != len(names):
        raise _fail(path, "an image is listed twice")
    return names, np.asarray(poses, dtype=np.float64).reshape(-1, 3), roles


def read_place_set(path: Path) -> PlaceSet:
    """The place set of `path` (a place_set.yaml, or the folder holding one); InputError naming the problem."""
    path = Path(path)
    yaml_path = path / FILE_NAME if path.is_dir() else path
    if not yaml_path.is_file():
        raise _fail(yaml_path, "no such file", "write a place_set.yaml (docs/data-formats.md#place-sets)")
    try:
        raw = yaml.safe_load(read_text(yaml_path, what="place set"))
        spec = PlaceSetFile.model_validate(raw or {})
    except yaml.YAMLError as exc:
        raise InputError(f"{yaml_path}: not valid YAML", [Problem(str(yaml_path), str(exc))]) from None
    except ValidationError as err:
        raise InputError(f"{yaml_path}: invalid place set", validation_problems(yaml_path, err)) from None
    root, rule = yaml_path.parent / (spec.root or "."), spec.positives
    if not root.is_dir():
        raise _fail(yaml_path, f"root {spec.root!r} is not a folder ({root})")
    not_views = {root / rule.matrix} if rule.matrix else set()
    db_poses = q_poses = None
    if spec.poses is not None:
        if rule.distance_m is None:
            raise _fail(yaml_path, "a posed set takes positives: {distance_m: D, angle_deg: A}")
        names, poses, roles = _poses(root / spec.poses, root / (spec.images or "."))
        is_db = np.array([r == "database" for r in roles])
        database = [n for n, d in zip(names, is_db, strict=True) if d]
        queries = [n for n, d in zip(names, is_db, strict=True) if not d]
        db_poses, q_poses = poses[is_db], poses[~is_db]
        from pipeline.retrieval.metrics import positives as by_pose

        positive = by_pose(q_poses, db_poses, rule.distance_m, rule.angle_deg or 180.0) if queries and database \
            else np.zeros((len(queries), len(database)), bool)
    elif spec.images is not None:
        if spec.database is None or spec.queries is None:
            raise _fail(yaml_path, "with images: give database and queries as positions, e.g. database: 1-40")
        every = images_in(root / spec.images, not_views)
        db_idx = positions(spec.database, len(every), f"{yaml_path} database")
        q_idx = positions(spec.queries, len(every), f"{yaml_path} queries")
        if set(db_idx) & set(q_idx):
            raise _fail(yaml_path, "an image is both in the database and a query")
        database, queries = [every[i] for i in db_idx], [every[i] for i in q_idx]
        positive = _rule(rule, root, database, queries, yaml_path, every=(every, db_idx, q_idx))
    else:
        if spec.database is None or spec.queries is None:
            raise _fail(yaml_path, "give database and queries folders, images with positions, or poses")
        database, queries = images_in(root / spec.database, not_views), images_in(root / spec.queries, not_views)
        positive = _rule(rule, root, database, queries, yaml_path)
    if not database or not queries:
        raise _fail(yaml_path, f"{len(database)} database images and {len(queries)} queries: both are needed")
    ps = PlaceSet(spec.name or root.name, root, database, queries, positive, db_poses, q_poses)
    if ps.queries_with_positives == 0:
        raise _fail(yaml_path, "no query has a positive", "check the ground truth and the split")
    return ps


def _rule(rule: Positives, root: Path, database: list[Path], queries: list[Path], where: Path,
          every=None) -> np.ndarray:
    q, d = len(queries), len(database)
    if rule.distance_m is not None:
        raise _fail(where, "distance_m needs poses: give poses: poses.csv")
    if rule.aligned is not None:
        i, j = np.arange(q)[:, None], np.arange(d)[None, :]
        return np.abs(i - j) <= rule.aligned
    if rule.pairs is not None:
        return _pairs(root / rule.pairs, database, queries)
    m = read_matrix(root / rule.matrix)
    if m.shape == (q, d):
        return m
    if every is not None and m.shape == (len(every[0]),) * 2:  # over all images: symmetrised, then cut
        m = m | m.T
        return m[np.ix_(every[2], every[1])]
    expected = f"({q}, {d})" + (f" or ({len(every[0])}, {len(every[0])}) over all images" if every else "")
    raise _fail(root / rule.matrix, f"shape {m.shape}, expected {expected} (rows queries, columns database)")


def site_place_set(ingested: Path, *, run_stride: int = 10, distance_m: float = 2.0,
                   angle_deg: float = 30.0) -> PlaceSet:
    """The place set of an ingested site (`siteloc ingest`): database = the train stops' views, queries =
    the test stops' views and every `run_stride`-th frame of the query runs, positives within `distance_m`
    and `angle_deg` (the split `evaluate-retrieval` measures)."""
    from pipeline.retrieval.extract import site_images
    from pipeline.retrieval.metrics import positives

    ingested = Path(ingested)
    records = site_images(ingested, include_runs=True)
    runs = [r for r in records if r.split.startswith("run:")]
    database = [r for r in records if r.split == "train"]
    queries = [r for r in records if r.split == "test"] + runs[::run_stride]
    if not database or not queries:
        raise _fail(ingested, f"{len(database)} train-stop views and {len(queries)} test views or run frames",
                    "ingest a site with a train / test split (ingest.split) and query runs")

    def pose(rs):
        return np.array([[r.x, r.y, r.theta] for r in rs], dtype=np.float64)

    db_poses, q_poses = pose(database), pose(queries)
    return PlaceSet(ingested.name, ingested, [ingested / r.image_id for r in database],
                    [ingested / r.image_id for r in queries], positives(q_poses, db_poses, distance_m, angle_deg),
                    db_poses, q_poses)


def load_places(path: Path, *, run_stride: int = 10) -> PlaceSet:
    """A place set (place_set.yaml) or an ingested site (a folder with images.parquet)."""
    path = Path(path)
    if path.is_dir() and (path / "images.parquet").is_file() and not (path / FILE_NAME).is_file():
        return site_place_set(path, run_stride=run_stride)
    return read_place_set(path)


def load_tensor(path: Path, max_side: int | None, scale: float = 1.0):
    """(3, H, W) float tensor in [0, 1] of an image, its longest side at most max_side, times `scale`
    (`detection.inference.load_image`'s conversion, after the resize)."""
    from torchvision.transforms.functional import pil_to_tensor

    from pipeline.io.images import open_image

    im = open_image(path)
    w, h = im.size
    f = scale * (min(1.0, max_side / max(w, h)) if max_side else 1.0)
    if f != 1.0:
        from PIL import Image

        im = im.resize((max(1, round(w * f)), max(1, round(h * f))), Image.BILINEAR)
    return pil_to_tensor(im).float() / 255.0
