"""Typed configuration: YAML presets in `configs/` validated into frozen pydantic models.

An unknown key or a bad value is a `ConfigError` naming the file and the dotted key. Every stage
writes the effective (fully defaulted) config beside its outputs with `write_effective_config`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, Field, ValidationError

from pipeline import __version__
from pipeline.config.base import Strict
from pipeline.config.bundle import CheckConfig, ExportConfig, UpdateConfig  # noqa: F401
from pipeline.config.detector import DetectorConfig  # noqa: F401
from pipeline.config.evaluate import EvaluateConfig  # noqa: F401
from pipeline.config.prior import PriorConfig  # noqa: F401
from pipeline.config.retrieval import IndexParams, PlaceConfig, RetrievalConfig  # noqa: F401
from pipeline.config.runtime import (  # noqa: F401
    CameraConfig,
    FilterConfig,
    KidnapConfig,
    KldConfig,
    ScanCheckConfig,
    SensorModelConfig,
)
from pipeline.config.sequence import SequenceConfig  # noqa: F401
from pipeline.config.site import (  # noqa: F401
    IngestConfig,
    IngestLogConfig,
    LaserLogConfig,
    MappingConfig,
    OdometryNoise,
    SplitConfig,
    SynthConfig,
)
from pipeline.errors import ConfigError

CONFIG_DIR = Path(os.environ.get("SITELOC_CONFIGS", Path(__file__).resolve().parents[2] / "configs"))


class SitelocConfig(Strict):
    """The whole configuration; each stage reads its own section."""

    preset: str = Field("default", description="name of the preset this config came from")
    synth: SynthConfig = SynthConfig()
    ingest: IngestConfig = IngestConfig()
    ingest_log: IngestLogConfig = IngestLogConfig()
    filter: FilterConfig = FilterConfig()
    detector: DetectorConfig = DetectorConfig()
    retrieval: RetrievalConfig = RetrievalConfig()
    place: PlaceConfig = PlaceConfig()
    export: ExportConfig = ExportConfig()
    update: UpdateConfig = UpdateConfig()
    check: CheckConfig = CheckConfig()
    sequence: SequenceConfig = SequenceConfig()
    prior: PriorConfig = PriorConfig()
    evaluate: EvaluateConfig = EvaluateConfig()


def format_validation_error(source: str, err: ValidationError, root: type[BaseModel] | None = None) -> str:
    lines = [f"{source}: invalid configuration"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "<top level>"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            parent = _model_at(root or SitelocConfig, e["loc"][:-1])
            known = ", ".join(sorted(parent.model_fields)) if parent else "?"
            msg = f"unknown key (known keys here: {known})"
        else:
            msg += f" (got {e.get('input')!r})"
        lines.append(f"  - key '{key}': {msg}")
    return "\n".join(lines)


def _model_at(model: type[BaseModel], loc: tuple) -> type[BaseModel] | None:
    for part in loc:
        field = model.model_fields.get(str(part))
        if field is None or not (isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)):
            return None
        model = field.annotation
    return model


def resolve_preset(name_or_path: str | Path) -> Path:
    """A path to a YAML file, or the name of a preset in `configs/` (`demo`, `ci`, `paper`)."""
    p = Path(name_or_path)
    # A directory that happens to share a preset's name (a `demo/` output folder, say) is not a config file.
    if p.suffix in (".yaml", ".yml") or p.is_file():
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        return p
    candidate = CONFIG_DIR / f"{name_or_path}.yaml"
    if not candidate.is_file():
        known = sorted(x.stem for x in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError(f"unknown preset '{name_or_path}' (presets in {CONFIG_DIR}: {', '.join(known)})")
    return candidate


def _set_dotted(tree: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = tree
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"override '{dotted}': '{part}' is not a section")
    node[parts[-1]] = value


def parse_overrides(items: list[str] | None) -> dict:
    """`KEY=VALUE` strings as {dotted key: YAML-parsed value}; a malformed item is a ConfigError."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}': expected KEY=VALUE, e.g. camera.width=320")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override '{item}': the value is not valid YAML: {exc}") from None
    return out


def load_config(preset: str | Path = "demo", overrides: list[str] | None = None) -> SitelocConfig:
    """Load a preset and apply `key.sub=value` overrides (values parsed as YAML)."""
    path = resolve_preset(preset)
    try:
        from pipeline.io.text_files import read_text

        raw = yaml.safe_load(read_text(path, what="config file")) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    raw.setdefault("preset", path.stem)
    source = str(path)
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}': expected KEY=VALUE, e.g. ingest.split.seed=3")
        key, value = item.split("=", 1)
        _set_dotted(raw, key.strip(), yaml.safe_load(value))
        source = f"{path} with overrides {overrides}"
    try:
        return SitelocConfig.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(format_validation_error(source, err)) from None


def write_effective_config(cfg: SitelocConfig, out_dir: Path, *, stage: str, inputs: dict | None = None) -> Path:
    """Write `config.yaml` beside a stage's outputs: the full config plus what produced it.

    No timestamp: the same inputs and config must give byte-identical outputs.
    """
    from pipeline.io.atomic import write_text_atomic

    doc = {
        "stage": stage,
        "siteloc_version": __version__,
        "inputs": {k: str(v) for k, v in (inputs or {}).items()},
        "config": cfg.model_dump(mode="json"),
    }
    return write_text_atomic(Path(out_dir) / "config.yaml", yaml.safe_dump(doc, sort_keys=False))


PARAMS_FILE = CONFIG_DIR / "params.yaml"
PARAMS_HEADER = """\
# The config `dvc repro` runs (every stage of dvc.yaml reads --config configs/params.yaml): the {preset}
# preset with every default written out, so that DVC tracks each value a stage reads. Made by
#   siteloc config show --config {preset} --out configs/params.yaml
# Change a value here, or with `dvc exp run -S configs/params.yaml:detector.iterations=3000`, and
# `dvc repro` reruns exactly the stages that read it (docs/pipeline.md).
"""


def resolved_params_text(cfg: SitelocConfig) -> str:
    """The fully defaulted config as the YAML of DVC's params file, under a header saying how it was made."""
    body = yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
    return PARAMS_HEADER.format(preset=cfg.preset) + body
