"""Config presets: every preset validates; unknown keys and bad values name the file and the key."""

from __future__ import annotations

import pytest
import yaml

from pipeline.config import CONFIG_DIR, SitelocConfig, load_config, write_effective_config
from pipeline.errors import ConfigError


@pytest.mark.parametrize("preset", sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))
def test_presets_are_valid(preset):
    cfg = load_config(preset)
    # configs/params.yaml is the demo preset resolved for DVC, and keeps the name it was made from
    assert cfg.preset == ("demo" if preset == "params" else preset)


def test_presets_exist():
    assert {"demo", "ci", "paper"} <= {p.stem for p in CONFIG_DIR.glob("*.yaml")}


def test_unknown_key_names_file_and_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"ingest": {"split": {"test_fracton": 0.3}}}))
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    text = str(exc.value)
    assert str(path) in text and "ingest.split.test_fracton" in text and "unknown key" in text
    assert "test_fraction" in text  # the known keys are offered


def test_bad_value_names_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"ingest_log": {"mapping": {"resolution": -0.05}}}))
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert "ingest_log.mapping.resolution" in str(exc.value) and str(path) in str(exc.value)


def test_cross_field_rule(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"ingest_log": {"mapping": {"free_thresh": 0.8}}}))
    with pytest.raises(ConfigError, match="free_thresh must be below occupied_thresh"):
        load_config(path)


def test_overrides_and_their_errors():
    cfg = load_config("demo", ["ingest.split.seed=7", "ingest_log.mapping.resolution=0.1"])
    assert cfg.ingest.split.seed == 7 and cfg.ingest_log.mapping.resolution == 0.1
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        load_config("demo", ["ingest.split.seed"])
    with pytest.raises(ConfigError, match="ingest.split.sed"):
        load_config("demo", ["ingest.split.sed=1"])


def test_unknown_preset_lists_presets():
    with pytest.raises(ConfigError, match="unknown preset 'nope'.*demo"):
        load_config("nope")


def test_not_yaml(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(path)


def test_effective_config_round_trips(tmp_path):
    cfg = load_config("ci", ["filter.seed=3"])
    write_effective_config(cfg, tmp_path, stage="ingest", inputs={"site": "x"})
    doc = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert doc["stage"] == "ingest" and doc["inputs"] == {"site": "x"}
    assert SitelocConfig.model_validate(doc["config"]) == cfg


def test_a_directory_named_like_a_preset_does_not_shadow_it(tmp_path, monkeypatch):
    from pipeline.config import resolve_preset

    (tmp_path / "demo").mkdir()
    monkeypatch.chdir(tmp_path)
    assert resolve_preset("demo") == CONFIG_DIR / "demo.yaml"
    with pytest.raises(ConfigError, match="config file not found"):
        resolve_preset("missing.yaml")


def test_every_key_is_described_and_the_reference_page_is_current():
    from pathlib import Path

    from pipeline.config.keys import keys, markdown

    found = keys()
    assert len(found) > 200 and [k.key for k in found if not k.description] == []
    named = {k.key for k in found}
    assert {"filter.camera.threshold", "retrieval.index_params.ivf_nprobe", "ingest.split.seed"} <= named
    page = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"
    assert page.read_text() == markdown(), "stale: run `siteloc config docs --out docs/configuration.md`"


def test_explain_prints_a_keys_default_value_and_meaning_and_refuses_an_unknown_one():
    from typer.testing import CliRunner

    from stages.app import app

    runner = CliRunner()
    res = runner.invoke(app, ["config", "show", "--config", "ci", "--set", "filter.camera.threshold=7.5",
                              "--explain", "filter.camera.threshold"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].startswith("filter.camera.threshold  (number; read by the runtime")
    assert "  default: 6.0" in lines and "  in this config: 7.5" in lines and "replaces the belief" in res.output
    res = runner.invoke(app, ["config", "show", "--set", "filter.camera.settled_updates=null",
                              "--explain", "filter.camera.settled_updates"])
    assert res.exit_code == 0 and "  in this config: null" in res.output.splitlines()  # a null value is a value
    res = runner.invoke(app, ["config", "show", "--explain", "filter.kld"])
    assert res.exit_code == 0 and "  filter.kld.bin_xy: 0.5" in res.output.splitlines()
    res = runner.invoke(app, ["config", "show", "--explain", "filter.camera.treshold"])
    assert res.exit_code == 1 and "did you mean filter.camera.threshold" in res.output
    assert "Traceback" not in res.output


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
def test_no_config_number_may_be_infinite_or_nan(value):
    """A garbage number is refused when the config is read, not found mid-run."""
    with pytest.raises(ConfigError, match="finite number"):
        load_config("ci", [f"ingest_log.laser.range_max={value}"])
    with pytest.raises(ConfigError, match="finite number"):
        load_config("ci", [f"filter.sensor.sigma_hit={value}"])
