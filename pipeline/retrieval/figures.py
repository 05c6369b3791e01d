"""Figures of retrieval: recall@N curves per variant, and queries with their Top-4 (like seed 000 Figure 7)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def recall_figure(path: Path, rankings: dict[str, np.ndarray], query_poses: np.ndarray, db_poses: np.ndarray,
                  threshold: tuple[float, float]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.evaluation.plots import save_figure
    from pipeline.retrieval.metrics import positives, relevance

    pos = positives(query_poses, db_poses, *threshold)
    has = pos.any(axis=1)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for name, ranked in rankings.items():
        rel = relevance(ranked, pos)[has]
        ns = np.arange(1, ranked.shape[1] + 1)
        curve = [rel[:, :n].any(axis=1).mean() for n in ns]
        ax.plot(ns, curve, ls="-" if "rpa" in name else "--", label=name)
    ax.set_xscale("log")
    ax.set_xlabel("N")
    ax.set_ylabel("recall@N")
    ax.set_ylim(0, 1.01)
    ax.grid(alpha=0.3)
    ax.set_title(f"recall@N, positives within {threshold[0]:g} m and {threshold[1]:g} deg ({int(has.sum())} queries)")
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def examples_figure(path: Path, database: tuple, query: tuple, ranked: np.ndarray, threshold: tuple[float, float],
                    *, title: str, rows: int = 6) -> Path:
    """Rows of (query, Top-4): a green border marks a positive, red a wrong place.

    `database` and `query` are (image root, extraction, image indices) each; they may be two sites."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.evaluation.plots import save_figure
    from pipeline.io.images import open_image
    from pipeline.retrieval.metrics import positives

    db_root, ex, db = database
    q_root, qx, queries = query
    picks = np.unique(np.linspace(0, len(queries) - 1, min(rows, len(queries))).round().astype(int))
    fig, axes = plt.subplots(len(picks), 5, figsize=(13, 2.3 * len(picks)), squeeze=False)
    for row, k in zip(axes, picks, strict=True):
        q = queries[k]
        pos = positives(qx.poses[[q]], ex.poses[db[ranked[k][:4]]], *threshold)[0]
        entries = [(q_root, qx, q, "query", None)] + [
            (db_root, ex, db[j], f"#{n + 1}", bool(pos[n])) for n, j in enumerate(ranked[k][:4])]
        for ax, (root, source, i, label, ok) in zip(row, entries, strict=False):
            ax.set_xticks([])
            ax.set_yticks([])
            if (root / source.image_ids[i]).is_file():
                ax.imshow(open_image(root / source.image_ids[i]))
            x, y, th = source.poses[i]
            ax.set_title(f"{label}  ({x:.1f}, {y:.1f}, {np.degrees(th):.0f} deg)", fontsize=7)
            colour = "black" if ok is None else ("#2a9d8f" if ok else "#e63946")
            for spine in ax.spines.values():
                spine.set_edgecolor(colour)
                spine.set_linewidth(4 if ok is not None else 1)
    fig.suptitle(f"{title}: query, then Top-4 (green: within {threshold[0]:g} m and {threshold[1]:g} deg)",
                 fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)
