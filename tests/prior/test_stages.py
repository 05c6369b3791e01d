"""The area prior from the command line on the CI micro site: features, build, append, query, evaluate,
and a bundle that seeds the runtime filter over areas without torch."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stages.app import app

runner = CliRunner()
SETS = ["prior.weights=null", "prior.input_size=64", "prior.n_components=8", "prior.k=4", "evaluate.trials=1"]


def cli(*argv):
    args = list(argv) + ["--config", "ci"] + [x for s in SETS for x in ("--set", s)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(scope="module")
def prior_dirs(micro_bundle, tmp_path_factory):
    _, ing, _, _, bundle = micro_bundle
    root = tmp_path_factory.mktemp("prior")
    cli("prior", "features", str(ing), "--out", str(root / "f"))
    cli("prior", "build", str(root / "f"), "--out", str(root / "p"))
    return ing, bundle, root


def test_features_cover_every_image_with_its_labels(prior_dirs):
    from pipeline.io import tables
    from pipeline.prior.features import read_layers

    ing, _, root = prior_dirs
    meta, raw, rep = read_layers(root / "f")
    images = tables.read_table(ing / "images.parquet", "images").to_pydict()
    assert meta["image_id"] == images["image_id"] and meta["area"] == images["area"]
    assert set(raw) == {"pool", "head", "logits"} and raw["pool"].shape[1] == 2880
    np.testing.assert_allclose(np.linalg.norm(raw["head"], axis=1), 1.0, rtol=1e-5)
    assert (root / "f" / "config.yaml").is_file() and rep["encoder"]["weights"] == "none (random init)"


def test_build_query_and_append(prior_dirs, tmp_path):
    from pipeline.prior.model import AreaPrior

    ing, _, root = prior_dirs
    prior = AreaPrior.load(root / "p")
    n_train = len(prior.labels)
    assert set(prior.rows["split"]) == {"train"}
    image = ing / prior.rows["image_id"][0]
    out = json.loads(cli("prior", "query", str(root / "p"), str(image), "--json", "--top", "2"))
    probs = [a["probability"] for a in out[0]["areas"]]
    assert len(probs) == 2 and probs[0] >= probs[1] and 0 < sum(probs) <= 1 + 1e-6
    # images already in the prior are refused, without a traceback
    result = runner.invoke(app, ["prior", "append", str(root / "p"), str(root / "f"), "--out", str(tmp_path / "p2"),
                                 "--config", "ci", *[x for s in SETS for x in ("--set", s)]])
    assert result.exit_code == 1 and "in the prior already" in result.output and "Traceback" not in result.output
    from pipeline.config import load_config
    from pipeline.prior.build import run_prior_append
    from pipeline.prior.features import read_layers

    meta, _, _ = read_layers(root / "f")
    assert "test" in meta["split"]
    # the held-out images' features only, as a site team would compute them for a new wing: appending
    # them keeps every old row as it was
    sub = tmp_path / "f_test"
    _write_subset(root / "f", sub, [s == "test" for s in meta["split"]])
    run_prior_append(load_config("ci", SETS), inputs={"prior": root / "p", "features": sub},
                     outputs={"out": tmp_path / "p2"})
    grown = AreaPrior.load(tmp_path / "p2")
    assert len(grown.labels) == len(meta["image_id"]) > n_train
    for n in prior.layers:
        np.testing.assert_array_equal(grown.vectors[n][:n_train], prior.vectors[n])
    report = json.loads((tmp_path / "p2" / "report.json").read_text())
    assert report["appended"][-1]["images"] == len(meta["image_id"]) - n_train


def _write_subset(src: Path, dst: Path, keep: list[bool]):
    import shutil

    from pipeline.io import tables

    dst.mkdir()
    shutil.copyfile(src / "report.json", dst / "report.json")
    for layer in json.loads((src / "report.json").read_text())["encoder"]["layers"]:
        f = src / f"{layer}.parquet"
        t = tables.read_table(f, "multilayer")
        tables.write_table(dst / f.name, t.filter(np.array(keep)), "multilayer")


def test_update_drops_changed_images_adds_new_ones_and_keeps_the_rest(prior_dirs, tmp_path):
    """The site after an update, as `prior features` sees it: one area's images re-captured (same ids,
    new bytes), another area's gone. The updated prior holds exactly the new database images."""
    from pipeline.io import tables
    from pipeline.io.image_reuse import HASHES_FILE
    from pipeline.prior.features import read_layers
    from pipeline.prior.model import AreaPrior

    _, _, root = prior_dirs
    meta, _, _ = read_layers(root / "f")
    prior = AreaPrior.load(root / "p")
    assert (root / "p" / HASHES_FILE).is_file()
    classes = sorted(set(zip(meta["room"], meta["area"], strict=True)))
    changed, gone = classes[0], classes[-1]
    rows = list(zip(meta["room"], meta["area"], strict=True))
    f2 = tmp_path / "f2"
    _write_subset(root / "f", f2, [c != gone for c in rows])
    sha = tables.read_table(root / "f" / HASHES_FILE, "image_hashes").to_pydict()
    new_sha = [h if c != changed else "0" * 64 for h, c in zip(sha["sha256"], rows, strict=True)]
    keep = [c != gone for c in rows]
    tables.write_table(f2 / HASHES_FILE, tables.to_table("image_hashes", {
        "image_id": [i for i, k in zip(sha["image_id"], keep, strict=True) if k],
        "sha256": [h for h, k in zip(new_sha, keep, strict=True) if k]}), "image_hashes")
    out = cli("prior", "update", str(root / "p"), str(f2), "--out", str(tmp_path / "p2"))
    assert "removed" in out and "Traceback" not in out
    grown = AreaPrior.load(tmp_path / "p2")
    train = [i for i, (m, s) in enumerate(zip(rows, meta["split"], strict=True)) if s == "train"]
    stay = [meta["image_id"][i] for i in train if rows[i] not in (changed, gone)]
    redo = [meta["image_id"][i] for i in train if rows[i] == changed]
    assert grown.rows["image_id"] == stay + redo
    assert gone not in grown.classes and changed in grown.classes
    old_row = {i: n for n, i in enumerate(prior.rows["image_id"])}
    for n in prior.layers:
        np.testing.assert_array_equal(grown.vectors[n][: len(stay)], prior.vectors[n][[old_row[i] for i in stay]])
    u = json.loads((tmp_path / "p2" / "report.json").read_text())["updated"][-1]
    assert (u["kept"], u["added"], u["dropped"]) == (len(stay), len(redo), len(prior.labels) - len(stay))
    assert u["removed_classes"] == [list(gone)] and u["refitted_classes"] == [list(changed)]
    # the same features again: nothing to change, and the prior is byte for byte the same
    cli("prior", "update", str(tmp_path / "p2"), str(f2), "--out", str(tmp_path / "p3"))
    again = json.loads((tmp_path / "p3" / "report.json").read_text())["updated"][-1]
    assert (again["dropped"], again["added"]) == (0, 0)
    for name in ("db_pool.parquet", "pool_gaussians.npz", HASHES_FILE):
        assert (tmp_path / "p2" / name).read_bytes() == (tmp_path / "p3" / name).read_bytes()


