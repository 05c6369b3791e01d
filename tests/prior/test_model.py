"""The area prior's database: ball tree against brute force, scoring, persistence, incremental append."""

import numpy as np
import pytest

from pipeline.prior.model import MEASURES, AreaPrior, PriorSettings

LAYERS = {"low": 40, "mid": 30, "high": 20}
ENCODER = {"backbone": "test", "layers": list(LAYERS)}


def make_images(rng, classes, per_class, noise=0.3, centres=None):
    """Clustered raw vectors per layer: images of one (room, area) share a centre."""
    centres = centres or {n: {c: rng.standard_normal(d) for c in classes} for n, d in LAYERS.items()}
    meta = {k: [] for k in ("image_id", "stop_id", "room", "area", "split", "x", "y", "theta")}
    raw = {n: [] for n in LAYERS}
    for ci, (room, area) in enumerate(classes):
        for i in range(per_class):
            meta["image_id"].append(f"images/{room}_{area}_{i}_{rng.integers(1 << 30)}.jpg")
            meta["stop_id"].append(f"{room}{area}{i // 3}")
            meta["room"].append(room)
            meta["area"].append(area)
            meta["split"].append("train")
            meta["x"].append(float(2 * ci + (i // 3) * 0.2))
            meta["y"].append(1.0)
            meta["theta"].append(0.0)
            for n in LAYERS:
                raw[n].append(centres[n][(room, area)] + noise * rng.standard_normal(LAYERS[n]))
    return meta, {n: np.asarray(v, dtype=np.float32) for n, v in raw.items()}, centres


CLASSES = [("R0", "a"), ("R0", "b"), ("R1", "a"), ("R1", "b"), ("R2", "a")]


def build(meta, raw, compression="ipca", measure="spearman", k=5):
    return AreaPrior.build(meta, raw, compression=compression, n_components=8, seed=0,
                           settings=PriorSettings(k=k, measure=measure, layer_weights=(0.5, 0.3, 0.2)),
                           encoder=ENCODER)


@pytest.fixture(scope="module")
def site():
    rng = np.random.default_rng(0)
    meta, raw, centres = make_images(rng, CLASSES, 9)
    qmeta, qraw, _ = make_images(rng, CLASSES, 3, centres=centres)
    return meta, raw, qmeta, qraw, centres


def test_ball_tree_neighbours_are_the_brute_force_ones(site):
    meta, raw, _, qraw, _ = site
    prior = build(meta, raw)
    comp = prior.compress(qraw)
    found = prior.neighbours(comp)
    for n in LAYERS:
        d = np.linalg.norm(comp[n][:, None] - prior.vectors[n][None], axis=2)
        np.testing.assert_array_equal(np.sort(found[n][1], axis=1), np.sort(np.argsort(d, axis=1)[:, :5], axis=1))
        np.testing.assert_allclose(found[n][0], np.sort(d, axis=1)[:, :5], rtol=1e-5)


def test_brute_force_index_gives_the_trees_neighbours(site):
    meta, raw, _, qraw, _ = site
    tree = build(meta, raw)
    brute = build(meta, raw)
    brute.settings.index = "brute"
    comp = tree.compress(qraw)
    a, b = tree.neighbours(comp), brute.neighbours(comp)
    for n in LAYERS:
        np.testing.assert_array_equal(a[n][1], b[n][1])
        np.testing.assert_allclose(a[n][0], b[n][0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(tree.probabilities(qraw), brute.probabilities(qraw), atol=1e-9)


@pytest.mark.parametrize("measure", MEASURES)
def test_separable_classes_are_found_and_probabilities_sum_to_one(site, measure):
    meta, raw, qmeta, qraw, _ = site
    prior = build(meta, raw, measure=measure)
    probs = prior.probabilities(qraw)
    np.testing.assert_allclose(probs.sum(axis=1), 1.0)
    assert np.all(probs >= 0)
    want = [prior.classes.index((r, a)) for r, a in zip(qmeta["room"], qmeta["area"], strict=True)]
    np.testing.assert_array_equal(probs.argmax(axis=1), want)


def test_spearman_class_score_is_the_best_neighbour_similarity(site):
    """One layer, hand-computed: a class's probability is its best neighbour's (1 + rho) / 2, normalised."""
    from scipy.stats import spearmanr

    meta, raw, _, qraw, _ = site
    prior = build(meta, raw)
    comp = prior.compress({n: v[:1] for n, v in qraw.items()})
    _, idx = prior.neighbours(comp)["low"]
    scores = {}
    for i in idx[0]:
        s = (1 + spearmanr(comp["low"][0], prior.vectors["low"][i]).statistic) / 2
        c = int(prior.labels[i])
        scores[c] = max(scores.get(c, 0.0), s)
    total = sum(scores.values())
    got = prior.layer_probabilities(comp)["low"][0]
    for c, s in scores.items():
        assert got[c] == pytest.approx(s / total, rel=1e-6)
    assert got.sum() == pytest.approx(1.0)


def test_layer_weights_select_the_layer(site):
    meta, raw, _, qraw, _ = site
    prior = build(meta, raw)
    per = prior.layer_probabilities(prior.compress(qraw))
    np.testing.assert_allclose(prior.combine(per, (0, 1, 0)), per["mid"])
    with pytest.raises(ValueError, match="layer weights"):
        prior.combine(per, (1, 0))


@pytest.mark.parametrize("compression", ["ipca", "srp", "kpca"])
def test_save_load_round_trip(site, tmp_path, compression):
    meta, raw, _, qraw, _ = site
    prior = build(meta, raw, compression=compression, measure="gaussian")
    prior.save(tmp_path / "p")
    back = AreaPrior.load(tmp_path / "p")
    assert back.classes == prior.classes and back.layers == prior.layers
    np.testing.assert_array_equal(back.labels, prior.labels)
    np.testing.assert_array_equal(back.probabilities(qraw), prior.probabilities(qraw))


def test_load_refuses_what_is_not_a_prior(tmp_path):
    from pipeline.errors import InputError

    with pytest.raises(InputError, match="not an area prior"):
        AreaPrior.load(tmp_path)
    (tmp_path / "prior.json").write_text('{"format": "other", "version": "9.0"}')
    with pytest.raises(InputError, match="not readable"):
        AreaPrior.load(tmp_path)


def test_append_leaves_the_old_database_and_old_queries_unchanged(site):
    meta, raw, qmeta, qraw, centres = site
    prior = build(meta, raw)
    old = {n: prior.vectors[n].copy() for n in LAYERS}
    gauss = {n: prior.gaussians[n].chol_.copy() for n in LAYERS}
    comps = {n: prior.compressors[n].transform(qraw[n]) for n in LAYERS}
    before = prior.probabilities(qraw)
    rng = np.random.default_rng(9)
    new_classes = [("R9", "a"), ("R9", "b")]
    nmeta, nraw, ncentres = make_images(rng, new_classes, 6)
    touched = prior.append(nmeta, nraw)
    assert touched == [len(CLASSES), len(CLASSES) + 1]
    for n in LAYERS:
        np.testing.assert_array_equal(prior.vectors[n][: len(old[n])], old[n])
        np.testing.assert_array_equal(prior.gaussians[n].chol_[: len(CLASSES)], gauss[n])
        np.testing.assert_array_equal(prior.compressors[n].transform(qraw[n]), comps[n])
    after = prior.probabilities(qraw)
    # the new area is far from the old ones: no old query has a new neighbour, and nothing changes for them
    found = prior.neighbours(prior.compress(qraw))
    assert all(np.all(found[n][1] < len(old[n])) for n in LAYERS)
    np.testing.assert_array_equal(after[:, : len(CLASSES)], before)
    assert np.all(after[:, len(CLASSES):] == 0)
    # and the new area's own queries are recognised
    qn, qnraw, _ = make_images(rng, new_classes, 2, centres=ncentres)
    got = prior.probabilities(qnraw).argmax(axis=1)
    np.testing.assert_array_equal(got, [prior.classes.index((r, a)) for r, a in zip(qn["room"], qn["area"],
                                                                                     strict=True)])


def test_append_equals_building_with_the_same_compressions(site):
    """Appending in two steps gives the same database as adding everything at once with the same fits
    (to float32 rounding: a matrix product over half the rows may sum in another order than over all of
    them, as AVX2 kernels do; one ulp, measured on an AMD EPYC)."""
    meta, raw, _, qraw, _ = site
    half = len(meta["image_id"]) // 2
    first = {k: v[:half] for k, v in meta.items()}
    rest = {k: v[half:] for k, v in meta.items()}
    a = build(first, {n: v[:half] for n, v in raw.items()})
    comps = a.compressors
    a.append(rest, {n: v[half:] for n, v in raw.items()})
    b = AreaPrior(a.layers, comps, a.settings, ENCODER)
    b._add(meta, raw)
    for n in LAYERS:
        np.testing.assert_allclose(a.vectors[n], b.vectors[n], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(a.labels, b.labels)


def test_area_cells_are_the_nearest_stop_within_the_radius():
    from pipeline.io.map_yaml import FREE, OccupancyMap
    from pipeline.runtime.grid import LaserMap

    grid = np.full((20, 40), FREE, dtype=np.int8)
    grid[0, :] = 100
    lmap = LaserMap.from_occupancy(OccupancyMap(grid=grid, resolution=0.1))
    rng = np.random.default_rng(1)
    meta, raw, _ = make_images(rng, [("R0", "a"), ("R1", "a")], 3)
    meta["x"] = [0.5, 0.5, 0.5, 3.0, 3.0, 3.0]
    prior = build(meta, raw, k=3)
    cells = prior.area_cells(lmap, radius_m=1.0)
    row, col = np.divmod(lmap.free_cells, lmap.width)
    x, y = (col + 0.5) * 0.1, (row + 0.5) * 0.1
    d0, d1 = np.hypot(x - 0.5, y - 1.0), np.hypot(x - 3.0, y - 1.0)
    want = np.where(d0 <= d1, 0, 1)
    want[np.minimum(d0, d1) > 1.0] = -1
    np.testing.assert_array_equal(cells, want)


def test_memory_is_the_compression_plus_the_database(site):
    meta, raw, _, _, _ = site
    for comp in ("srp", "kpca", "none"):
        prior = build(meta, raw, compression=comp)
        for n in LAYERS:
            want = prior.compressors[n].nbytes() + prior.vectors[n].size * 4
            assert prior.nbytes()[n] == want
    assert build(meta, raw, compression="none").nbytes()["low"] == len(meta["image_id"]) * LAYERS["low"] * 4


def test_replace_keeps_untouched_rows_and_classes_bit_for_bit(site):
    """One class re-captured (its rows replaced), one gone, one new: kept rows and the Gaussians of
    untouched classes are as they were; the touched ones equal a fresh fit of their rows."""
    from pipeline.prior.scoring import ClassGaussians

    meta, raw, _, qraw, centres = site
    prior = build(meta, raw)
    old_vec = {n: prior.vectors[n].copy() for n in LAYERS}
    old_g = {n: {f: v.copy() for f, v in prior.gaussians[n].arrays().items()} for n in LAYERS}
    rows = np.asarray(list(zip(meta["room"], meta["area"], strict=True)), dtype=object)
    recaptured, gone = ("R1", "a"), ("R2", "a")
    keep = np.array([tuple(c) not in (recaptured, gone) for c in rows])
    rng = np.random.default_rng(5)
    shifted = {n: {recaptured: centres[n][recaptured] + 0.5} for n in LAYERS}
    nmeta, nraw, _ = make_images(rng, [recaptured], 7, centres=shifted)
    wmeta, wraw, _ = make_images(rng, [("R7", "a")], 4)
    both = {k: nmeta[k] + wmeta[k] for k in nmeta}
    braw = {n: np.vstack([nraw[n], wraw[n]]) for n in LAYERS}
    change = prior.replace(keep, both, braw)

    assert change["kept"] == keep.sum() and change["dropped"] == (~keep).sum() and change["added"] == 11
    assert change["removed_classes"] == [list(gone)] and change["new_classes"] == [["R7", "a"]]
    assert change["refitted_classes"] == [list(recaptured)]
    assert prior.classes == [("R0", "a"), ("R0", "b"), ("R1", "a"), ("R1", "b"), ("R7", "a")]
    assert prior.rows["image_id"] == [i for i, k in zip(meta["image_id"], keep, strict=True) if k] + both["image_id"]
    untouched = {("R0", "a"): 0, ("R0", "b"): 1, ("R1", "b"): 3}  # class -> its number before
    for n in LAYERS:
        np.testing.assert_array_equal(prior.vectors[n][: keep.sum()], old_vec[n][keep])
        np.testing.assert_array_equal(prior.vectors[n][keep.sum():], prior.compressors[n].transform(braw[n]))
        g = prior.gaussians[n]
        for c, before in untouched.items():
            k = prior.classes.index(c)
            for f in ("mean_", "chol_", "logdet_", "alpha_", "count_"):
                np.testing.assert_array_equal(getattr(g, f)[k], old_g[n][f][before])
        # the touched classes: a fresh fit of their rows with the build's pooled scale
        twin = ClassGaussians(g.shrinkage)
        twin.sigma2_, twin.mean_ = g.sigma2_, np.zeros((0, g.mean_.shape[1]))
        twin.chol_, twin.logdet_ = np.zeros((0,) + g.chol_.shape[1:]), np.zeros(0)
        twin.alpha_, twin.count_ = np.zeros(0), np.zeros(0, dtype=np.int64)
        twin.update(prior.vectors[n], prior.labels, range(len(prior.classes)))
        for c in (recaptured, ("R7", "a")):
            k = prior.classes.index(c)
            np.testing.assert_allclose(g.mean_[k], twin.mean_[k], rtol=1e-12)
            np.testing.assert_allclose(g.chol_[k], twin.chol_[k], rtol=1e-10, atol=1e-12)
            assert g.count_[k] == (prior.labels == k).sum()
    # queries work and never name the class that went
    probs = prior.probabilities(qraw)
    assert probs.shape == (len(qraw["low"]), 5)
    np.testing.assert_allclose(probs.sum(axis=1), 1.0)
