"""The figures of the localization report, numbered as in seed 000 (Figures 8-12)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from pipeline.evaluation.experiments import METHODS
from pipeline.evaluation.jobs import Replay
from pipeline.evaluation.plots import map_axes, save_figure

COLOURS = {"proposed": "#264653", "sequence": "#6a4c93", "image_reloc": "#43aa8b",
           "amcl": "#e76f51", "mcl": "#f4a261", "mixture": "#2a9d8f", "image_only": "#8d99ae"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _cdf(ax, errors: np.ndarray, label: str, colour: str) -> None:
    e = np.sort(np.asarray(errors))
    ax.plot(np.maximum(e, 1e-3), np.arange(1, len(e) + 1) / len(e), label=label, color=colour)


def figure8_error_cdf(path: Path, results: dict[str, list[Replay]], paper_p90: dict[str, float]) -> Path:
    """Error CDF of global localization (start to first kidnapping, every replay), with and without retrieval
    seeding; p90 marked."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for m, paper in (("proposed", paper_p90["with"]), ("amcl", paper_p90["without"])):
        errs = np.concatenate([r.global_errors for r in results[m]])
        p90 = float(np.percentile(errs, 90))
        _cdf(ax, errs, f"{'with' if m == 'proposed' else 'without'} image retrieval (p90 {p90:.2f} m; "
             f"paper {paper:g} m)", COLOURS[m])
        ax.axvline(max(p90, 1e-3), color=COLOURS[m], ls=":", lw=0.9)
    ax.axhline(0.9, color="0.4", lw=0.6, ls="--")
    ax.set_xscale("log")
    ax.set_xlabel("position error (m), every step from the start to the first kidnapping")
    ax.set_ylabel("share of steps")
    ax.set_title("Figure 8: global localization error with and without image retrieval")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    return save_figure(fig, path)


def _mean_curve(replays: list[Replay], key: str) -> np.ndarray:
    n = min(len(getattr(r, key)) for r in replays)
    return np.mean([getattr(r, key)[:n] for r in replays], axis=0)


def figure9_particles(path: Path, results: dict[str, list[Replay]]) -> Path:
    """Particle count per step (mean over replays) and error CDF, fixed-count MCL vs KLD-AMCL."""
    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for m in ("mcl", "amcl"):
        ax1.plot(_mean_curve(results[m], "particles"), color=COLOURS[m], label=METHODS[m])
        _cdf(ax2, np.concatenate([r.global_errors for r in results[m]]), METHODS[m], COLOURS[m])
    ax1.set_xlabel("step")
    ax1.set_ylabel("particles (mean over replays)")
    ax1.set_title("Figure 9a: particle count")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax2.set_xscale("log")
    ax2.set_xlabel("position error (m), start to first kidnapping")
    ax2.set_ylabel("share of steps")
    ax2.set_title("Figure 9b: error CDF")
    ax2.legend(fontsize=8, loc="lower right")
    ax2.grid(alpha=0.3)
    return save_figure(fig, path)