def test_update_refuses_a_prior_without_image_hashes(prior_dirs, tmp_path):
    import shutil

    from pipeline.io.image_reuse import HASHES_FILE

    _, _, root = prior_dirs
    shutil.copytree(root / "p", tmp_path / "old")
    (tmp_path / "old" / HASHES_FILE).unlink()
    result = runner.invoke(app, ["prior", "update", str(tmp_path / "old"), str(root / "f"), "--out",
                                 str(tmp_path / "p2"), "--config", "ci", *[x for s in SETS for x in ("--set", s)]])
    assert result.exit_code == 1 and "sha256" in result.output and "rebuild it" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "p2").exists()


def test_evaluate_writes_table_one_and_the_seeding_comparison(prior_dirs):
    ing, bundle, root = prior_dirs
    # the site's own features stand in for a changed site's: the path is exercised, the figures are checked
    out = cli("prior", "evaluate", str(root / "f"), "--bundle", str(bundle), "--data", str(ing), "--out",
              str(root / "r"), "--changed", str(root / "f"))
    assert "Table I" in out
    m = json.loads((root / "r" / "metrics.json").read_text())
    assert [r["compression"] for r in m["table_one"]] == ["ipca", "kpca", "srp", "grp", "none"]
    for r in m["table_one"]:
        assert 0 <= r["area_accuracy"] <= 1 and r["memory_kb_mean_layer"] > 0 and r["query_ms"] > 0
    assert {r["compression"]: r["dims"]["pool"] for r in m["table_one"]}["none"] == 2880
    assert set(m["weights"]) == {"spearman", "pearson", "euclidean", "gaussian"}
    n_images = sum(json.loads((root / "f" / "report.json").read_text())["splits"].values())
    assert m["changed"]["query_images"] == n_images
    assert set(m["changed"]["weights"]) == set(m["weights"])
    for r in m["table_one"]:
        assert 0 <= r["changed_area_accuracy"] <= 1 and 0 <= r["changed_room_accuracy"] <= 1
    a = m["append"]
    assert a["late_area_accuracy_before"] in (0.0, None)  # their classes are not in the first prior
    assert a["images_first"] + a["images_appended"] == m["site"]["database_images"]
    assert 0 <= a["other_unchanged_share"] <= 1
    sd = m["seeding"]
    assert set(sd["summary"]) == {"area_prior", "candidates", "uniform"}
    assert all(s["replays"] == len(sd["starts"]) > 0 for s in sd["summary"].values())
    for f in ("report.md", "table_one.png", "layer_weights.png", "seeding.png", "examples.png", "config.yaml"):
        assert (root / "r" / f).is_file()
    from tests.tracked_files import approx, read_headline, read_plot

    h = read_headline(root / "r")
    t1 = m["table_one"]
    conf = next(r for r in t1 if r["compression"] == m["settings"]["compression"])
    assert h["table_one"] == {"area_accuracy_best": approx(max(r["area_accuracy"] for r in t1)),
                              "room_accuracy_best": approx(max(r["room_accuracy"] for r in t1)),
                              "area_accuracy": approx(conf["area_accuracy"]),
                              "room_accuracy": approx(conf["room_accuracy"]),
                              "changed_area_accuracy_best": approx(max(r["changed_area_accuracy"] for r in t1)),
                              "changed_room_accuracy_best": approx(max(r["changed_room_accuracy"] for r in t1))}
    assert h["seeding"] == {k: approx(sd[k]) for k in ("prior_hit_rate", "prior_top1_rate", "retrieval_top1_rate")}
    for name, v in sd["summary"].items():
        assert h[f"seeding_{name}"] == {k: approx(v[k]) for k in ("replays", "converged", "within_15",
                                                                  "converged_step_median")}
    assert set(h) == {"table_one", "seeding", "seeding_area_prior", "seeding_candidates", "seeding_uniform"}
    curve = read_plot(root / "r", "seeding", ["steps", "area_prior", "candidates", "uniform"])
    assert [r["steps"] for r in curve] == list(range(max(r["steps"] for r in sd["replays"]["uniform"])))
    for name, reps in sd["replays"].items():
        conv = [r["converged_step"] for r in reps if r["converged_step"] is not None]
        assert curve[-1][name] == approx(len(conv) / len(reps))  # every converged replay by the last step
        for row in curve[::5]:
            assert row[name] == approx(sum(c <= row["steps"] for c in conv) / len(reps))


