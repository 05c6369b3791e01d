"""The main job on data the project ships or generates.

The reference site of the config (`synth.site`, office for the demo) is rendered and ingested, the
detector is fine-tuned on it and scored on its held-out stops, IPA / RPA descriptors are extracted, the
whitened retrieval database is built and measured, the image-sequence LSTM is trained on the mapping
runs' frames, the deployable bundle is exported, and the site's
query runs are localized from the bundle alone (camera frames + odometry + laser, as a robot would)
beside the paper's baselines (`siteloc evaluate`: reports/<site>/report.md);
then every real CARMEN log becomes runs + map and the documented example site is ingested.
Steps whose output is already complete are reused, so an interrupted demo resumes where it stopped.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.io.atomic import write_text_atomic

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_CARMEN_DIR = Path(os.environ.get("SITELOC_CARMEN_DIR", REPO_ROOT.parent / "shared" / "data" / "carmen"))
EXAMPLE_SITE = REPO_ROOT / "docs" / "example-site"


_clock = {"t": time.perf_counter()}


def _lap() -> float:
    """Seconds since the previous step was recorded (steps are recorded right after their work)."""
    now = time.perf_counter()
    dt, _clock["t"] = now - _clock["t"], now
    return round(dt, 1)


@dataclass(frozen=True)
class DemoStep:
    name: str
    output: Path
    reused: bool
    report: dict
    seconds: float = field(default_factory=_lap)


def _complete(out: Path, report: str = "report.json") -> bool:
    # The report is written inside the atomic output directory, so its presence means the step finished.
    return (out / report).is_file() and (out / "config.yaml").is_file()


def _same_synth(site_dir: Path, preset, seed: int) -> bool:
    """Whether the site there was made from this preset and seed (another config must not reuse it)."""
    import yaml

    try:
        made = yaml.safe_load((site_dir / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return False
    return made.get("seed") == seed and not made.get("change") and made.get("preset") == preset.model_dump(mode="json")


def _same_section(out: Path, section: str, value) -> bool:
    """Whether the stage output there was made with this config section (another must not reuse it)."""
    import yaml

    try:
        made = yaml.safe_load((out / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return False
    return (made.get("config") or {}).get(section) == value.model_dump(mode="json")


def run_demo(
    cfg: SitelocConfig,
    *,
    inputs: dict[str, Path] | None = None,
    outputs: dict[str, Path],
    force: bool = False,
    progress: bool = True,
) -> list[DemoStep]:
    """Run the chain into `outputs['data']`; returns one entry per step with its report."""
    from pipeline.detection.evaluate import run_evaluate_detector
    from pipeline.detection.train import run_train_detector
    from pipeline.ingest import run_ingest
    from pipeline.ingest_log import run_ingest_log, run_name
    from pipeline.sitegen.presets import load_site_preset
    from pipeline.sitegen.synth import run_synth

    inputs = inputs or {}
    _clock["t"] = time.perf_counter()
    carmen_dir = Path(inputs.get("carmen_dir", DEFAULT_CARMEN_DIR))
    example = Path(inputs.get("example_site", EXAMPLE_SITE))
    data = Path(outputs["data"])
    steps: list[DemoStep] = []

    preset = load_site_preset(cfg.synth.site, cfg.synth.preset_overrides)
    site_dir = data / "reference" / "site"  # where dvc.yaml's synth stage writes it too
    reused = _complete(site_dir, "synth_report.json") and not force and _same_synth(site_dir, preset, cfg.synth.seed)
    if not reused:
        run_synth(preset, outputs={"out": site_dir}, seed=cfg.synth.seed, force=True, progress=progress)
    steps.append(DemoStep(f"synth {preset.name}", site_dir, reused,
                          json.loads((site_dir / "synth_report.json").read_text())))
    out = data / "reference" / "ingested"
    reused = _complete(out) and not force and steps[-1].reused
    if not reused:
        run_ingest(cfg, inputs={"site": site_dir}, outputs={"out": out}, force=True, progress=progress)
    steps.append(DemoStep(f"ingest {preset.name}", out, reused, json.loads((out / "report.json").read_text())))
    ingested = out

    models = Path(outputs.get("models", data.parent / "models"))
    detector = models / "detector"
    reused = (_complete(detector, "metrics.json") and not force and steps[-1].reused
              and _same_section(detector, "detector", cfg.detector))
    if not reused:
        run_train_detector(cfg, inputs={"data": ingested}, outputs={"out": detector}, force=True, progress=progress)
    steps.append(DemoStep(f"train-detector {cfg.detector.backbone}", detector, reused,
                          json.loads((detector / "metrics.json").read_text())))
    out = models / "detector-eval"
    reused = _complete(out, "metrics.json") and not force and steps[-1].reused
    if not reused:
        run_evaluate_detector(cfg, inputs={"model": detector, "data": ingested}, outputs={"out": out}, force=True,
                              progress=progress)
    steps.append(DemoStep("evaluate-detector", out, reused, json.loads((out / "metrics.json").read_text())))
    steps += _retrieval_and_bundle(cfg, ingested, detector, data, Path(outputs.get("bundles", data.parent / "bundles")),
                                   Path(outputs.get("reports", data.parent / "reports")),
                                   detector_reused=steps[-2].reused, ingest_reused=steps[1].reused, models=models,
                                   force=force, progress=progress)

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

    summary = {s.name: {"output": str(s.output), "reused": s.reused, "seconds": s.seconds, "report": s.report}
               for s in steps}
    summary["total"] = {"seconds": round(sum(s.seconds for s in steps), 1)}
    write_text_atomic(data / "demo-summary.json", json.dumps(summary, indent=2) + "\n")
    write_effective_config(cfg, data, stage="demo", inputs={"carmen_dir": carmen_dir, "example_site": example})
    return steps


def _retrieval_and_bundle(cfg: SitelocConfig, ingested: Path, detector: Path, data: Path, bundles: Path,
                          reports: Path, *, detector_reused: bool, ingest_reused: bool, models: Path, force: bool,
                          progress: bool) -> list[DemoStep]:
    """extract -> build-index -> evaluate-retrieval -> frame-features -> train-sequence -> export -> evaluate
    (the query runs localized from the bundle, with the paper's baselines). The sequence steps run when the
    site has mapping runs with camera frames.

    A step is reused when its output is complete, was made with the same config section, and every
    step it reads was reused too."""
    from pipeline.bundle.export import run_export
    from pipeline.evaluation.report import run_evaluate
    from pipeline.io.site import read_site
    from pipeline.retrieval.database import run_build_index
    from pipeline.retrieval.evaluate import run_evaluate_retrieval
    from pipeline.retrieval.extract import run_extract
    from pipeline.sequence.frames import run_frame_features
    from pipeline.sequence.train import run_train_sequence

    steps: list[DemoStep] = []
    ref = data / "reference"

    def step(name: str, out: Path, report: str, upstream: bool, section: str, run) -> bool:
        reused = upstream and not force and _complete(out, report) and _same_section(out, section,
                                                                                      getattr(cfg, section))
        if not reused:
            run(out)
        steps.append(DemoStep(name, out, reused, json.loads((out / report).read_text())))
        return reused

    descriptors, index = ref / "descriptors", ref / "index"
    extracted = step("extract", descriptors, "report.json", detector_reused, "retrieval", lambda out: run_extract(
        cfg, inputs={"model": detector, "data": ingested}, outputs={"out": out}, force=True, progress=progress))
    indexed = step("build-index", index, "report.json", extracted, "retrieval", lambda out: run_build_index(
        cfg, inputs={"descriptors": descriptors}, outputs={"out": out}, force=True))
    step("evaluate-retrieval", ref / "retrieval-eval", "metrics.json", extracted, "retrieval",
         lambda out: run_evaluate_retrieval(cfg, inputs={"descriptors": descriptors, "data": ingested},
                                            outputs={"out": out}, force=True, progress=progress))
    sequence, sequenced = None, True
    if any((ingested / "runs").glob("mapping*.parquet")):
        framed = step("frame-features", ref / "frames", "report.json", ingest_reused, "sequence",
                      lambda out: run_frame_features(cfg, inputs={"data": ingested}, outputs={"out": out}, force=True,
                                                     progress=progress))
        sequence = models / "sequence"
        sequenced = step("train-sequence", sequence, "metrics.json", framed, "sequence",
                         lambda out: run_train_sequence(cfg, inputs={"frames": ref / "frames", "data": ingested},
                                                        outputs={"out": out}, force=True, progress=progress))
    site = read_site(ingested / "site.yaml").name if (ingested / "site.yaml").is_file() else ingested.name
    bundle = bundles / f"{site}-{cfg.export.version}"
    manifest_path = bundle / "manifest.json"
    exported = (indexed and sequenced and not force and manifest_path.is_file()
                and json.loads(manifest_path.read_text()).get("config") == cfg.model_dump(mode="json"))
    if not exported:
        run_export(cfg, inputs={"model": detector, "index": index, "data": ingested,
                                **({"sequence": sequence} if sequence else {})}, outputs={"out": bundles}, force=True)
    manifest = json.loads(manifest_path.read_text())
    parity = json.loads((bundle / "models" / "describer.json").read_text())["parity"]["max_differences"]
    steps.append(DemoStep("export", bundle, exported, {"files": len(manifest["files"]), "parity": parity,
                                                       "bytes": sum(e["size"] for e in manifest["files"].values())}))
    if any((ingested / "runs").glob("query_*.parquet")):
        # The query runs localized from the bundle alone, beside the paper's baselines (seed 000 section 4).
        step("evaluate (bundle)", reports / site, "metrics.json", exported, "evaluate",
             lambda out: run_evaluate(cfg, inputs={"bundle": bundle, "data": ingested}, outputs={"out": out},
                                      force=True, progress=progress))
    return steps
