"""`siteloc evaluate`: the paper's localization experiments on a site, as a report."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Reproduce seed 000's localization experiments on a site and write reports/<site>/report.md.

BUNDLE is a deployable bundle (`siteloc export`, a directory or its .tar.gz) and DATA the ingested site
whose query runs (camera frame, odometry, laser and ground truth per step, with kidnappings) are replayed.
Every method gets the same runs, seeds (filter.seed .. + evaluate.trials - 1) and the bundle's filter
settings:

  proposed    the bundle's Localizer: the first frame's Top-4 retrieved poses (4:3:2:1) seed KLD-AMCL,
              the current frame's Top-4 are injected while the filter is lost (with the bundle's
              filter.yaml: checked against the scan, with the sequence's, the camera challenging
              a tracked belief)
  amcl        the same filter started uniform, no camera ("without image-based localization")
  mcl         fixed-count MCL (filter.max_particles, the paper's 5000), uniform start
  mixture     mixture MCL, uniform start
  image_only  each frame's Top-1 retrieved pose, no filter

The report holds Table 1 (the Top-4 candidates of each run's first frame, the fine pose, the ground
truth, the error), the summary beside the paper's figures (90th-percentile error with and without
retrieval, mean error after convergence, steps to converge, steps to recover from each kidnapping) and
Figures 8 (error CDF with / without retrieval), 9 (particles and error, MCL vs KLD-AMCL), 10 (error
per step: mixture MCL, image-only, proposed), 11 (a kidnapped run on the map) and 12 (recovery from
every kidnapping). Also metrics.json, estimates/<method>.parquet (per step) and config.yaml.
Each frame is retrieved once (0.04-0.07 s on 2 CPU cores) and shared by the methods that use it.

Example: siteloc evaluate bundles/office-0.1.0 data/reference/ingested --out reports/office
"""


def evaluate(
    bundle: Annotated[Path, typer.Argument(help="A bundle from `siteloc export`.", show_default=False)],
    data: Annotated[Path, typer.Argument(help="The ingested site with query runs.", show_default=False)],
    out: Annotated[Path | None, typer.Option("--out", "-o",
                                             help="Output directory \\[default: reports/<site>].")] = None,
    run: Annotated[
        list[str] | None, typer.Option("--run", "-r", help="Replay only this run (repeatable) \\[default: query_*].")
    ] = None,
    trials: Annotated[int | None, typer.Option("--trials", min=1, help="Replays per run and method "
                                               "\\[default: evaluate.trials].")] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("evaluate.converge_threshold_m=1.0") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.evaluation.report import run_evaluate

        sets = list(set_ or [])
        if run:
            sets.append(f"evaluate.runs={json.dumps(list(run))}")
        if trials:
            sets.append(f"evaluate.trials={trials}")
        cfg = load(config, sets)
        out = out or Path("reports") / _site_of(bundle)
        report = run_evaluate(cfg, inputs={"bundle": bundle, "data": data}, outputs={"out": out}, force=force)
        doc = json.loads((report / "metrics.json").read_text())
        s = doc["summary"]["proposed"]
        typer.echo(f"proposed: p90 error of global localization {s['error_p90_global_m']} m (without retrieval "
                   f"{doc['summary']['amcl']['error_p90_global_m']} m), mean error after convergence "
                   f"{s['error_mean_converged_m']} m, {s['recovered']} of {s['kidnaps']} kidnappings recovered "
                   f"(median {s['recovery_steps_median']} steps)")
        echo_path("report", report / "report.md")


def _site_of(bundle: Path) -> str:
    """The site a bundle is of (its manifest's `site`), only to name the default output; verified later."""
    from pipeline.runtime.bundle import peek_site

    # the run itself reports what is wrong with the bundle
    return peek_site(bundle) or bundle.name.removesuffix(".tar.gz").removesuffix(".tgz")
