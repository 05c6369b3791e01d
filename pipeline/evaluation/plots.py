"""Figures of a localization replay: error and particles per step, error CDF, the trajectory on the map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.atomic import atomic_file

STATE_COLOURS = {"tracking": "#2a9d8f", "relocalising": "#e9c46a", "lost": "#e76f51"}


def save_figure(fig, path: Path) -> Path:
    with atomic_file(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def replay_figure(path: Path, title: str, errors: np.ndarray, states: list[str], particles: np.ndarray,
                  kidnaps: list[int]) -> Path:
    """Error (log scale, coloured by filter state) and particle count against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    steps = np.arange(len(errors))
    ax1.plot(steps, np.maximum(errors, 1e-3), color="0.6", lw=0.8)
    for state, colour in STATE_COLOURS.items():
        sel = np.array([s == state for s in states])
        ax1.scatter(steps[sel], np.maximum(errors[sel], 1e-3), s=6, color=colour, label=state)
    for k in kidnaps:
        ax1.axvline(k, color="k", ls="--", lw=0.8)
        ax2.axvline(k, color="k", ls="--", lw=0.8)
    ax1.set_yscale("log")
    ax1.set_ylabel("position error (m)")
    ax1.axhline(0.5, color="0.3", lw=0.6, ls=":")
    ax1.legend(loc="upper right", fontsize=8, markerscale=2)
    ax1.set_title(title)
    ax2.plot(steps, particles, color="#264653")
    ax2.set_ylabel("particles")
    ax2.set_xlabel("step (dashed: kidnapping)")
    return save_figure(fig, path)


def error_cdf_figure(path: Path, curves: dict[str, np.ndarray]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, errs in curves.items():
        e = np.sort(np.asarray(errs))
        if len(e):
            ax.plot(e, np.arange(1, len(e) + 1) / len(e), label=name)
    ax.set_xscale("log")
    ax.set_xlabel("position error (m), converged steps")
    ax.set_ylabel("share of steps")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def map_axes(occ_map):
    """A figure with the occupancy map drawn in map coordinates (free white, occupied black, unknown grey)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = np.asarray(occ_map.grid)
    img = np.full(grid.shape, 0.75)
    img[grid == 0] = 1.0
    img[grid >= 65] = 0.0
    h, w = grid.shape
    extent = (occ_map.origin_x, occ_map.origin_x + w * occ_map.resolution,
              occ_map.origin_y, occ_map.origin_y + h * occ_map.resolution)
    fig, ax = plt.subplots(figsize=(8, 8 * h / max(w, 1)))
    ax.imshow(img, cmap="gray", origin="lower", extent=extent, vmin=0, vmax=1, interpolation="nearest")
    return fig, ax


def trajectory_figure(path: Path, occ_map, gt: np.ndarray | None, est: np.ndarray, particles: np.ndarray,
                      title: str) -> Path:
    """The map, ground truth and estimated trajectories, and the final particle set."""
    fig, ax = map_axes(occ_map)
    ax.scatter(particles[:, 0], particles[:, 1], s=1, color="#e76f51", alpha=0.4, label="particles (final)")
    if gt is not None:
        ax.plot(gt[:, 0], gt[:, 1], color="#2a9d8f", lw=1.2, label="ground truth")
    ax.plot(est[:, 0], est[:, 1], color="#264653", lw=0.8, ls="--", label="estimate")
    ax.set_aspect("equal")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8, markerscale=4)
    return save_figure(fig, path)
