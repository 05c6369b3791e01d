"""Image-sequence re-localization at run time: the bundle's sequence files, the ring buffer, the closed loop."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.runtime.bundle import BundleError


def test_the_bundle_carries_the_checked_sequence_models(micro_sequence_bundle):
    from pipeline.runtime.bundle import verify_bundle
    from pipeline.runtime.sequence import FILES

    cfg, _, seq, bundle = micro_sequence_bundle
    assert set(FILES) <= set(verify_bundle(bundle)["files"])
    meta = json.loads((bundle / "models" / "sequence.json").read_text())
    assert meta["length"] == cfg.sequence.length
    assert meta["frames"]["parity"]["max_abs"] <= meta["frames"]["parity"]["tolerance"]
    assert max(meta["lstm_parity"]["max_abs_by_length"].values()) <= meta["lstm_parity"]["tolerance"]
    assert (bundle / "sequence" / "database.parquet").read_bytes() == (seq / "database.parquet").read_bytes()


def test_sequence_candidates_match_the_torch_model_searched_by_hand(micro_sequence_bundle):
    """Frames through the ONNX graphs give the Top-4 that torch's encoder + LSTM + whitening + a full sort give."""
    import torch

    from pipeline.detection.inference import load_image
    from pipeline.evaluation.replay import load_run
    from pipeline.io import tables
    from pipeline.retrieval.whitening import PCAWhitening
    from pipeline.runtime.sequence import SequenceRelocaliser
    from pipeline.sequence.frames import FrameEncoder
    from pipeline.sequence.onnx_export import load_sequence_model

    cfg, ing, seq, bundle = micro_sequence_bundle
    run = load_run(sorted((ing / "runs").glob("query_*.parquet"))[0])
    images = [ing / i for i in run.image_ids[: cfg.sequence.length + 2]]
    reloc = SequenceRelocaliser(bundle)
    for im in images:
        reloc.push(im)
    assert len(reloc.buffer) == cfg.sequence.length and reloc.ready  # a ring: the oldest frames fell out
    got = reloc.candidates((4.0, 3.0, 2.0, 1.0))

    enc = FrameEncoder(cfg.sequence.frame_weights, cfg.sequence.frame_size)
    logits = enc([load_image(p) for p in images[-cfg.sequence.length:]])
    model, _ = load_sequence_model(seq)
    with torch.no_grad():
        pooled = model.describe(torch.from_numpy(logits)[None]).numpy()
    q = PCAWhitening.load(seq / "whitening.npz").transform(pooled)[0]
    db = tables.read_table(seq / "database.parquet", "sequences")
    top = np.argsort(-(tables.descriptor_matrix(db) @ q), kind="stable")[:4]
    want = np.column_stack([db.column(c).to_numpy()[top] for c in ("x", "y", "theta")])
    np.testing.assert_allclose(got[:, :3], want, atol=1e-6)
    np.testing.assert_allclose(got[:, 3], [0.4, 0.3, 0.2, 0.1])
    reloc.keep_last(1)
    assert len(reloc.buffer) == 1 and not reloc.ready
    reloc.keep_last(0)
    with pytest.raises(BundleError, match="no frames"):
        reloc.candidates()


class StubFilter:
    """A filter whose state the test scripts; records what the Localizer injects."""

    def __init__(self, states):
        from pipeline.runtime.amcl import FilterState

        self.script = [FilterState(s) for s in states]
        self.state = FilterState.RELOCALISING
        self.injected: list[tuple[int, np.ndarray]] = []
        self.step = 0
        self.particles = np.zeros((10, 3))

    def init_candidates(self, poses, weights):
        pass

    def init_uniform(self):
        pass

    def inject(self, poses, weights, std_theta=None):
        self.injected.append((self.step, np.asarray(weights), std_theta))

    def update(self, odometry, scan):
        self.state = self.script[self.step]
        self.step += 1
        return SimpleNamespace(pose=np.zeros(3), covariance=np.eye(3), state=self.state, particles=10, updated=True,
                               best_likelihood=1.0)


