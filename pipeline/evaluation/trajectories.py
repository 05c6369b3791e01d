"""Estimates and ground truth as TUM trajectory files, and evo's APE / RPE on them.

evo, the SLAM community's trajectory tool, writes and reads the files and computes the metrics, so that a
user can check our figures with the tool they know (`evo_ape tum groundtruth.tum estimate.tum`). A
planar pose (x, y, theta) becomes a 3D one with z = 0 and the yaw as a quaternion. Estimates and ground
truth share the map frame, so APE is computed without alignment (as `evo_ape` without `-a`): a filter
in the wrong place must not be aligned onto the right one.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: RPE compares the motion over this distance travelled (evo's `--delta 1 --delta_unit m`).
RPE_DELTA_M = 1.0


def planar_trajectory(poses: np.ndarray, stamps: np.ndarray):
    """An evo PoseTrajectory3D from planar poses (N, 3) x, y, theta (radians) and stamps (N,) in seconds."""
    from evo.core.trajectory import PoseTrajectory3D

    poses = np.asarray(poses, dtype=np.float64)
    half = 0.5 * poses[:, 2]
    xyz = np.column_stack([poses[:, 0], poses[:, 1], np.zeros(len(poses))])
    wxyz = np.column_stack([np.cos(half), np.zeros(len(poses)), np.zeros(len(poses)), np.sin(half)])
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=wxyz, timestamps=np.asarray(stamps, float))


def write_tum(path: Path, poses: np.ndarray, stamps: np.ndarray) -> Path:
    """Write planar poses as a TUM file (`stamp x y z qx qy qz qw` per line) with evo's writer, atomically."""
    from evo.tools.file_interface import write_tum_trajectory_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    write_tum_trajectory_file(tmp, planar_trajectory(poses, stamps))
    os.replace(tmp, path)
    return path


def step_stamps(t: np.ndarray | None, n: int) -> np.ndarray:
    """The scans' stamps when they increase strictly (TUM needs it); else the step index as seconds."""
    if t is not None and len(t) == n and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
        return np.asarray(t, dtype=np.float64)
    return np.arange(n, dtype=np.float64)


def evo_metrics(estimate: np.ndarray, groundtruth: np.ndarray, stamps: np.ndarray,
                rpe_delta_m: float = RPE_DELTA_M) -> dict:
    """APE (translation, no alignment) and RPE (translation, m, and rotation, degrees, per `rpe_delta_m`
    travelled) computed by evo on the two trajectories; statistics as evo names them."""
    from evo.core import metrics
    from evo.core.units import Unit

    out: dict = {"ape_m": None, "rpe_m": None, "rpe_deg": None, "rpe_delta_m": rpe_delta_m}
    if not (np.isfinite(estimate).all() and np.isfinite(groundtruth).all()):
        return out  # no estimate at some steps: evo has no notion of it
    est, ref = planar_trajectory(estimate, stamps), planar_trajectory(groundtruth, stamps)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    out["ape_m"] = _stats(ape)
    travelled = float(np.sum(np.hypot(*np.diff(np.asarray(groundtruth)[:, :2], axis=0).T)))
    for key, relation in (("rpe_m", metrics.PoseRelation.translation_part),
                          ("rpe_deg", metrics.PoseRelation.rotation_angle_deg)):
        if travelled < 2 * rpe_delta_m:
            continue
        rpe = metrics.RPE(relation, delta=rpe_delta_m, delta_unit=Unit.meters, all_pairs=False)
        try:
            rpe.process_data((ref, est))
        except metrics.MetricsException:  # no pair of poses rpe_delta_m apart within evo's tolerance
            continue
        out[key] = _stats(rpe)
    return out


def _stats(metric) -> dict:
    from evo.core.metrics import StatisticsType

    return {k.value: round(float(metric.get_statistic(k)), 4)
            for k in (StatisticsType.rmse, StatisticsType.mean, StatisticsType.median, StatisticsType.max)}
