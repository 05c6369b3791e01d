"""`train-place`: pairs against a brute-force twin, mining, the trunk split, NetVLAD's k-means start, and
the stage on the micro site (a checkpoint `extract` loads, resumable, byte-identical on rerun)."""

import numpy as np
import pytest
import torch

from pipeline.retrieval.place_data import heading_gap, mine, pair_sets
from pipeline.retrieval.train_place import init_netvlad, split_trunk


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 8, n), rng.uniform(0, 8, n), rng.uniform(-np.pi, np.pi, n)])


def test_pair_sets_match_a_brute_force_twin():
    poses = _poses(60)
    group = np.array([f"g{i // 3}" for i in range(60)])
    p = pair_sets(poses, group, positive_m=2.0, positive_heading_deg=45, negative_m=5.0, negative_heading_deg=90,
                  min_negatives=3)
    for i in range(60):
        want_pos, want_neg = [], []
        for j in range(60):
            d = float(np.hypot(*(poses[i, :2] - poses[j, :2])))
            dth = abs((poses[i, 2] - poses[j, 2] + np.pi) % (2 * np.pi) - np.pi)
            if d <= 2.0 and dth <= np.radians(45) and group[i] != group[j]:
                want_pos.append(j)
            if d > 5.0 or dth > np.radians(90):
                want_neg.append(j)
        assert p.positives[i].tolist() == want_pos and p.negatives[i].tolist() == want_neg
        assert (i in p.anchors) == (len(want_pos) > 0 and len(want_neg) >= 3)
    # positives are never negatives
    assert all(not set(a) & set(b) for a, b in zip(p.positives, p.negatives, strict=True))
    assert heading_gap(np.array([3.0]), np.array([-3.0]))[0] == pytest.approx(2 * np.pi - 6.0)


def test_mine_takes_the_best_positive_and_hard_negatives():
    poses = np.array([[0, 0, 0], [1, 0, 0], [1.5, 0, 0], [10, 0, 0], [11, 0, 0], [12, 0, 0], [13, 0, 0]], float)
    group = np.arange(7).astype(str)
    p = pair_sets(poses, group, positive_m=2, positive_heading_deg=30, negative_m=5, negative_heading_deg=90,
                  min_negatives=2)
    sim = np.zeros((7, 7))
    sim[0, [1, 2]] = [0.2, 0.7]  # positive 2 matches best
    sim[0, [3, 4, 5, 6]] = [0.9, 0.1, 0.8, 0.0]  # the hardest negatives: 3, then 5
    rng = np.random.default_rng(0)
    for _ in range(5):
        pos, neg = mine(sim, p, np.array([0]), negatives=2, hard_pool=2, rng=rng)
        assert pos[0] == 2 and sorted(neg[0]) == [3, 5]


@pytest.mark.parametrize("trunk", ["lite0_s16", "vgg16"])
@pytest.mark.parametrize("tail", [0, 1, 2])
def test_the_split_trunk_composes_to_the_whole(trunk, tail):
    from pipeline.retrieval.backbones import assemble

    torch.manual_seed(0)
    bb = assemble(trunk).eval()
    x = torch.rand(1, 3, 48, 64)
    prefix, rest = split_trunk(bb.trunk, tail)
    with torch.no_grad():
        assert torch.allclose(rest(prefix(x)), bb.trunk(x), atol=1e-5)
    n_tail = sum(p.numel() for p in rest.parameters())
    assert (n_tail > 0) == (tail > 0)
    with pytest.raises(ValueError, match="tune_blocks"):
        split_trunk(bb.trunk, 99)


