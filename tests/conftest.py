"""Shared pytest set-up.

Property tests run derandomized: the same examples on every run, so a red CI always means a
change broke something rather than a new random draw. `HYPOTHESIS_PROFILE=explore` searches
afresh (more examples, random seed) when hunting for edge cases locally.
"""

import os

# Under pytest-xdist each worker shares the cores with the others: torch's default of one OpenMP thread per
# core makes n workers run n x cores spinning threads, and a 5 s training took 119 s beside another one.
# Each worker gets its share of the cores (before torch is imported; subprocesses inherit it).
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    _share = max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    os.environ.setdefault("OMP_NUM_THREADS", str(_share))

import pytest  # noqa: E402
from hypothesis import settings

settings.register_profile("default", derandomize=True, print_blob=True)
settings.register_profile("explore", max_examples=2000, derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


@pytest.fixture(scope="session")
def local_ray():
    """A local Ray of 2 CPUs for the `--engine ray` tests (skipped without the ray extra)."""
    ray = pytest.importorskip("ray")
    from pipeline.ray_engine import connect

    yield connect(None, num_cpus=2)
    ray.shutdown()


MICRO_SETS = ["detector.weights=null", "detector.iterations=4", "retrieval.chunk=16", "retrieval.rpa_proposals=20"]


@pytest.fixture(scope="session")
def micro_site(tmp_path_factory):
    """(config, ingest dir, detector dir) of the CI micro reference site with a barely trained detector."""
    from pipeline.config import load_config
    from pipeline.sitegen.render import egl_available

    if not egl_available():
        pytest.skip("no headless EGL context for the reference site")
    from pipeline.detection.train import run_train_detector
    from pipeline.ingest import run_ingest
    from pipeline.sitegen.presets import load_site_preset
    from pipeline.sitegen.synth import run_synth

    cfg = load_config("ci", MICRO_SETS)
    root = tmp_path_factory.mktemp("micro")
    preset = load_site_preset(cfg.synth.site, cfg.synth.preset_overrides)
    synth = run_synth(preset, outputs={"out": root / "site"}, seed=cfg.synth.seed, progress=False)
    ing = run_ingest(cfg, inputs={"site": synth}, outputs={"out": root / "ing"}, progress=False)
    model = run_train_detector(cfg, inputs={"data": ing}, outputs={"out": root / "det"}, progress=False)
    return cfg, ing, model


@pytest.fixture(scope="session")
def micro_extraction(micro_site, tmp_path_factory):
    """`siteloc extract` of the micro site."""
    from pipeline.retrieval.extract import run_extract

    cfg, ing, model = micro_site
    return run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": tmp_path_factory.mktemp("x") / "d"},
                       progress=False)


@pytest.fixture(scope="session")
def micro_bundle(micro_site, micro_extraction, tmp_path_factory):
    """(config, ingest dir, detector dir, index dir, bundle dir): `siteloc export` of the micro site."""
    from pipeline.bundle.export import run_export
    from pipeline.retrieval.database import run_build_index

    cfg, ing, model = micro_site
    root = tmp_path_factory.mktemp("bundle")
    index = run_build_index(cfg, inputs={"descriptors": micro_extraction}, outputs={"out": root / "index"})
    bundle = run_export(cfg, inputs={"model": model, "index": index, "data": ing}, outputs={"out": root / "bundles"})
    return cfg, ing, model, index, bundle


SEQUENCE_SETS = ["sequence.frame_size=32", "sequence.length=3", "sequence.hidden=16", "sequence.epochs=4",
                 "sequence.dims=8", "sequence.place_cell_m=4.0"]


@pytest.fixture(scope="session")
def micro_frames(micro_site, tmp_path_factory):
    """(config with SEQUENCE_SETS, ingest dir, frame-features dir) of the micro site."""
    from pipeline.config import load_config
    from pipeline.sequence.frames import run_frame_features

    _, ing, _ = micro_site
    cfg = load_config("ci", [*MICRO_SETS, *SEQUENCE_SETS])
    return cfg, ing, run_frame_features(cfg, inputs={"data": ing}, outputs={"out": tmp_path_factory.mktemp("f") / "f"},
                                        progress=False)


@pytest.fixture(scope="session")
def micro_sequence_bundle(micro_bundle, micro_frames, tmp_path_factory):
    """(config, ingest dir, sequence model dir, bundle dir): the micro bundle exported with a sequence LSTM."""
    from pipeline.bundle.export import run_export
    from pipeline.sequence.train import run_train_sequence

    _, ing, model, index, _ = micro_bundle
    cfg, _, frames = micro_frames
    root = tmp_path_factory.mktemp("seqbundle")
    seq = run_train_sequence(cfg, inputs={"frames": frames, "data": ing}, outputs={"out": root / "seq"}, progress=False)
    bundle = run_export(cfg, inputs={"model": model, "index": index, "data": ing, "sequence": seq},
                        outputs={"out": root / "bundles"})
    return cfg, ing, seq, bundle


def pytest_collection_modifyitems(config, items):
    """The tests marked slow run first (the order is otherwise kept): under pytest-xdist one worker starts the
    longest, the DVC demo of about 9 minutes on 2 cores, while the other runs the rest, instead of the demo
    starting late and running alone at the end (16 min against about 13 for the whole suite)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