def test_closed_loop_injects_the_sequence_every_step_from_lost_until_tracking(micro_sequence_bundle):
    from pipeline.runtime.localizer import Localizer

    _, ing, _, bundle = micro_sequence_bundle
    loc = Localizer.from_bundle(bundle)
    length = loc.sequence.length  # 3
    fc = loc.filter_config
    loc.filter_config = fc.model_copy(update={"relocalise_with": "sequence", "sequence_confirm_steps": 0,
                                              "kidnap": fc.kidnap.model_copy(update={"updates": 1})})
    loc.reset()
    n = {"v": 0}

    def encode(image):  # a distinct vector per frame; the real encoder is checked above
        n["v"] += 1
        return np.full(1000, float(n["v"]), np.float32)

    loc.sequence.encode = encode
    loc.retrieved = lambda image: np.array([[1.0, 2.0, 0.0], [3.0, 4.0, 0.0], [5.0, 6.0, 0.0], [7.0, 8.0, 0.0]])
    # Lost for two updates (nothing injected yet): the buffer is trimmed once, at the first.
    states = ["tracking"] * 4 + ["lost", "lost"] + ["relocalising"] * 4 + ["tracking"] * 3
    loc.camera.filter = StubFilter(states)
    loc.camera.started = True
    loc.camera.seeded_by_camera = True
    sources = [loc.update(np.zeros(3), None, image="frame").source for _ in states]
    lost_at = states.index("lost")  # the result of update 4; update 5 sees it
    # Update 5 keeps the 1 frame the kidnap rule counted plus its own; ready once `length` frames: update 6.
    first = lost_at + 1 + (length - 2)
    assert sources[:first] == [None] * first
    back = len(states) - 3  # the first update whose previous result was tracking again
    assert sources[first:back + 1] == ["sequence"] * (back + 1 - first)
    assert sources[back + 1:] == [None] * (len(states) - back - 1)
    assert [s for s, _, _ in loc.filter.injected] == list(range(first, back + 1))
    # Frames are encoded only for the queries, each once: the 3 of the first query, then one new a step.
    assert n["v"] == length + (back - first)
    for _, w, spread in loc.filter.injected:
        np.testing.assert_allclose(w.sum(), 1.0)  # injection weights stay normalised
        assert spread == pytest.approx(np.radians(fc.sequence_heading_std_deg))

    # Both, injecting the image only when declared lost: the image then, the sequence once ready.
    loc.filter_config = loc.filter_config.model_copy(update={"relocalise_with": "both",
                                                             "inject_while_relocalising": False})
    loc.reset()
    loc.sequence.encode = encode
    loc.camera.filter, loc.camera.started, loc.camera.seeded_by_camera = StubFilter(states), True, True
    sources = [loc.update(np.zeros(3), None, image="frame").source for _ in states]
    assert sources[lost_at + 1] == "image" and sources[first:back + 1] == ["sequence"] * (back + 1 - first)
    # ... and injecting the image while re-localizing: every update from lost to tracking, with the sequence
    # once it is ready (each source's Top-4 at half weight).
    loc.filter_config = loc.filter_config.model_copy(update={"inject_while_relocalising": True})
    loc.reset()
    loc.sequence.encode = encode
    loc.camera.filter, loc.camera.started, loc.camera.seeded_by_camera = StubFilter(states), True, True
    sources = [loc.update(np.zeros(3), None, image="frame").source for _ in states]
    assert sources[lost_at + 1:first] == ["image"] * (first - lost_at - 1)
    assert sources[first:back + 1] == ["sequence+image"] * (back + 1 - first)
    assert sources[back + 1:] == [None] * (len(states) - back - 1)
    _, w, spread = loc.filter.injected[-1]
    np.testing.assert_allclose(w, np.r_[[0.4, 0.3, 0.2, 0.1], [0.4, 0.3, 0.2, 0.1]] / 2)
    np.testing.assert_allclose(spread, np.radians([fc.sequence_heading_std_deg] * 4 + [fc.init_std_theta_deg] * 4))

    # With confirmation steps the sequence keeps proposing for that many updates after tracking resumes.
    loc.filter_config = loc.filter_config.model_copy(update={"relocalise_with": "sequence",
                                                             "sequence_confirm_steps": 2})
    loc.reset()
    loc.sequence.encode = encode
    cam = loc.camera
    cam.filter, cam.started, cam.seeded_by_camera = StubFilter(states + ["tracking"] * 3), True, True
    sources = [loc.update(np.zeros(3), None, image="frame").source for _ in states + ["tracking"] * 3]
    assert sources[first:back + 3] == ["sequence"] * (back + 3 - first) and sources[back + 3:] == [None] * 3


