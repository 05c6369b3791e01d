"""One run at a glance: the estimated path on the map, coloured by the filter's state, with its events.

Tracking is green, relocalising orange, lost red (`OVERVIEW_COLOURS`); the ground truth, where known, is a
thin blue line. Markers: the start (white circle), the end (black square), where the filter converged (a
gold star with its step), where it lost track (red x) and where the robot was kidnapped (purple triangle).
A jump of the estimate (a relocalisation across the map) is a thin dotted grey line, not a coloured one.
When the map is much larger than the path, the axes are zoomed to the path with a margin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.evaluation.plots import map_axes, save_figure

OVERVIEW_COLOURS = {"tracking": "#2ca02c", "relocalising": "#ff7f0e", "lost": "#d62728"}
GT_COLOUR = "#1f77b4"
CONVERGED_COLOUR = "#ffd700"
KIDNAPPED_COLOUR = "#9467bd"
FIG_WIDTH_IN = 8.0
#: Step dots drawn at most (evenly spaced, every change of state kept): a figure shows no more.
SCATTER_POINTS = 4000


def _view(occ_map, xy: np.ndarray) -> tuple[float, float, float, float] | None:
    """(x0, x1, y0, y1) around the points with a margin, or None to show the whole map (the path covers much
    of it, or there is no path)."""
    if not len(xy):
        return None
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = float(max(hi[0] - lo[0], hi[1] - lo[1], 20 * occ_map.resolution, 1.0))
    margin = 0.15 * span + 0.5
    x0, x1 = lo[0] - margin, hi[0] + margin
    y0, y1 = lo[1] - margin, hi[1] + margin
    map_w, map_h = occ_map.width * occ_map.resolution, occ_map.height * occ_map.resolution
    if (x1 - x0) * 1.5 >= map_w and (y1 - y0) * 1.5 >= map_h:
        return None
    return float(x0), float(x1), float(y0), float(y1)


def _valid(steps, n: int) -> list[int]:
    return sorted({int(k) for k in steps if 0 <= int(k) < n})


def overview_figure(path: Path, occ_map, pose: np.ndarray, states: list[str], *, gt: np.ndarray | None = None,
                    converged_step: int | None = None, lost_steps=(), kidnapped_steps=(), title: str = "") -> Path:
    """A PNG of one run on the map: `pose` (T, 3) the estimates, `states` (T,) the filter's states, `gt` (T, 3)
    the ground truth if known; steps (indices into pose) of the convergence, of losing track, of kidnappings."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    pose = np.asarray(pose, dtype=np.float64).reshape(-1, 3)
    n = len(pose)
    states = [str(s) for s in states]
    if len(states) != n:
        raise ValueError(f"{len(states)} states for {n} poses")
    gt = None if gt is None else np.asarray(gt, dtype=np.float64).reshape(-1, 3)
    fig, ax = map_axes(occ_map)
    xy = pose[:, :2]
    handles = [Line2D([], [], color=c, lw=2.2, label=s) for s, c in OVERVIEW_COLOURS.items()]
    if gt is not None and len(gt):
        ax.plot(gt[:, 0], gt[:, 1], color=GT_COLOUR, lw=1.0, alpha=0.8, zorder=2)
        handles.append(Line2D([], [], color=GT_COLOUR, lw=1.0, label="ground truth"))
    colours = np.array([OVERVIEW_COLOURS.get(s, "0.5") for s in states], dtype=object)
    if n > 1:
        length = np.linalg.norm(xy[1:] - xy[:-1], axis=1)
        jump = length > max(1.0, 10 * float(np.median(length)))
        # One polyline per stretch of one state without a jump (not a segment per step: a 20-minute run at
        # 40 Hz is 48 000 steps); segment k (step k to k + 1) takes the colour of step k + 1.
        new = np.r_[True, (colours[2:] != colours[1:-1]) | jump[1:] | jump[:-1]]
        lines, line_colours = [], []
        for a, e in zip(np.flatnonzero(new), [*np.flatnonzero(new)[1:], n - 1], strict=True):
            if not jump[a]:
                lines.append(xy[a: e + 1])
                line_colours.append(colours[a + 1])
        ax.add_collection(LineCollection(lines, colors=line_colours, linewidths=2.2, zorder=3, capstyle="round",
                                         joinstyle="round"))
        if jump.any():
            seg = np.stack([xy[:-1], xy[1:]], axis=1)
            ax.add_collection(LineCollection(seg[jump], colors="0.45", linewidths=0.8, linestyles=":", zorder=3))
            handles.append(Line2D([], [], color="0.45", lw=0.8, ls=":", label="jump of the estimate"))
    if n:
        shown = np.unique(np.r_[np.arange(0, n, max(1, n // SCATTER_POINTS)), np.flatnonzero(colours[1:] !=
                                                                                             colours[:-1]) + 1])
        ax.scatter(xy[shown, 0], xy[shown, 1], s=5, c=list(colours[shown]), zorder=4, linewidths=0)
    if n:
        ax.plot(*xy[0], marker="o", ms=9, mfc="white", mec="black", mew=1.5, ls="", zorder=6)
        ax.plot(*xy[-1], marker="s", ms=8, mfc="black", mec="black", ls="", zorder=6)
        handles += [Line2D([], [], marker="o", ms=8, mfc="white", mec="black", ls="", label="start"),
                    Line2D([], [], marker="s", ms=7, mfc="black", mec="black", ls="", label="end")]
    if converged_step is not None and 0 <= int(converged_step) < n:
        k = int(converged_step)
        ax.plot(*xy[k], marker="*", ms=18, mfc=CONVERGED_COLOUR, mec="black", mew=1.0, ls="", zorder=7)
        ax.annotate(f"converged (step {k})", xy[k], xytext=(8, 8), textcoords="offset points", fontsize=8,
                    zorder=8, bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "0.5", "alpha": 0.85})
        handles.append(Line2D([], [], marker="*", ms=12, mfc=CONVERGED_COLOUR, mec="black", ls="", label="converged"))
    lost = _valid(lost_steps, n)
    if lost:
        ax.scatter(xy[lost, 0], xy[lost, 1], marker="x", s=70, color=OVERVIEW_COLOURS["lost"], linewidths=2.2,
                   zorder=7)
        handles.append(Line2D([], [], marker="x", ms=8, mew=2, color=OVERVIEW_COLOURS["lost"], ls="",
                              label="lost track"))
    kidnapped = _valid(kidnapped_steps, n)
    if kidnapped:
        where = gt if gt is not None and len(gt) == n else pose
        ax.scatter(where[kidnapped, 0], where[kidnapped, 1], marker="v", s=70, color=KIDNAPPED_COLOUR,
                   edgecolors="black", linewidths=0.8, zorder=7)
        handles.append(Line2D([], [], marker="v", ms=8, mfc=KIDNAPPED_COLOUR, mec="black", ls="",
                              label="kidnapped"))
    points = xy if gt is None else np.vstack([xy, gt[:, :2]])
    view = _view(occ_map, points[np.all(np.isfinite(points), axis=1)])
    if view is not None:
        ax.set_xlim(view[0], view[1])
        ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal")
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    aspect = abs(y1 - y0) / max(abs(x1 - x0), 1e-9)
    fig.set_size_inches(FIG_WIDTH_IN, float(np.clip(FIG_WIDTH_IN * aspect, 3.0, 12.0)))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)  # beside: hides nothing
    return save_figure(fig, Path(path))
