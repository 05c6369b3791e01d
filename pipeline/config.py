"""Typed configuration: YAML presets in `configs/` validated into frozen pydantic models.

An unknown key or a bad value is a `ConfigError` naming the file and the dotted key. Every stage
writes the effective (fully defaulted) config beside its outputs with `write_effective_config`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pipeline import __version__
from pipeline.errors import ConfigError

CONFIG_DIR = Path(os.environ.get("SITELOC_CONFIGS", Path(__file__).resolve().parent.parent / "configs"))


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class SplitConfig(Strict):
    test_fraction: float = Field(0.2, ge=0.0, lt=1.0, description="share of whole stops held out for testing")
    seed: int = Field(0, description="seed of the stop-level shuffle")


class IngestConfig(Strict):
    split: SplitConfig = SplitConfig()
    decode_images: bool = Field(True, description="open every image to check it is readable and its size")
    position_tolerance_m: float = Field(0.05, gt=0, description="views of one stop must share x, y within this")
    heading_tolerance_deg: float = Field(
        3.0, gt=0, description="view headings must match the stop heading plus the rig yaw offset within this"
    )
    min_box_side_px: float = Field(1.0, ge=0, description="boxes thinner than this are rejected")
    link_images: bool = Field(True, description="hard-link images into the output (copy when not possible)")


class OdometryNoise(Strict):
    """Thrun's sample_motion_model_odometry parameters (Probabilistic Robotics, table 5.6), std form as nav2.

    The defaults synthesise a decent differential-drive robot: about 2% translation error, 3% rotation
    error and 1 degree of heading error per metre driven.
    """

    alpha1: float = Field(0.001, ge=0, description="rotation noise from rotation (rad^2 per rad^2)")
    alpha2: float = Field(0.0003, ge=0, description="rotation noise from translation (rad^2 per m^2)")
    alpha3: float = Field(0.0004, ge=0, description="translation noise from translation (m^2 per m^2)")
    alpha4: float = Field(0.0001, ge=0, description="translation noise from rotation (m^2 per rad^2)")


class MappingConfig(Strict):
    """Occupancy mapping with known poses (log-odds, ray-traced free space)."""

    resolution: float = Field(0.05, gt=0, le=1.0, description="cell size in metres")
    margin_m: float = Field(1.0, ge=0, description="border added around the observed area")
    max_range_m: float = Field(30.0, gt=0, description="returns beyond this are not used for mapping")
    log_odds_hit: float = Field(0.85, gt=0)
    log_odds_miss: float = Field(0.4, gt=0)
    log_odds_clamp: float = Field(5.0, gt=0)
    occupied_thresh: float = Field(0.65, gt=0, lt=1)
    free_thresh: float = Field(0.196, gt=0, lt=1)
    chunk_scans: int = Field(64, ge=1, description="scans ray-traced per vectorised batch")

    @model_validator(mode="after")
    def _thresholds(self) -> MappingConfig:
        if self.free_thresh >= self.occupied_thresh:
            raise ValueError("free_thresh must be below occupied_thresh")
        return self


class LaserLogConfig(Strict):
    """How raw CARMEN ranges are read."""

    no_return_ranges: tuple[float, ...] = Field(
        (81.83, 81.91, 50.0), description="range codes meaning 'no return' (compared to 0.005 m)"
    )
    range_max: float = Field(
        40.0, gt=0, description="sensor range written to the runs table; larger readings count as no return"
    )


class IngestLogConfig(Strict):
    seed: int = 0
    laser: LaserLogConfig = LaserLogConfig()
    odometry_noise: OdometryNoise = OdometryNoise()
    mapping: MappingConfig = MappingConfig()


class SynthConfig(Strict):
    """Which reference site the pipeline builds when it has no captures of the user's (`siteloc synth`)."""

    site: str = Field("office", description="site preset in configs/sites/ (tiny, office, paper) or a YAML path")
    seed: int = Field(0, description="seed of the layout, furnishing, stops, runs and noise")
    preset_overrides: dict[str, Any] = Field(
        default_factory=dict, description="site preset keys to override, e.g. {camera.width: 320}"
    )


class SitelocConfig(Strict):
    """The whole configuration; each stage reads its own section."""

    preset: str = Field("default", description="name of the preset this config came from")
    seed: int = 0
    synth: SynthConfig = SynthConfig()
    ingest: IngestConfig = IngestConfig()
    ingest_log: IngestLogConfig = IngestLogConfig()


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
    if p.suffix in (".yaml", ".yml") or p.exists():
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
        raw = yaml.safe_load(path.read_text()) or {}
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