def test_netvlad_starts_from_kmeans_of_the_site_features():
    from sklearn.cluster import KMeans
    from torch import nn

    from pipeline.retrieval.place_heads import NetVLAD

    rng = np.random.default_rng(1)
    centres = np.eye(8, dtype=np.float32)[:4] * 3  # four well separated directions
    maps = [torch.from_numpy((centres[rng.integers(0, 4, 30)] + 0.05 * rng.standard_normal((30, 8))).T
                             .reshape(8, 5, 6).astype(np.float32)).half() for _ in range(6)]
    head = NetVLAD(4, 8)
    init_netvlad(head, nn.Identity(), maps, seed=0)
    found = head.centroids.detach().numpy()
    x = np.concatenate([m.float().flatten(1).T.numpy() for m in maps])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    want = KMeans(4, n_init=1, random_state=0).fit(x).cluster_centers_
    assert np.allclose(np.sort(found, axis=0), np.sort(want, axis=0), atol=1e-4)
    # each direction is assigned to its own cluster, sharply (the 100:1 start)
    with torch.no_grad():
        a = torch.softmax(head.assign(torch.from_numpy(np.eye(8, dtype=np.float32)[:4, :, None, None])).flatten(1), 1)
    assert sorted(a.argmax(1).tolist()) == [0, 1, 2, 3] and float(a.max(1).values.min()) > 0.9


PLACE_SETS = ["place.frame_stride=1", "place.epochs=2", "place.batch=2", "place.negatives=1", "place.hard_pool=2",
              "place.clusters=4", "place.tune_blocks=1", "place.positive_m=3.0", "place.positive_heading_deg=60",
              "place.negative_m=4.0", "place.device=cpu", "place.validation_run=mapping_00"]


def _train(site, out, sets=(), **kw):
    from pipeline.config import load_config
    from pipeline.retrieval.train_place import run_train_place

    cfg = load_config("ci", [*PLACE_SETS, *sets])
    return run_train_place(cfg, inputs={"data": site[1]}, outputs={"out": out}, progress=False, **kw)


def test_train_place_writes_a_checkpoint_extract_loads(micro_site, tmp_path, monkeypatch):
    import json

    from pipeline.retrieval.backbones import load_checkpoint

    out = _train(micro_site, tmp_path / "place")
    m = json.loads((out / "metrics.json").read_text())
    assert [h["epoch"] for h in m["history"]] == [0, 1, 2] and m["history"][0]["loss"] is None
    assert all(h["loss"] >= 0 for h in m["history"][1:]) and m["anchors"] >= 2
    assert m["validation_frames"] > 0 and 0 <= m["history"][-1]["validation"]["recall_at_1"] <= 1
    kept = max(m["history"], key=lambda h: (h["validation"]["recall_at_1"], h["validation"]["map_at_4"]))
    assert m["kept_epoch"] == kept["epoch"]
    bb = load_checkpoint(out / "place.safetensors")
    assert (bb.trunk_name, bb.head_kind, bb.dim) == ("lite0_s16", "netvlad", 4 * 112)
    fmap, desc = bb(torch.rand(1, 3, 72, 96))
    assert desc.shape == (1, 448) and torch.allclose(desc.norm(dim=1), torch.ones(1))
    assert (out / "training.png").stat().st_size > 0 and (out / "config.yaml").is_file()
    head = json.loads((out / "headline.json").read_text())
    assert head["held_out_recall_at_1"] == pytest.approx(kept["validation"]["recall_at_1"], abs=1e-3)
    csv = (out / "plots" / "training.csv").read_text().splitlines()
    assert csv[0] == "epoch,loss,recall_at_1,map_at_4" and len(csv) == 4

    # interrupted after its first epoch's checkpoint: the rerun resumes it and writes the same bytes
    from pipeline.io import checkpoint

    real = checkpoint.save_checkpoint

    def save_then_stop(path, state, fingerprint):
        real(path, state, fingerprint)
        if state["epoch"] == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save_checkpoint", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        _train(micro_site, tmp_path / "again")
    assert (tmp_path / "again.partial" / "checkpoint.pt").is_file() and not (tmp_path / "again").exists()
    monkeypatch.undo()
    again = _train(micro_site, tmp_path / "again")
    assert (again / "place.safetensors").read_bytes() == (out / "place.safetensors").read_bytes()
    assert not (tmp_path / "again.partial").exists()


def test_train_place_names_what_is_missing(micro_site, tmp_path):
    from pipeline.errors import InputError

    with pytest.raises(InputError, match="validation_run 'nope' is not a mapping run"):
        _train(micro_site, tmp_path / "a", ["place.validation_run=nope"])
    with pytest.raises(InputError, match="have a positive"):
        _train(micro_site, tmp_path / "b", ["place.positive_m=0.01", "place.negative_m=0.02"])
