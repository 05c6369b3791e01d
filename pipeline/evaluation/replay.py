"""Runs as the filter replays them: arrays from a runs table, kidnappings made by teleporting, candidates.

A kidnapping on a real log is made the way it happens to a robot: at step k the robot is carried to
the pose of a far-away step j of the same log and the log continues from there, while the odometry
carries on from where it was, unaware (it receives the next steps' odometry increments, composed onto
its own last pose). Ground truth jumps, odometry does not, `kidnapped` marks step k.

Simulated retrieval candidates (for logs without images, until the image retrieval provides them):
the true pose with retrieval-like noise plus decoys from the free space, in a seeded random order
(with 4 candidates the true one lands at each rank a quarter of the time).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError, InputError, Problem
from pipeline.io import tables
from pipeline.io.scan_rows import ScanRows, batch_rows, ipc_rows
from pipeline.runtime.motion import compose_odometry, odometry_delta, wrap_angle


@dataclass(frozen=True)
class ReplayRun:
    name: str
    odom: np.ndarray  # (T, 3)
    gt: np.ndarray | None  # (T, 3) or None
    ranges: np.ndarray | ScanRows  # (T, B) float32; ScanRows for an Arrow IPC run, read a batch at a time
    angle_min: float
    angle_increment: float
    range_max: float
    kidnapped: np.ndarray  # (T,) bool
    image_ids: tuple[str | None, ...] | None = None  # the camera frame of each step, relative to the dataset
    t: np.ndarray | None = None  # (T,) the scans' stamps, s (TUM trajectory files)

    def __len__(self) -> int:
        return len(self.odom)


def _ranges(path: Path, column) -> np.ndarray:
    """The runs table's list<float32> column as one (T, B) float32 array, read from Arrow's buffers (not through
    Python lists)."""
    arr = column.combine_chunks() if column.num_chunks != 1 else column.chunk(0)
    return batch_rows(path, arr, None)


def _arrow_run(path: Path):
    """An Arrow IPC runs table read a record batch at a time: its other columns as one table, its ranges as
    `ScanRows` that read each batch again when a replay reaches it (a 20-minute 40 Hz run is 17 M readings)."""
    import pyarrow as pa

    small, lengths, width = [], [], None
    for part in tables.read_table_batches(path, "runs"):
        col = part.column("ranges").combine_chunks()
        width = batch_rows(path, col, width, first_row=sum(lengths)).shape[1] if len(col) else width
        lengths.append(part.num_rows)
        # take() copies: a column read from an IPC batch is a slice of the batch's body, ranges included
        small.append(part.drop_columns(["ranges"]).take(np.arange(part.num_rows)))
    table = pa.concat_tables(small) if small else None
    return table, ipc_rows(path, "ranges", lengths, width or 0)


def load_run(path: Path) -> ReplayRun:
    if Path(path).suffix == ".arrow":
        table, ranges = _arrow_run(Path(path))
    else:
        table = tables.read_table(path, "runs")
        ranges = _ranges(path, table.column("ranges"))
        table = table.drop_columns(["ranges"])
    rows = 0 if table is None else table.num_rows
    if rows < 2:
        raise InputError(f"{path}: a run needs at least 2 steps", [Problem(str(path), f"{rows} rows")])

    def col(name, dtype=np.float64):
        return table.column(name).to_numpy().astype(dtype, copy=False)

    gt = None
    if all(table.column(c).null_count == 0 for c in ("gt_x", "gt_y", "gt_theta")):
        gt = np.column_stack([col("gt_x"), col("gt_y"), col("gt_theta")])
    kidnapped = (table.column("kidnapped").fill_null(False).to_numpy() if "kidnapped" in table.column_names
                 else np.zeros(rows, bool)).astype(bool)
    first = table.slice(0, 1).to_pydict()
    return ReplayRun(
        name=Path(path).stem,
        odom=np.column_stack([col("odom_x"), col("odom_y"), col("odom_theta")]),
        gt=gt,
        ranges=ranges,
        angle_min=float(first["angle_min"][0]),
        angle_increment=float(first["angle_increment"][0]),
        range_max=float(first["range_max"][0]),
        kidnapped=kidnapped,
        image_ids=tuple(table.column("image_id").to_pylist()) if "image_id" in table.column_names else None,
        t=col("t"),
    )


def teleport(run: ReplayRun, at: list[int], min_jump_m: float, seed: int) -> ReplayRun:
    """The run with kidnappings at steps `at`: each jumps to a step >= min_jump_m away (seeded)."""
    if run.gt is None:
        raise ConfigError(f"run {run.name} has no ground truth: kidnappings need it to be measured")
    rng = np.random.default_rng(seed)
    kid = sorted(set(at))
    for k in kid:
        if not 0 < k < len(run):
            raise ConfigError(f"--kidnap-at {k} is outside run {run.name}: steps 1..{len(run) - 1}")
    src, cur = [], 0
    for t in range(len(run)):
        if t in kid:
            far = np.nonzero(np.hypot(*(run.gt[:-1, :2] - run.gt[cur, :2]).T) >= min_jump_m)[0]
            if len(far) == 0:
                raise ConfigError(f"run {run.name}: no step lies {min_jump_m} m from step {t}'s pose; "
                                  "lower --kidnap-min-jump or kidnap elsewhere")
            cur = int(rng.choice(far))
        elif t > 0:
            cur = min(cur + 1, len(run) - 1)
        src.append(cur)
    src = np.array(src)
    jumps = np.zeros(len(run), bool)
    jumps[kid] = True
    # Odometry: increments of the source steps, except across a jump (the odometry did not move).
    odom = np.zeros_like(run.odom)
    odom[0] = run.odom[src[0]]
    for t in range(1, len(run)):
        if jumps[t]:
            odom[t] = odom[t - 1]
        else:
            d = odometry_delta(run.odom[src[t - 1]], run.odom[src[t]])
            odom[t] = compose_odometry(odom[t - 1], *d)
    images = None if run.image_ids is None else tuple(run.image_ids[i] for i in src)  # the camera teleports too
    return replace(run, odom=odom, gt=run.gt[src], ranges=run.ranges[src], kidnapped=jumps | run.kidnapped[src],
                   image_ids=images)


def simulated_candidates(gt_pose: np.ndarray, lmap, n: int, rng: np.random.Generator, std_xy: float = 0.5,
                         std_theta: float = np.radians(10.0)) -> np.ndarray:
    """(n, 3) candidates: the true pose with noise and n - 1 free-space decoys, in a random order."""
    true = np.asarray(gt_pose, dtype=np.float64) + rng.standard_normal(3) * [std_xy, std_xy, std_theta]
    true[2] = wrap_angle(true[2])
    cands = np.vstack([true[None], lmap.sample_free(n - 1, rng)])
    return cands[rng.permutation(n)]
