"""The `evaluate` section: `evaluate` and `localize` replays."""

from __future__ import annotations

from pydantic import Field

from pipeline.config.base import Strict


class EvaluateConfig(Strict):
    """`siteloc evaluate`: the paper's localization experiments on a site's query runs (seed 000 section 4)."""

    trials: int = Field(5, ge=1, description="replays per run and method, seeds filter.seed .. + trials - 1")
    runs: tuple[str, ...] = Field((), description="runs to replay; empty: every query_* run of the site")
    converge_threshold_m: float = Field(0.5, gt=0, description="converged: position error under this ...")
    converge_hold: int = Field(10, ge=1, description="... for this many consecutive steps")
    workers: int | None = Field(None, ge=1, description="processes replaying side by side (null: the usable cores, "
                                "at most 8); 1 replays in this process. The figures do not depend on it")
