"""`siteloc evaluate`: the paper's experiments from a bundle, checked against recomputations."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import yaml

from pipeline.evaluation.experiments import summarise
from pipeline.evaluation.jobs import CachedRetrieval, Replay
from pipeline.evaluation.report_figures import recovery_curves


def _replay(errors, kidnaps=(), particles=None, converged=0, recovery=(), mean=0.1, median=0.05, lost=(),
            share=1.0):
    e = np.asarray(errors, float)
    return Replay("r", 0, np.zeros((len(e), 3)), np.zeros((len(e), 3)), e,
                  np.asarray(particles if particles is not None else np.full(len(e), 100)), list(kidnaps),
                  {"converged_step": converged, "recovery_steps": list(recovery), "lost_track_steps": list(lost),
                   "held": converged is not None and not lost, "within_threshold_share": share,
                   "error_mean_m": mean, "error_median_m": median, "update_ms_mean": 2.0})


def test_recovery_curves_align_each_kidnapping_and_stop_at_the_next():
    r = _replay(np.arange(20.0), kidnaps=[5, 12])
    c = recovery_curves([r], before=2, after=10)
    assert c.shape == (2, 12)
    np.testing.assert_array_equal(c[0, :9], np.arange(3.0, 12.0))  # steps 3..11, then the next kidnapping at 12
    assert np.isnan(c[0, 9:]).all()
    np.testing.assert_array_equal(c[1, :10], np.arange(10.0, 20.0))  # steps 10..19, then the run ends
    assert np.isnan(c[1, 10:]).all()
    early = recovery_curves([_replay(np.arange(6.0), kidnaps=[1])], before=3, after=2)
    np.testing.assert_array_equal(early[0], [np.nan, np.nan, 0.0, 1.0, 2.0])


def test_summary_counts_against_hand_computed_values():
    a = _replay([5.0, 0.1, 0.1, 0.1], kidnaps=[2], converged=1, recovery=[3], mean=0.1)
    b = _replay([9.0, 9.0, 0.2, 0.2], kidnaps=[1, 3], converged=None, recovery=[20, None], mean=None, median=None,
                 share=None)
    s = summarise([a, b])
    assert (s["replays"], s["converged"], s["converged_step_median"]) == (2, 1, 1.0)
    assert s["lost_track"] == 0 and s["within_threshold_share_median"] == 1.0
    # A third replay converged at step 0 and lost track at step 2: it converged, but is not counted as converged.
    c = _replay([0.1, 0.1, 3.0, 3.0], converged=0, lost=[2], share=0.5)
    s3 = summarise([a, b, c])
    assert (s3["converged"], s3["lost_track"], s3["converged_step_median"]) == (1, 1, 0.5)
    assert s3["within_threshold_share_median"] == 0.75
    assert s["kidnaps"] == 3 and s["recovered"] == 2 and s["recovery_steps_median"] == 11.5
    assert s["recovery_steps_max"] == 20 and s["recovered_within_15"] == 1 and s["recovered_within_40"] == 2
    assert s["error_p90_all_m"] == pytest.approx(np.percentile([5, .1, .1, .1, 9, 9, .2, .2], 90))
    assert s["error_p90_global_m"] == pytest.approx(np.percentile([5, .1, 9], 90))  # up to each first kidnapping
    assert s["error_mean_converged_m"] == pytest.approx(0.1) and s["error_median_converged_m"] == pytest.approx(0.05)


def test_cached_retrieval_describes_each_image_once():
    calls = []

    class Loc:
        def retrieved(self, image):
            calls.append(image)
            return np.full((50, 3), float(len(calls)))

    cache = CachedRetrieval(Loc())
    first = cache("a.png")
    assert cache("a.png") is first and len(calls) == 1
    cache("b.png")
    assert len(calls) == 2 and len(cache.seconds) == 2


@pytest.fixture(scope="module")
def report(micro_sequence_bundle, tmp_path_factory):
    """The report of the micro bundle exported with a sequence LSTM: every method, `sequence` included."""
    from pipeline.evaluation.report import run_evaluate

    cfg, ing, _, bundle = micro_sequence_bundle
    cfg = cfg.model_copy(update={"evaluate": cfg.evaluate.model_copy(update={"trials": 2, "workers": 2})})
    out = run_evaluate(cfg, inputs={"bundle": bundle, "data": ing}, outputs={"out": tmp_path_factory.mktemp("r") / "o"},
                       progress=False)
    return cfg, ing, bundle, out


def test_report_holds_every_experiment_and_figure(report):
    from pipeline.evaluation.experiments import METHODS

    _, ing, _, out = report
    doc = json.loads((out / "metrics.json").read_text())
    runs = sorted(p.stem for p in (ing / "runs").glob("query_*.parquet"))
    assert doc["runs"] == runs and runs
    assert set(doc["summary"]) == set(METHODS)
    for m in METHODS:
        expected = len(runs) * (1 if m == "image_only" else 2)
        assert doc["summary"][m]["replays"] == expected == len(doc["replays"][m])
        assert doc["summary"][m]["kidnaps"] == sum(len(r["kidnaps"]) for r in doc["replays"][m])
    for name in ("fig8_error_cdf", "fig9_particles", "fig10_error_vs_step", "fig11_kidnap_map",
                 "fig12_kidnap_recovery"):
        assert (out / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"({name}.png)" in (out / "report.md").read_text()
    text = (out / "report.md").read_text()
    assert "## Table 1" in text and "| 90th-percentile error of global localization, with image retrieval" in text
    assert len(doc["table1"]) == len(runs) and all(len(r["candidates"]) == 4 for r in doc["table1"])
    assert (out / "config.yaml").is_file()


def test_summary_figures_recompute_from_the_estimates_tables(report):
    from pipeline.io import tables

    _, _, _, out = report
    doc = json.loads((out / "metrics.json").read_text())
    for m in ("proposed", "sequence", "amcl", "mcl"):
        t = tables.read_table(out / "estimates" / f"{m}.parquet", "estimates").to_pydict()
        err = np.hypot(np.subtract(t["x"], t["gt_x"]), np.subtract(t["y"], t["gt_y"]))
        np.testing.assert_allclose(t["error_xy"], err)
        assert doc["summary"][m]["error_p90_all_m"] == pytest.approx(np.percentile(err, 90), abs=1e-4)
        step, kid = np.asarray(t["step"]), np.asarray(t["kidnapped"])
        replay = np.array([f"{r}/{k}" for r, k in zip(t["run"], t["trial"], strict=True)])
        first = {r: min([s_ for s_, k, q in zip(step, kid, replay, strict=True) if k and s_ > 0 and q == r],
                        default=10**9) for r in set(replay)}
        before = np.array([s_ < first[q] for s_, q in zip(step, replay, strict=True)])
        assert doc["summary"][m]["error_p90_global_m"] == pytest.approx(np.percentile(err[before], 90), abs=1e-4)
        assert doc["summary"][m]["particles_mean"] == pytest.approx(np.mean(t["particles"]), abs=0.1)
        # Each replay's TUM file is its estimates, and evo's APE of it is in the metrics.
        from evo.tools.file_interface import read_tum_trajectory_file

        rep0 = doc["replays"][m][0]
        sel = (np.asarray(t["run"]) == rep0["run"]) & (np.asarray(t["trial"]) == rep0["trial"])
        tum = read_tum_trajectory_file(out / "trajectories" / m / f"{rep0['run']}_trial{rep0['trial']}.tum")
        np.testing.assert_allclose(tum.positions_xyz[:, 1], np.asarray(t["y"])[sel])
        assert rep0["evo"]["ape_m"]["rmse"] == pytest.approx(np.sqrt(np.mean(err[sel] ** 2)), abs=1e-4)
    mcl = tables.read_table(out / "estimates" / "mcl.parquet", "estimates").column("particles").to_numpy()
    cfg = report[0]
    assert (mcl == cfg.filter.max_particles).all()  # fixed-count MCL never adapts


def test_kidnap_table_counts_every_kidnapping_of_every_replay(report):
    _, _, _, out = report
    doc = json.loads((out / "metrics.json").read_text())
    for m, v in doc["kidnappings"].items():
        steps = [s for r in doc["replays"][m] for s in r["recovery_steps"]]
        finals = [f for r in doc["replays"][m] for f in r["recovery_final_error_m"]]
        assert v["kidnappings"] == len(steps) == len(finals) == doc["summary"][m]["kidnaps"]
        ok = [s for s in steps if s is not None]
        assert v["recovered"] == len(ok) and v["within_15"] == sum(s <= 15 for s in ok)
        both = sum(s is not None and s <= 15 and f < 0.10 for s, f in zip(steps, finals, strict=True))
        assert v["within_15_and_10cm"] == both
    assert "## Kidnappings" in (out / "report.md").read_text()


def test_a_bundle_without_a_sequence_model_is_evaluated_without_the_sequence_method(micro_bundle, tmp_path):
    from pipeline.evaluation.report import run_evaluate

    cfg, ing, _, _, bundle = micro_bundle
    cfg = cfg.model_copy(update={"evaluate": cfg.evaluate.model_copy(update={"trials": 1})})
    out = run_evaluate(cfg, inputs={"bundle": bundle, "data": ing}, outputs={"out": tmp_path / "o"}, progress=False)
    doc = json.loads((out / "metrics.json").read_text())
    assert not {"sequence", "image_reloc"} & set(doc["summary"]) and "proposed" in doc["summary"]
    assert not (out / "estimates" / "sequence.parquet").exists()


def test_image_only_and_table1_match_a_fresh_localizer(report):
    """Independent of the cache: a new Localizer's Top-4 for the run's frames."""
    from pipeline.evaluation.replay import load_run
    from pipeline.io import tables
    from pipeline.runtime.localizer import Localizer

    _, ing, bundle, out = report
    doc = json.loads((out / "metrics.json").read_text())
    loc = Localizer.from_bundle(bundle)
    run = load_run(ing / "runs" / f"{doc['runs'][0]}.parquet")
    t = tables.read_table(out / "estimates" / "image_only.parquet", "estimates").to_pydict()
    rows = [i for i, r in enumerate(t["run"]) if r == run.name]
    for k in (0, len(run) // 2, len(run) - 1):
        top1 = loc.candidates(ing / run.image_ids[k])[0]
        np.testing.assert_allclose([t["x"][rows[k]], t["y"][rows[k]]], top1[:2], atol=1e-9)
    # Table 1 holds what the filter started from: trial 0's first update, replayed by a fresh Localizer
    # (with filter.scan_check, the four of the first frame's Top-pool that fit the first scan best).
    loc.reset(seed=loc.base_seed)
    first = loc.update(run.odom[0], run.ranges[0], image=ing / run.image_ids[0]).candidates
    np.testing.assert_allclose(doc["table1"][0]["candidates"], first, atol=1e-3)
    np.testing.assert_allclose(np.asarray(doc["table1"][0]["candidates"])[:, 3], [0.4, 0.3, 0.2, 0.1], rtol=1e-6)
    pool = loc.retrieved(ing / run.image_ids[0])[: loc.filter_config.scan_check.pool]
    near = np.min(np.hypot(*(first[:, None, :2] - pool[None, :, :2]).transpose(2, 0, 1)), axis=1)
    assert np.all(near < 5 * loc.filter_config.init_std_xy)  # each one a perturbation of a retrieved pose


def test_same_inputs_give_the_same_report_in_one_process_or_several(report, tmp_path):
    from pipeline.evaluation.report import run_evaluate
    from pipeline.io import tables

    cfg, ing, bundle, out = report  # replayed in 2 processes
    cfg = cfg.model_copy(update={"evaluate": cfg.evaluate.model_copy(update={"trials": 2, "workers": 1})})
    again = run_evaluate(cfg, inputs={"bundle": bundle, "data": ing}, outputs={"out": tmp_path / "o"}, progress=False)
    for path in sorted((out / "estimates").glob("*.parquet")):  # every step of every replay, timings aside
        a, b = (tables.read_table(d / "estimates" / path.name, "estimates").drop_columns(["update_ms"])
                for d in (out, again))
        assert a.equals(b), path.name
    a, b = (json.loads((p / "metrics.json").read_text()) for p in (out, again))
    for d in (a, b):
        for key in ("seconds", "machine", "retrieval"):
            d.pop(key)
        for m in d["replays"].values():
            for r in m:
                r.pop("update_ms_mean"), r.pop("update_ms_p90")
        for s in d["summary"].values():
            s.pop("update_ms_mean")
    a.pop("bundle"), b.pop("bundle")
    assert a == b


def test_cli_reports_and_refuses_bad_inputs_clearly(micro_bundle, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    _, ing, _, _, bundle = micro_bundle
    runner = CliRunner()
    archive = bundle.with_name(bundle.name + ".tar.gz")
    res = runner.invoke(app, ["evaluate", str(archive), str(ing), "--out", str(tmp_path / "r"), "--trials", "1",
                              "--config", "ci"])
    assert res.exit_code == 0, res.output
    assert "kidnappings recovered" in res.output and (tmp_path / "r" / "report.md").is_file()
    res = runner.invoke(app, ["evaluate", str(bundle), str(ing), "--run", "nope", "--out", str(tmp_path / "x"),
                              "--config", "ci"])
    assert res.exit_code == 1 and "nope" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "x").exists()
    other = tmp_path / "other"  # the same runs on a map shifted by a metre: another site's frame
    shutil.copytree(ing / "runs", other / "runs")
    shutil.copy(ing / "map.pgm", other / "map.pgm")
    doc = yaml.safe_load((ing / "map.yaml").read_text())
    doc["origin"][0] += 1.0
    (other / "map.yaml").write_text(yaml.safe_dump(doc))
    res = runner.invoke(app, ["evaluate", str(bundle), str(other), "--out", str(tmp_path / "z"), "--config", "ci"])
    assert res.exit_code == 1 and "not the site this bundle was exported for" in res.output, res.output
    res = runner.invoke(app, ["evaluate", str(tmp_path / "missing"), str(ing), "--out", str(tmp_path / "y"),
                              "--config", "ci"])
    assert res.exit_code == 1 and "missing" in res.output and "Traceback" not in res.output


def test_tracked_files_of_the_report_agree_with_metrics_and_estimates(report):
    from pipeline.evaluation.report import HEADLINE_KEYS
    from pipeline.io import tables
    from tests.tracked_files import approx, read_headline, read_plot

    _, _, _, out = report
    doc = json.loads((out / "metrics.json").read_text())
    methods = list(doc["summary"])
    assert read_headline(out) == {m: {k: approx(doc["summary"][m][k]) for k in HEADLINE_KEYS} for m in methods}
    assert set(HEADLINE_KEYS) == {"error_p90_global_m", "error_mean_converged_m", "recovered", "kidnaps",
                                  "recovered_within_15"}
    cdf = read_plot(out, "error_cdf", ["error_m", *methods])
    grid = [r["error_m"] for r in cdf]
    assert grid[:101] == [approx(0.05 * i) for i in range(101)] and grid == sorted(grid)
    for m in methods:  # recomputed from the estimates tables: every step before the replay's first kidnapping
        t = tables.read_table(out / "estimates" / f"{m}.parquet", "estimates").to_pydict()
        first: dict = {}
        for r, k, s, kid in zip(t["run"], t["trial"], t["step"], t["kidnapped"], strict=True):
            if kid and s > 0:
                first[(r, k)] = min(first.get((r, k), s), s)
        err = np.array([e for r, k, s, e in zip(t["run"], t["trial"], t["step"], t["error_xy"], strict=True)
                        if s < first.get((r, k), 10**9)])
        share = [r[m] for r in cdf]
        assert share == sorted(share) and share[-1] == approx(np.isfinite(err).mean())  # 1 when all are finite
        for r in cdf[::7]:
            assert r[m] == approx(np.mean(err <= r["error_m"] + 1e-9))
    rec = read_plot(out, "recovery_steps", ["kidnapping", *methods])
    labels = [f"{r['run']}@{k} trial {r['trial']}" for r in doc["replays"]["proposed"] for k in r["kidnaps"]]
    assert [r["kidnapping"] for r in rec] == labels and labels
    for m in methods:
        steps = {f"{r['run']}@{k} trial {r['trial']}": s for r in doc["replays"][m]
                 for k, s in zip(r["kidnaps"], r["recovery_steps"], strict=True)}
        assert [r[m] for r in rec] == [steps.get(lb) for lb in labels]  # None: never recovered (or no replay)


def test_error_cdf_and_recovery_tables_by_hand():
    from pipeline.evaluation.report import error_cdf_table, error_grid, recovery_steps_table

    assert list(error_grid(0.0)) == list(error_grid(5.0)) == [round(0.05 * i, 2) for i in range(101)]
    assert list(error_grid(6.2)[101:]) == [5.5, 6.0, 6.5]
    assert list(error_grid(26.0)[-3:]) == [20.0, 25.0, 30.0]
    a = _replay([0.0, 0.1, 7.0, 0.02], kidnaps=[3])  # global: 0.0, 0.1, 7.0
    b = _replay([np.nan, 0.3])
    columns, rows = error_cdf_table({"proposed": [a], "amcl": [b]})
    assert columns == ["error_m", "proposed", "amcl"]
    by = {r[0]: r[1:] for r in rows}
    assert rows[-1][0] == 7.0 and by[7.0] == (1.0, 0.5)  # a NaN step is a step, never under any error
    assert by[0.0] == (pytest.approx(1 / 3), 0.0) and by[0.1] == (pytest.approx(2 / 3), 0.0)
    assert by[0.3] == (pytest.approx(2 / 3), 0.5)
    replays = {"proposed": [{"run": "q0", "trial": 0, "kidnaps": [5, 9], "recovery_steps": [3, None]},
                            {"run": "q0", "trial": 1, "kidnaps": [5, 9], "recovery_steps": [4, 2]}],
               "image_only": [{"run": "q0", "trial": 0, "kidnaps": [5, 9], "recovery_steps": [None, 1]}]}
    columns, rows = recovery_steps_table(replays)
    assert columns == ["kidnapping", "proposed", "image_only"]
    assert rows == [("q0@5 trial 0", 3, None), ("q0@9 trial 0", None, 1), ("q0@5 trial 1", 4, None),
                    ("q0@9 trial 1", 2, None)]