def test_a_bundle_without_or_with_half_the_sequence_files_is_refused_for_it(micro_bundle, micro_sequence_bundle,
                                                                            tmp_path):
    import yaml

    from pipeline.runtime.bundle import read_manifest
    from pipeline.runtime.localizer import Localizer
    from pipeline.runtime.sequence import has_sequence

    bundle = micro_bundle[4]
    settings = yaml.safe_load((bundle / "filter.yaml").read_text())
    settings["filter"]["relocalise_with"] = "sequence"
    with pytest.raises(BundleError, match="no sequence model.*--sequence"):
        Localizer(bundle, read_manifest(bundle), settings)
    plain = Localizer.from_bundle(bundle)
    assert plain.sequence is None and plain.relocalise_with == "image"  # auto, without a sequence model
    assert Localizer.from_bundle(micro_sequence_bundle[3]).relocalise_with == "both"
    half = tmp_path / "half"
    shutil.copytree(micro_sequence_bundle[3], half)
    (half / "models" / "sequence.onnx").unlink()
    with pytest.raises(BundleError, match="incomplete.*sequence.onnx"):
        has_sequence(half)


def test_export_refuses_a_sequence_model_whose_frames_were_encoded_otherwise(micro_bundle, micro_sequence_bundle,
                                                                            tmp_path):
    from pipeline.bundle.export import run_export
    from pipeline.errors import InputError

    _, ing, model, index, _ = micro_bundle
    cfg, _, seq, _ = micro_sequence_bundle
    assert json.loads((seq / "config.json").read_text())["frame_encoder"]["frame_size"] == str(cfg.sequence.frame_size)
    other = cfg.model_copy(update={"sequence": cfg.sequence.model_copy(update={"frame_size": 48})})
    with pytest.raises(InputError, match="encoded otherwise") as err:
        run_export(other, inputs={"model": model, "index": index, "data": ing, "sequence": seq},
                   outputs={"out": tmp_path / "b"})
    assert "size 48" in err.value.render()
    leftovers = list((tmp_path / "b").glob("*")) if (tmp_path / "b").exists() else []
    assert leftovers == []  # nothing published
    with pytest.raises(InputError, match="4 required files missing") as err:  # refused before any export work
        run_export(cfg, inputs={"model": model, "index": index, "data": ing, "sequence": tmp_path / "none"},
                   outputs={"out": tmp_path / "c"})
    assert "point --sequence at" in err.value.render() and not (tmp_path / "c").exists()


def _far_poses(loc, truth, n=5):
    """n free poses more than 4 m from the truth and 3 m from each other: no view is near another's."""
    far = []
    for pose in loc.map.sample_free(4000, np.random.default_rng(3)):
        if np.hypot(*(pose[:2] - truth[:2])) > 4.0 and all(np.hypot(*(pose[:2] - p[:2])) > 3.0 for p in far):
            far.append(pose)
    assert len(far) >= n
    return np.asarray(far[:n])


def _weigh(loc, estimate, scan):
    """One weighing of the camera path against a tracked `estimate` (no motion in between)."""
    from pipeline.runtime.amcl import FilterState

    loc.camera._ranked_for = None
    return loc.camera._weigh(np.zeros(3), SimpleNamespace(pose=np.asarray(estimate), state=FilterState.TRACKING),
                             "frame", scan)


