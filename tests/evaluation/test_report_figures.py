"""The report's figures are laid out readably: no panel's title is drawn over the panel above it."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation import report_figures
from pipeline.evaluation.jobs import Replay


def _replay(run: str, seed: int, steps: int = 60) -> Replay:
    errors = np.abs(np.random.default_rng(seed).normal(0, 1, steps)) * np.linspace(5, 0.1, steps)
    return Replay(run, 0, np.zeros((steps, 3)), np.zeros((steps, 3)), errors, np.full(steps, 500), [steps // 2], {})


def _is_above(upper, lower) -> bool:
    """`upper` is in the row above `lower`, sharing some of its width."""
    a, b = upper.get_position(), lower.get_position()
    return a.y0 >= b.y1 and a.x0 < b.x1 and b.x0 < a.x1


@pytest.mark.parametrize("n_runs", [3, 4])
def test_figure10_titles_clear_the_panel_above(tmp_path, monkeypatch, n_runs):
    import matplotlib.pyplot as plt

    figures = []

    def keep(fig, path):
        figures.append(fig)
        return path

    monkeypatch.setattr(report_figures, "save_figure", keep)
    runs = [f"query_{i}" for i in range(n_runs)]
    results = {m: [_replay(r, i + 10 * j) for i, r in enumerate(runs)]
               for j, m in enumerate(("mixture", "image_only", "proposed"))}
    report_figures.figure10_error_vs_step(tmp_path / "fig10.png", results)
    (fig,) = figures
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    axes = [ax for ax in fig.axes if ax.get_visible()]
    pairs = [(upper, lower) for upper in axes for lower in axes if _is_above(upper, lower)]
    assert pairs, "the figure should have a panel below another"
    for upper, lower in pairs:
        title = lower.title.get_window_extent(renderer)
        for text in [upper.xaxis.label, *upper.get_xticklabels()]:
            if text.get_visible() and text.get_text():
                assert not title.overlaps(text.get_window_extent(renderer)), (
                    f"title {lower.get_title()!r} overlaps {text.get_text()!r} of {upper.get_title()!r}")
    plt.close(fig)
