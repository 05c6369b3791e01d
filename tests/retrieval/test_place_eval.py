"""evaluate-places: pooling against closed forms, the figures against a brute-force count, and the
command end to end on a generated place set."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from PIL import Image
from typer.testing import CliRunner

from pipeline.retrieval.descriptors import ipa_descriptor
from pipeline.retrieval.place_eval import measure, pool


def test_pooling_closed_forms():
    rng = np.random.default_rng(0)
    fmap = rng.normal(size=(6, 4, 5)).astype(np.float32)
    np.testing.assert_allclose(pool(fmap, "sum"), ipa_descriptor(fmap), atol=1e-6)
    pos = np.abs(fmap) + 0.1
    mean = pos.reshape(6, -1).mean(axis=1)
    np.testing.assert_allclose(pool(pos, "gem", p=1.0), mean / np.linalg.norm(mean), atol=1e-6)
    mx = pos.reshape(6, -1).max(axis=1)
    np.testing.assert_allclose(pool(pos, "gem", p=200.0), mx / np.linalg.norm(mx), atol=2e-2)  # p -> inf: max
    # negative activations (a linear bottleneck) are clamped, not raised to a fractional power
    assert np.all(np.isfinite(pool(-pos, "gem")))
    with pytest.raises(ValueError, match="pooling must be one of"):
        pool(fmap, "max")


def test_figures_against_a_brute_force_count():
    rng = np.random.default_rng(1)
    db = rng.normal(size=(30, 8)).astype(np.float32)
    q = rng.normal(size=(12, 8)).astype(np.float32)
    positive = rng.random((12, 30)) < 0.1
    positive[0] = False  # a query without a true match counts in no figure
    figures, ranked = measure(db, q, positive)
    sims = q @ db.T
    has = [i for i in range(12) if positive[i].any()]
    for n in (1, 5, 10):
        hits = [any(positive[i, j] for j in sorted(range(30), key=lambda j: -sims[i, j])[:n]) for i in has]
        assert figures[f"recall@{n}"] == pytest.approx(np.mean(hits), abs=1e-4)
    aps = []
    for i in has:
        order = sorted(range(30), key=lambda j: -sims[i, j])[:4]
        hits, ap = 0, 0.0
        for k, j in enumerate(order, start=1):
            if positive[i, j]:
                hits += 1
                ap += hits / k
        aps.append(ap / min(4, positive[i].sum()))
    assert figures["map@4"] == pytest.approx(np.mean(aps), abs=1e-4)
    assert ranked.shape == (12, 30)


def scene(seed: int) -> np.ndarray:
    """A distinct 'place': coloured shapes at random on a coloured wall."""
    from PIL import ImageDraw

    rng = np.random.default_rng(seed)
    im = Image.new("RGB", (160, 120), tuple(int(v) for v in rng.integers(0, 255, 3)))
    draw = ImageDraw.Draw(im)
    for _ in range(12):
        x, y, w, h = rng.integers(0, 160), rng.integers(0, 120), rng.integers(10, 60), rng.integers(10, 60)
        shape = draw.ellipse if rng.random() < 0.5 else draw.rectangle
        shape([x, y, x + w, y + h], fill=tuple(int(v) for v in rng.integers(0, 255, 3)))
    return np.asarray(im)


def seen_again(root, n: int):
    """A place set of `n` scenes (ref/) each seen again (query/), matched by position: query k is ref k a
    few pixels to the side, a little darker (pixel noise on flat synthetic walls changes ImageNet features
    more than another scene does: not a trait of photographs)."""
    (root / "ref").mkdir(parents=True)
    (root / "query").mkdir()
    for k in range(n):
        base = scene(k)
        Image.fromarray(base).save(root / "ref" / f"{k}.png")
        again = np.roll(base, (3, 5), axis=(0, 1)).astype(float) * 0.9
        Image.fromarray(np.clip(again, 0, 255).astype(np.uint8)).save(root / "query" / f"{k}.png")
    (root / "place_set.yaml").write_text(yaml.safe_dump({"database": "ref", "queries": "query",
                                                          "positives": {"aligned": 0}}))
    return root


def test_the_command_on_a_generated_place_set(tmp_path):
    from stages.app import app

    root = seen_again(tmp_path / "set", 8)
    Image.fromarray(scene(99)).save(root / "query" / "7.png")  # its place repainted: nothing alike to find
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["evaluate-places", str(root), "--out", str(out), "--backbone", "lite0_s16",
                                   "--whitening", "none", "--whitening", "shrinkage", "--scales", "1",
                                   "--scales", "1/2"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "metrics.json").read_text())
    assert len(doc["variants"]) == 2 * 2 * 2 and doc["queries_with_positives"] == 8
    base = next(v for v in doc["variants"] if v["variant"] == doc["baseline"])
    assert base["variant"] == "lite0_s16 sum none"
    assert base["recall@1"] == pytest.approx(7 / 8)  # the seven places seen again are found
    best = next(v for v in doc["variants"] if v["variant"] == doc["best"])
    assert best["recall@1"] >= base["recall@1"]
    assert doc["misses"]["wrong"] == round((1 - best["recall@1"]) * 8) and doc["misses"]["queries"] == 8
    assert (out / "misses.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| lite0_s16 sum none |" in (out / "report.md").read_text()
    assert (out / "config.yaml").is_file()


def test_the_command_refuses_unknown_choices_in_one_line(tmp_path):
    from stages.app import app

    for args, message in ((["--pooling", "max"], "--pooling max: expected one of sum, gem"),
                          (["--scales", "1/x"], "--scales '1/x': numbers joined by /"),
                          (["--weights", "lite0_s16"], "expected BACKBONE=FILE"),
                          (["--backbone", "detector"], "--backbone detector: expected one of lite0_s16")):
        res = CliRunner().invoke(app, ["evaluate-places", str(tmp_path), "--out", str(tmp_path / "o"), *args])
        assert res.exit_code == 1 and message in res.output, res.output


def test_rpa_reranking_permutes_the_top_n_by_region_matches():
    from pipeline.retrieval.place_rerank import Regions, reranked
    from pipeline.retrieval.whitening import l2_normalize

    rng = np.random.default_rng(3)
    per_image = [l2_normalize(rng.normal(size=(3, 16))) for _ in range(6)]
    db = Regions(np.concatenate(per_image), np.arange(0, 19, 3), [np.arange(3)] * 6)
    # query 0 shows database image 4's regions; query 1 shows image 0's, which its first stage ranks last
    q_rows = np.concatenate([per_image[4], per_image[0]])
    queries = Regions(q_rows, np.array([0, 3, 6]), [np.arange(3), np.arange(3)])
    first = np.array([[1, 2, 4, 3, 5, 0], [5, 4, 3, 2, 1, 0]])
    out = reranked(first, db, queries, whiten=False, top_n=4)
    assert out[0, 0] == 4 and sorted(out[0, :4]) == sorted(first[0, :4])  # a permutation of the Top-4
    np.testing.assert_array_equal(out[0, 4:], first[0, 4:])  # the rest as the first stage left it
    np.testing.assert_array_equal(out[1, 4:], first[1, 4:])  # image 0 is outside the Top-4: not found
    assert sorted(out[1, :4]) == sorted(first[1, :4])


def test_the_command_reranks_with_a_detector(tmp_path, micro_site):
    from stages.app import app

    _, _, model = micro_site
    root = seen_again(tmp_path / "set", 5)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["evaluate-places", str(root), "--out", str(out), "--backbone", "lite0_s16",
                                   "--pooling", "sum", "--whitening", "none", "--whitening", "pca",
                                   "--detector", str(model), "--set", "retrieval.top_n=3"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "metrics.json").read_text())
    labels = [v["variant"] for v in doc["variants"]]
    assert labels == ["lite0_s16 sum none", "lite0_s16 sum pca", "lite0_s16 sum none +rpa", "lite0_s16 sum pca +rpa"]
    plain, rpa = doc["variants"][0], doc["variants"][2]
    assert rpa["rerank"] == "rpa top 3" and rpa["recall@5"] == plain["recall@5"]  # only the Top-3 move
    assert "| lite0_s16 sum none +rpa |" in (out / "report.md").read_text()