def test_a_hypothesis_the_scan_and_the_image_prefer_replaces_a_wrong_belief(micro_sequence_bundle):
    """filter.camera: a far pose the image ranks above the estimate and the scan fits better collects
    log(1 + rank of the estimate) - log(1 + its rank), plus laser_nats when the laser tells the two
    apart, per check; at the threshold, after min_checks, the belief is replaced by one around it (and
    the sequence stops waiting to confirm). With the estimate right, poses that fit worse are dropped."""
    from pipeline.evaluation.replay import load_run
    from pipeline.runtime.amcl import FilterState
    from pipeline.runtime.localizer import Localizer

    _, ing, _, bundle = micro_sequence_bundle
    loc = Localizer.from_bundle(bundle)
    cam = loc.filter_config.camera
    assert cam.every >= 1 and cam.max_rank is not None
    run = load_run(sorted((ing / "runs").glob("query_*.parquet"))[0])
    t = len(run) // 2
    truth, scan = run.gt[t], loc.scan(run.ranges[t])
    far = _far_poses(loc, truth)
    loc.retrieved = lambda image: np.vstack([truth + [0.2, -0.1, 0.1], far[1:]])
    loc.filter.init_pose(far[0])
    loc.camera.awaiting_sequence = True
    # far[0] has no view among the five ranked: rank 5 (under max_rank), the truth's rank 0; the scan fits
    # the truth, not far[0], so the laser adds laser_nats at each check.
    verifier, how = loc.verifier, loc.camera.weighing
    beams = verifier.beams(scan)[0].size
    ll = [check_candidates_once(verifier, loc.map, p, scan, how) for p in (truth, far[0])]
    assert (ll[0] - ll[1]) / beams > cam.distinct
    per_check = np.log(6.0) + cam.laser_nats
    need = max(cam.min_checks, int(np.ceil(cam.threshold / per_check)))
    for k in range(1, need):
        assert _weigh(loc, far[0], scan) is None
        assert loc.camera.hypotheses.evidence.max() == pytest.approx(k * per_check)
    got = _weigh(loc, far[0], scan)
    assert got is not None and np.hypot(*(got[:2] - truth[:2])) < 0.6
    assert loc.filter.state == FilterState.TRACKING and not loc.camera.awaiting_sequence
    assert np.hypot(*(loc.filter.estimate.pose[:2] - truth[:2])) < 0.6

    # The estimate right: ranked poses that do not fit the scan are never followed.
    loc.retrieved = lambda image: far[1:]
    loc.filter.init_pose(truth)
    for _ in range(need + 2):
        assert _weigh(loc, truth, scan) is None
    assert len(loc.camera.hypotheses.poses) == 0


def check_candidates_once(verifier, lmap, pose, scan, how):
    """A pose's best refined fit, as the weighing scores it."""
    from pipeline.runtime.scancheck import check_candidates

    got = check_candidates(verifier, lmap, np.asarray(pose)[None], scan, keep=1, samples=how.samples,
                           std_xy=how.std_xy, std_theta=how.std_theta, rng=np.random.default_rng(0), rounds=how.rounds)
    return float(got.log_likelihood[0])


def test_a_settled_belief_needs_the_settled_threshold(micro_sequence_bundle):
    """After settled_updates tracked updates without a jump, a hypothesis needs settled_threshold."""
    from pipeline.evaluation.replay import load_run
    from pipeline.runtime.localizer import Localizer

    _, ing, _, bundle = micro_sequence_bundle
    loc = Localizer.from_bundle(bundle)
    fc = loc.filter_config
    cam = fc.camera.model_copy(update={"min_checks": 1})
    loc.filter_config = fc.model_copy(update={"camera": cam})
    loc.reset()
    run = load_run(sorted((ing / "runs").glob("query_*.parquet"))[0])
    t = len(run) // 2
    truth, scan = run.gt[t], loc.scan(run.ranges[t])
    far = _far_poses(loc, truth)
    loc.retrieved = lambda image: np.vstack([truth + [0.2, -0.1, 0.1], far[1:]])
    loc.filter.init_pose(far[0])
    for _ in range(cam.settled_updates + 1):  # tracked without a jump: settled
        loc.camera.hypotheses.follow(np.zeros(3), far[0], tracking=True, jump_m=cam.min_distance_m)
    assert loc.camera.hypotheses.age == cam.settled_updates
    per_check = np.log(6.0) + cam.laser_nats
    need = max(cam.min_checks, int(np.ceil(cam.settled_threshold / per_check)))
    assert need > max(cam.min_checks, int(np.ceil(cam.threshold / per_check)))
    for _ in range(1, need):
        assert _weigh(loc, far[0], scan) is None
    assert _weigh(loc, far[0], scan) is not None
