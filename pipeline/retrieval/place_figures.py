"""The picture of a place set's misses: each query whose Top-1 is wrong, that Top-1, and a true match."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.retrieval.place_set import PlaceSet


def misses_figure(path: Path, ps: PlaceSet, ranked: np.ndarray, *, title: str, rows: int = 12) -> dict:
    """A PNG of up to `rows` wrong queries (evenly spread over the set): query | wrong Top-1 (red) | the
    best-ranked true match (green, with its rank). Returns how many queries were wrong and shown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.evaluation.plots import save_figure
    from pipeline.io.images import open_image

    has = ps.positive.any(axis=1)
    wrong = [i for i in range(len(ps.queries)) if has[i] and not ps.positive[i, ranked[i, 0]]]
    picks = [wrong[k] for k in np.unique(np.linspace(0, len(wrong) - 1, min(rows, len(wrong))).round().astype(int))] \
        if wrong else []
    n = max(len(picks), 1)
    fig, axes = plt.subplots(n, 3, figsize=(9, 2.4 * n), squeeze=False)
    for row, i in zip(axes, picks, strict=False):
        order = ranked[i]
        hit = int(np.flatnonzero(ps.positive[i, order])[0])  # rank of the first true match
        entries = [(ps.queries[i], f"query {ps.queries[i].name}", "black"),
                   (ps.database[order[0]], f"Top-1 {ps.database[order[0]].name} (wrong)", "#e63946"),
                   (ps.database[order[hit]], f"true match {ps.database[order[hit]].name} at rank {hit + 1}",
                    "#2a9d8f")]
        for ax, (image, label, colour) in zip(row, entries, strict=True):
            ax.imshow(open_image(image))
            ax.set_title(label, fontsize=7)
            ax.set_xticks([])
            ax.set_yticks([])
            for spine in ax.spines.values():
                spine.set_edgecolor(colour)
                spine.set_linewidth(1 if colour == "black" else 4)
    if not picks:
        axes[0][1].text(0.5, 0.5, "every Top-1 is a true match", ha="center", va="center")
        for ax in axes[0]:
            ax.axis("off")
    fig.suptitle(f"{title}: {len(wrong)} of {int(has.sum())} queries with a wrong Top-1"
                 + (f" ({len(picks)} shown)" if len(picks) < len(wrong) else ""), fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.4 / (2.4 * n)))  # room for the title above the first row
    save_figure(fig, path)
    return {"queries": int(has.sum()), "wrong": len(wrong), "shown": len(picks)}
