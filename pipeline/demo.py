"""The main job on shipped data: every real CARMEN log -> runs + map, and the example site -> site database.

Later stages (reference site, detector, retrieval, bundle, localization) join this chain as they land.
Steps whose output is already complete are reused, so an interrupted demo resumes where it stopped.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.io.atomic import write_text_atomic

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_CARMEN_DIR = Path(os.environ.get("SITELOC_CARMEN_DIR", REPO_ROOT.parent / "shared" / "data" / "carmen"))
EXAMPLE_SITE = REPO_ROOT / "docs" / "example-site"


@dataclass(frozen=True)
class DemoStep:
    name: str
    output: Path
    reused: bool
    report: dict


def _complete(out: Path) -> bool:
    # report.json is written inside the atomic output directory, so its presence means the step finished.
    return (out / "report.json").is_file() and (out / "config.yaml").is_file()


def run_demo(
    cfg: SitelocConfig,
    *,
    inputs: dict[str, Path] | None = None,
    outputs: dict[str, Path],
    force: bool = False,
    progress: bool = True,
) -> list[DemoStep]:
    """Run the chain into `outputs['data']`; returns one entry per step with its report."""
    from pipeline.ingest import run_ingest
    from pipeline.ingest_log import run_ingest_log, run_name

    inputs = inputs or {}
    carmen_dir = Path(inputs.get("carmen_dir", DEFAULT_CARMEN_DIR))
    example = Path(inputs.get("example_site", EXAMPLE_SITE))
    data = Path(outputs["data"])
    steps: list[DemoStep] = []

    logs = sorted(carmen_dir.glob("*.log.gz")) + sorted(carmen_dir.glob("*.log")) if carmen_dir.is_dir() else []
    for log in logs:
        name = run_name(log)
        out = data / "carmen" / name
        reused = _complete(out) and not force
        if not reused:
            run_ingest_log(cfg, inputs={"log": log}, outputs={"out": out}, force=True, progress=progress)
        steps.append(DemoStep(f"ingest-log {name}", out, reused, json.loads((out / "report.json").read_text())))

    out = data / "example" / "ingested"
    reused = _complete(out) and not force
    if not reused:
        run_ingest(cfg, inputs={"site": example}, outputs={"out": out}, force=True, progress=progress)
    steps.append(DemoStep("ingest example-site", out, reused, json.loads((out / "report.json").read_text())))

    summary = {s.name: {"output": str(s.output), "reused": s.reused, "report": s.report} for s in steps}
    write_text_atomic(data / "demo-summary.json", json.dumps(summary, indent=2) + "\n")
    write_effective_config(cfg, data, stage="demo", inputs={"carmen_dir": carmen_dir, "example_site": example})
    return steps
