"""PNG preview of a built map with the trajectory it was built from, for a human to eyeball."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from pipeline.io.atomic import write_bytes_atomic
from pipeline.io.map_yaml import OccupancyMap

_GREY = {"unknown": 0.78, "free": 1.0, "occupied": 0.0}


def _scale_bar_length(span_m: float) -> float:
    """A round length (1, 2, 5 x 10^k m) about a fifth of the map's width."""
    target = max(span_m / 5.0, 1e-3)
    base = 10 ** np.floor(np.log10(target))
    return float(max(m * base for m in (1, 2, 5) if m * base <= target))


def write_preview(
    path: Path,
    occ_map: OccupancyMap,
    map_from_base: np.ndarray,
    title: str,
    *,
    max_inches: float = 10.0,
    dpi: int = 120,
) -> Path:
    """Map in grey (black occupied, white free, grey unknown), trajectory coloured by step, start/end marked.

    Rendered in memory with the Agg backend and written atomically; no date metadata, so it is
    byte-identical for the same inputs and matplotlib version.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    grid = occ_map.grid
    image = np.full(grid.shape, _GREY["unknown"])
    image[occ_map.free] = _GREY["free"]
    image[occ_map.occupied] = _GREY["occupied"]
    w_m, h_m = occ_map.width * occ_map.resolution, occ_map.height * occ_map.resolution
    extent = (occ_map.origin_x, occ_map.origin_x + w_m, occ_map.origin_y, occ_map.origin_y + h_m)

    scale = max_inches / max(w_m, h_m)
    fig = Figure(figsize=(max(w_m * scale, 4.0) + 1.5, max(h_m * scale, 3.0) + 1.0), dpi=dpi)
    ax = fig.add_subplot()
    ax.imshow(image, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent, interpolation="nearest")
    xy = np.asarray(map_from_base, dtype=np.float64)[:, :2]
    if len(xy) > 1:
        segments = np.stack([xy[:-1], xy[1:]], axis=1)
        lines = LineCollection(segments, cmap="viridis", linewidths=1.2, alpha=0.9)
        lines.set_array(np.arange(len(segments), dtype=np.float64))
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, fraction=0.035, pad=0.02, label="scan index")
    if len(xy):
        ax.plot(*xy[0], "o", color="tab:green", markersize=8, markeredgecolor="k", label="start")
        ax.plot(*xy[-1], "s", color="tab:red", markersize=8, markeredgecolor="k", label="end")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    bar = _scale_bar_length(w_m)
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData,
            bar,
            f"{bar:g} m",
            loc="lower left",
            pad=0.5,
            sep=4,
            frameon=True,
            size_vertical=bar / 40,
        )
    )
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (map frame)")
    ax.set_ylabel("y [m]")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return write_bytes_atomic(Path(path), buf.getvalue())