def test_evaluate_refuses_half_a_seeding_request(prior_dirs):
    _, bundle, root = prior_dirs
    result = runner.invoke(app, ["prior", "evaluate", str(root / "f"), "--bundle", str(bundle), "--out",
                                 str(root / "r2")])
    assert result.exit_code == 1 and "--bundle and --data go together" in result.output


@pytest.fixture(scope="module")
def prior_bundle(prior_dirs, micro_bundle, tmp_path_factory):
    from pipeline.bundle.export import run_export
    from pipeline.config import load_config

    cfg_sets = [*SETS, "filter.seed_with=area_prior", "filter.inject_areas=true", "export.archive=false"]
    _, ing, model, index, _ = micro_bundle
    _, _, root = prior_dirs
    return run_export(load_config("ci", cfg_sets), inputs={"model": model, "index": index, "data": ing,
                                                           "prior": root / "p"},
                      outputs={"out": tmp_path_factory.mktemp("pb")})


def test_bundle_with_a_prior_seeds_the_filter_over_areas_without_torch(prior_dirs, prior_bundle):
    from pipeline.prior.model import AreaPrior
    from pipeline.runtime.localizer import Localizer

    ing, _, root = prior_dirs
    bundle = prior_bundle
    meta = json.loads((bundle / "models" / "prior.json").read_text())
    assert max(meta["parity"]["max_abs_by_layer"].values()) <= meta["parity"]["tolerance"]
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert "prior/prior.json" in manifest["files"] and "models/prior.onnx" in manifest["files"]
    loc = Localizer.from_bundle(bundle)
    from pipeline.evaluation.replay import load_run

    run = load_run(sorted((ing / "runs").glob("query_*.parquet"))[0])
    est = loc.update(run.odom[0], run.ranges[0], image=ing / run.image_ids[0])
    assert est.source == "area_prior" and est.candidates is None
    # every particle was born in one of the seeded areas' free space
    probs = loc.area_prior.probabilities(ing / run.image_ids[0])
    seeded = np.flatnonzero(loc.area_prior.weights(probs) > 0)
    assert np.isin(loc.area_prior.cells, seeded).any()
    # the ONNX encoder gives the torch encoder's layers, and the probabilities are the prior's of them
    from pipeline.detection.inference import load_image
    from pipeline.prior.seeding import encoder_for

    prior = AreaPrior.load(root / "p")
    frame = ing / run.image_ids[0]
    torch_layers = encoder_for(prior, None)([load_image(frame)])
    onnx_layers = loc.area_prior.layers(frame)
    for n in prior.layers:
        np.testing.assert_allclose(onnx_layers[n], torch_layers[n], atol=1e-4)
    np.testing.assert_array_equal(probs, prior.probabilities(onnx_layers)[0])
    code = ("import sys; from pipeline.runtime.localizer import Localizer; "
            f"loc = Localizer.from_bundle({str(bundle)!r}); "
            f"loc.area_prior.probabilities({str(frame)!r}); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip().endswith("False")


def test_export_refuses_area_seeding_without_a_prior(micro_bundle, tmp_path):
    from pipeline.bundle.export import run_export
    from pipeline.config import load_config
    from pipeline.errors import ConfigError

    _, ing, model, index, _ = micro_bundle
    with pytest.raises(ConfigError, match="no --prior"):
        run_export(load_config("ci", ["filter.inject_areas=true", "export.archive=false"]),
                   inputs={"model": model, "index": index, "data": ing}, outputs={"out": tmp_path})
    with pytest.raises(ConfigError, match="no --prior"):
        run_export(load_config("ci", ["filter.seed_with=area_prior", "export.archive=false"]),
                   inputs={"model": model, "index": index, "data": ing}, outputs={"out": tmp_path})


class StubFilter:
    """Scripted states; records what the Localizer injects."""

    def __init__(self, states):
        from pipeline.runtime.amcl import FilterState

        self.script, self.step = [FilterState(x) for x in states], 0
        self.state = FilterState.TRACKING
        self.poses, self.regions = [], []
        self.particles = np.zeros((10, 3))

    def inject(self, poses, weights, std_theta=None):
        self.poses.append(self.step)

    def inject_regions(self, cells, weights, n=None):
        self.regions.append((self.step, np.asarray(weights)))

    def update(self, odometry, scan):
        from types import SimpleNamespace

        self.state = self.script[self.step]
        self.step += 1
        return SimpleNamespace(pose=np.zeros(3), covariance=np.eye(3), state=self.state, particles=10, updated=True,
                               best_likelihood=1.0)


def test_areas_are_injected_once_when_the_filter_is_declared_lost(prior_dirs, prior_bundle):
    from pipeline.runtime.localizer import Localizer

    ing, _, _ = prior_dirs
    loc = Localizer.from_bundle(prior_bundle)
    frame = ing / loc.area_prior.prior.rows["image_id"][0]
    states = ["tracking"] * 3 + ["lost", "lost"] + ["relocalising"] * 2 + ["tracking"] * 2 + ["lost"] + ["tracking"]
    loc.camera.filter, loc.camera.started, loc.camera.seeded_by_camera = StubFilter(states), True, True
    sources = [loc.update(np.zeros(3), None, image=frame).source for _ in states]
    lost = [i + 1 for i, st in enumerate(states) if st == "lost" and (i == 0 or states[i - 1] != "lost")]
    assert [s for s, _ in loc.filter.regions] == lost  # the first update that sees each loss, once
    assert all(sources[i] == "image+area_prior" for i in lost)
    for _, w in loc.filter.regions:
        assert np.count_nonzero(w) <= loc.area_prior.max_areas and w.sum() > 0


def test_area_options_need_a_prior_in_the_bundle(micro_bundle, tmp_path):
    import yaml

    from pipeline.runtime.bundle import BundleError
    from pipeline.runtime.localizer import Localizer

    bundle = micro_bundle[4]
    settings = yaml.safe_load((bundle / "filter.yaml").read_text())
    for key in ("seed_with", "inject_areas"):
        s = {**settings, "filter": {**settings["filter"], key: "area_prior" if key == "seed_with" else True}}
        with pytest.raises(BundleError, match=f"filter.{key}"):
            Localizer(bundle, {}, s)


def test_build_is_byte_identical_when_rerun(prior_dirs, tmp_path):
    import hashlib

    _, _, root = prior_dirs
    cli("prior", "build", str(root / "f"), "--out", str(tmp_path / "again"), "--set", "prior.compression=kpca")
    cli("prior", "build", str(root / "f"), "--out", str(tmp_path / "twice"), "--set", "prior.compression=kpca")

    def digest(d):
        return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in d.iterdir()}

    assert digest(tmp_path / "again") == digest(tmp_path / "twice")
