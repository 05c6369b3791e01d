"""The main job: the DVC pipeline of dvc.yaml, run stage by stage through DVC, with a summary.

dvc.yaml is the one definition of the chain (reference site -> detector -> retrieval -> sequence LSTM ->
area prior -> bundle -> localization report, then the real CARMEN logs and the example site), so
`siteloc demo`, `dvc repro` and `make repro` decide alike what is out of date and leave a dvc.lock
that matches the outputs. Each stage is reproduced through DVC's own API in dependency order and timed;
a stage DVC finds up to date is reported as reused. Stages whose inputs lie outside the project and are
missing (the CARMEN logs of ../shared/data/carmen) are skipped with a warning.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import SitelocError

REPO_ROOT = Path(__file__).resolve().parent.parent


def project_root(start: Path | None = None) -> Path:
    """The DVC project holding `start` (default: the working directory), as `dvc` itself finds it."""
    here = Path(start or Path.cwd()).resolve()
    for folder in (here, *here.parents):
        if (folder / "dvc.yaml").is_file() and (folder / ".dvc").is_dir():
            return folder
    raise DemoError(f"{here}: not inside a DVC project (no dvc.yaml and .dvc/ here or above); run the demo "
                    f"from a clone of siteloc, e.g. cd {REPO_ROOT}")
PARAMS = Path("configs") / "params.yaml"
REPORT_FILES = ("synth_report.json", "report.json", "metrics.json", "bag_report.json", "export_report.json")


class DemoError(SitelocError):
    """The DVC pipeline could not be opened or one of its stages failed."""


@dataclass(frozen=True)
class DemoStep:
    name: str  # the DVC stage (`ingest_log@intel-corrected`)
    output: Path
    reused: bool  # DVC found it up to date
    report: dict
    seconds: float


def write_params(cfg, root: Path) -> bool:
    """Make configs/params.yaml the fully defaulted `cfg`; returns whether its content changed."""
    from pipeline.config import resolved_params_text
    from pipeline.io.atomic import write_text_atomic

    path = root / PARAMS
    text = resolved_params_text(cfg)
    if path.is_file() and path.read_text() == text:
        return False
    write_text_atomic(path, text)
    return True


def _open_repo(root: Path):
    try:
        from dvc.repo import Repo
    except ImportError:
        raise DemoError("siteloc demo runs the DVC pipeline of dvc.yaml, but DVC is not installed: "
                        "pip install 'siteloc[dvc]' (make setup installs it)") from None
    from dvc.exceptions import DvcException

    try:
        return Repo(str(root))
    except DvcException as exc:
        raise DemoError(f"{root}: not a DVC project ({exc}); run the demo from a clone of siteloc") from None


def _ordered_stages(repo) -> list:
    """Every stage of dvc.yaml, upstream first, otherwise in the order dvc.yaml lists them."""
    import networkx as nx
    from dvc.stage import PipelineStage

    stages = [s for s in repo.index.stages if isinstance(s, PipelineStage)]
    position = {s.addressing: i for i, s in enumerate(stages)}
    # DVC's graph points from a stage to what it depends on; reversed, a topological order runs upstream first.
    graph = repo.index.graph.reverse(copy=True)
    order = nx.lexicographical_topological_sort(graph, key=lambda s: position.get(s.addressing, -1))
    return [s for s in order if isinstance(s, PipelineStage)]


def _missing_inputs(stage, produced: set[str]) -> list[str]:
    """Dependencies no stage produces and that are not on disk (data from outside the project)."""
    return [d.def_path for d in stage.deps
            if not hasattr(d, "params") and d.fs_path not in produced and not os.path.exists(d.fs_path)]


def _report(out: Path) -> dict:
    if (out / "manifest.json").is_file():  # a bundle
        manifest = json.loads((out / "manifest.json").read_text())
        parity = json.loads((out / "models" / "describer.json").read_text())["parity"]["max_differences"]
        return {"files": len(manifest["files"]), "parity": parity,
                "bytes": sum(e["size"] for e in manifest["files"].values())}
    for name in REPORT_FILES:
        if (out / name).is_file():
            return json.loads((out / name).read_text())
    return {}


def run_demo(
    cfg=None,
    *,
    root: Path | None = None,
    force: bool = False,
    on_skip: Callable[[str, list[str]], None] | None = None,
) -> list[DemoStep]:
    """Reproduce every stage of `root`'s dvc.yaml whose inputs exist; one entry per stage run or reused.

    With `cfg`, configs/params.yaml is first made that config (fully defaulted), so DVC reruns exactly the
    stages whose parameters it changes. The summary goes to data/demo-summary.json.
    """
    from pipeline.io.atomic import write_text_atomic

    root = project_root(root)
    if cfg is not None:
        write_params(cfg, root)
    # The stages' commands are `siteloc ...`: the one of this interpreter, whatever PATH says.
    os.environ["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    steps: list[DemoStep] = []
    with _open_repo(root) as repo:  # refuses clearly when DVC is not installed
        from dvc.exceptions import DvcException

        stages = _ordered_stages(repo)
        produced = {o.fs_path for s in stages for o in s.outs}
        for stage in stages:
            missing = _missing_inputs(stage, produced)
            if missing:
                produced -= {o.fs_path for o in stage.outs}  # what reads its outputs is skipped too
                if on_skip:
                    on_skip(stage.addressing, missing)
                continue
            start = time.perf_counter()
            try:
                ran = repo.reproduce(f"{stage.path}:{stage.name}", single_item=True, force=force)
            except DvcException as exc:
                cause = f": {exc.__cause__}" if exc.__cause__ else ""
                raise DemoError(f"stage '{stage.addressing}' failed{cause} (its output is above; `dvc repro "
                                f"{stage.addressing}` reruns it alone)") from None
            out = Path(stage.outs[0].fs_path)
            steps.append(DemoStep(stage.addressing, out, not ran, _report(out),
                                  round(time.perf_counter() - start, 1)))
    summary = {s.name: {"output": str(s.output.relative_to(root)), "reused": s.reused, "seconds": s.seconds,
                        "report": s.report} for s in steps}
    summary["total"] = {"seconds": round(sum(s.seconds for s in steps), 1)}
    write_text_atomic(root / "data" / "demo-summary.json", json.dumps(summary, indent=2) + "\n")
    return steps