def figure10_error_vs_step(path: Path, results: dict[str, list[Replay]]) -> Path:
    """Error per step on each run (trial 0): mixture MCL, image-only localization, the proposed method."""
    plt = _plt()
    runs = [r.run for r in results["proposed"] if r.trial == 0]
    cols = min(2, len(runs))
    rows = int(np.ceil(len(runs) / cols))
    # constrained layout makes room for each panel's title below the step axis of the panel above
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 3.2 * rows), squeeze=False, sharey=True,
                             layout="constrained")
    for ax, name in zip(axes.ravel(), runs, strict=False):
        for m in ("mixture", "image_only", "proposed"):
            r = next(x for x in results[m] if x.run == name and x.trial == 0)
            ax.plot(np.maximum(r.errors, 1e-3), color=COLOURS[m], lw=1.0 if m != "image_only" else 0.6,
                    label=METHODS[m])
            for k in r.kidnaps:
                ax.axvline(k, color="k", ls="--", lw=0.6)
        ax.set_yscale("log")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("step (dashed: kidnapping)")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(runs):]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("position error (m)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle("Figure 10: error per step, mixture MCL vs image-only vs proposed")
    return save_figure(fig, path)


def figure11_kidnap_map(path: Path, occ_map, replay: Replay) -> Path:
    """One kidnapped run on the map: A start, B just before the kidnapping, C where it was carried, D the end."""
    fig, ax = map_axes(occ_map)
    cuts = [0, *replay.kidnaps, len(replay.gt)]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        ax.plot(replay.gt[a:b, 0], replay.gt[a:b, 1], color="#2a9d8f", lw=1.6)
        ax.plot(replay.pose[a:b, 0], replay.pose[a:b, 1], color=COLOURS["proposed"], lw=0.8, ls="--")
    ax.plot([], [], color="#2a9d8f", label="ground truth")
    ax.plot([], [], color=COLOURS["proposed"], ls="--", label="estimate (proposed)")
    if replay.kidnaps:
        k = replay.kidnaps[0]
        marks = {"A": replay.gt[0], "B": replay.gt[k - 1], "C": replay.gt[k],
                 "D": replay.gt[(replay.kidnaps[1] - 1) if len(replay.kidnaps) > 1 else -1]}
        ax.annotate("", xy=marks["C"][:2], xytext=marks["B"][:2],
                    arrowprops={"arrowstyle": "->", "color": "#e76f51", "lw": 1.2, "ls": ":"})
        for label, p in marks.items():
            ax.scatter([p[0]], [p[1]], s=30, color="#e76f51", zorder=5)
            ax.annotate(label, p[:2], xytext=(4, 4), textcoords="offset points", fontsize=11, weight="bold")
    ax.set_aspect("equal")
    ax.set_title(f"Figure 11: {replay.run}, kidnapped B -> C (dotted)")
    ax.legend(loc="upper right", fontsize=8)
    return save_figure(fig, path)


def recovery_curves(replays: list[Replay], before: int, after: int) -> np.ndarray:
    """(K, before + after) errors around every kidnapping (NaN past the run's end or the next kidnapping)."""
    rows = []
    for r in replays:
        for i, k in enumerate(r.kidnaps):
            stop = r.kidnaps[i + 1] if i + 1 < len(r.kidnaps) else len(r.errors)
            row = np.full(before + after, np.nan)
            lo = max(k - before, 0)
            seg = r.errors[lo:min(k + after, stop)]
            row[lo - (k - before): lo - (k - before) + len(seg)] = seg
            rows.append(row)
    return np.array(rows).reshape(-1, before + after)


def figure12_kidnap_recovery(path: Path, results: dict[str, list[Replay]], before: int = 5,
                             after: int = 60) -> Path:
    """Error around each kidnapping (faint) and the median over kidnappings (bold), for each method: the
    paper's MCL (here KLD-AMCL without a camera), image-based re-localization and the sequence method."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.2))
    x = np.arange(-before, after)
    for m in ("amcl", "image_reloc", "sequence", "proposed") if "sequence" in results else ("amcl", "mixture",
                                                                                             "proposed"):
        curves = recovery_curves(results[m], before, after)
        if not len(curves):
            continue
        for c in curves:
            ax.plot(x, np.maximum(c, 1e-3), color=COLOURS[m], lw=0.4, alpha=0.25)
        with warnings.catch_warnings():  # steps no kidnapping reaches are NaN in every row
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(curves, axis=0)
        ax.plot(x, np.maximum(med, 1e-3), color=COLOURS[m], lw=2.0, label=f"{METHODS[m]} (median of {len(curves)})")
    ax.axvline(0, color="k", ls="--", lw=0.8)
    ax.axhline(0.4, color="0.4", ls=":", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("steps since the kidnapping")
    ax.set_ylabel("position error (m)")
    ax.set_title("Figure 12: recovery from kidnapping (dotted: the paper's 40 cm)")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    return save_figure(fig, path)
