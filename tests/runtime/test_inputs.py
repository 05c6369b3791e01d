"""The runtime's public API checks its inputs (`pipeline.runtime.inputs`): a bad scan, odometry reading,
image or pose is a RuntimeInputError naming the argument, never a NaN pose, an IndexError or a belief
tracked where no robot can be; legitimate no-return beams and the accepted image layouts still work."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.config import FilterConfig
from pipeline.errors import RuntimeInputError, SitelocError
from pipeline.runtime.amcl import AdaptiveMCL, FilterState
from pipeline.runtime.inputs import ODOMETRY_LIMIT, STEP_LIMIT_M
from pipeline.runtime.localizer import Localizer
from pipeline.runtime.sensor import Scan
from pipeline.sitegen.laser import LaserScanner, rasterise_map
from tests.sitegen.small_floor import small_floor

RANGE_MAX = 30.0
BEAMS = 181
HW = (24, 32)
START = np.array([1.5, 1.5, 0.0])  # in the corridor of the small floor


class Reached(Exception):
    """The describer was called: the image got past the checks."""


class StubDescriber:
    """The bundle's describer, as far as the checks see it: records the images that reach it."""

    image_hw = HW

    def __init__(self, *args, **kwargs):
        self.seen = []

    def describe(self, image):
        self.seen.append(image)
        raise Reached


@pytest.fixture(scope="module")
def floor(tmp_path_factory):
    """(bundle root with map/map.yaml, its settings, a scanner of its laser): the small floor as a bundle
    without the retrieval files (the Localizer's describer and database are stubbed)."""
    from pipeline.io.map_yaml import write_map

    occ = rasterise_map(small_floor())
    root = tmp_path_factory.mktemp("inputs")
    (root / "map").mkdir()
    write_map(root / "map" / "map.yaml", occ)
    scanner = LaserScanner(occ, beams=BEAMS, fov_deg=270, range_max=RANGE_MAX, seed=1)
    fcfg = FilterConfig(min_particles=100, max_particles=500)
    fcfg = fcfg.model_copy(update={"scan_check": fcfg.scan_check.model_copy(update={"model": "filter"})})
    settings = {"filter": fcfg.model_dump(mode="json"),
                "retrieval": {"candidate_weights": [4.0, 3.0, 2.0, 1.0], "top_n": 10},
                "laser": {"angle_min": scanner.angle_min, "angle_increment": scanner.angle_increment,
                          "range_max": RANGE_MAX, "base_from_laser": [0.0, 0.0, 0.0], "beams": BEAMS}}
    return root, settings, scanner


def make_localizer(floor, *, beams_recorded: bool = True) -> Localizer:
    root, settings, _ = floor
    settings = {**settings, "laser": dict(settings["laser"])}
    if not beams_recorded:
        del settings["laser"]["beams"]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("pipeline.retrieval.database.load_database", lambda path: None)
        mp.setattr("pipeline.runtime.describer.OnnxDescriber", StubDescriber)
        return Localizer(root, {}, settings)


@pytest.fixture
def loc(floor):
    return make_localizer(floor)


def scan_at(floor, pose) -> np.ndarray:
    return floor[2].cast_many(np.asarray(pose, dtype=np.float64)[None])[0].astype(np.float64)


def image_uint8():
    return np.random.default_rng(0).integers(0, 256, (*HW, 3), dtype=np.uint8)


def image_float():
    return np.random.default_rng(0).random((3, *HW))


def nan_image():
    x = image_float()
    x[1, 2, 3] = np.nan
    return x


def ranges_with(index: int, value: float) -> np.ndarray:
    r = np.full(BEAMS, 5.0)
    r[index] = value
    return r


# (what is called, the message it must raise): each names the argument, what was expected and what was given.
REFUSED = {
    "wrong beam count": (lambda loc: loc.update(np.zeros(3), np.full(180, 5.0)),
                         r"^scan: expected 181 ranges \(the bundle's laser\), got 180$"),
    "negative range": (lambda loc: loc.update(np.zeros(3), ranges_with(17, -0.5)),
                       r"^scan: expected ranges >= 0 m .*got -0\.5 at beam 17 \(1 negative\)$"),
    "2-D scan": (lambda loc: loc.update(np.zeros(3), np.full((2, BEAMS), 5.0)),
                 r"^scan: expected a 1-D array of ranges .*got shape \(2, 181\)$"),
    "text scan": (lambda loc: loc.update(np.zeros(3), ["5.0"] * BEAMS), r"^scan: expected ranges in metres, got dtype"),
    "scan() entry": (lambda loc: loc.scan(np.full(BEAMS + 1, 5.0)), r"^scan: expected 181 ranges"),
    "1e300 odometry": (lambda loc: loc.update([1e300, 0.0, 0.0], np.full(BEAMS, 5.0)),
                       r"^odometry: expected \|x\|, \|y\| \(m\) and \|theta\| \(rad\) up to 1e\+07, got x = 1e\+300$"),
    "NaN odometry": (lambda loc: loc.update([0.0, 0.0, np.nan], np.full(BEAMS, 5.0)),
                     r"^odometry: expected 3 finite values x, y \(m\), theta \(rad\), got \[0\.0, 0\.0, nan\] "
                     r"\(theta is nan\)$"),
    "odometry of 2 values": (lambda loc: loc.update([0.0, 0.0], None), r"^odometry: expected 3 finite .*shape \(2,\)$"),
    "(3, H, W) uint8 image": (lambda loc: loc.update(np.zeros(3), None, image=np.zeros((3, *HW), np.uint8)),
                              r"^image: expected \(H, W, 3\) uint8 RGB or \(3, H, W\) float in \[0, 1\], got shape "
                              r"\(3, 24, 32\) uint8: channel-first, transpose it to \(H, W, 3\)$"),
    "NaN float image": (lambda loc: loc.update(np.zeros(3), None, image=nan_image()),
                        r"^image: expected finite values in \[0, 1\], got nan at \(1, 2, 3\)"),
    "float image above 1": (lambda loc: loc.update(np.zeros(3), None, image=image_float() * 255.0),
                            r"^image: expected float values in \[0, 1\], got 0\.\d+\.\.2\d\d\.\d+ \(shape "
                            r"\(3, 24, 32\) float64\): divide an 8-bit image by 255"),
    "empty image": (lambda loc: loc.retrieved(np.zeros((3, 0, 0))), r"^image: expected .*got an empty array"),
    "(H, W, 3) float image": (lambda loc: loc.update(np.zeros(3), None, image=image_float().transpose(1, 2, 0)),
                              r"^image: expected .*got shape \(24, 32, 3\) float64: channel-last float"),
    "uint16 image": (lambda loc: loc.candidates(image_uint8().astype(np.uint16) * 257),
                     r"^image: expected .*got shape \(24, 32, 3\) uint16$"),
    "grey image to retrieved": (lambda loc: loc.retrieved(np.zeros(HW, np.uint8)),
                                r"^image: expected .*got shape \(24, 32\) uint8$"),
    "init pose off the map": (lambda loc: loc.filter.init_pose([500.0, 3.0, 0.0]),
                              r"^init_pose: expected a position on the map \(x -1\.\.13 m, y -1\.\.9 m\), "
                              r"got \(500, 3\)$"),
    "init pose in unknown space": (lambda loc: loc.filter.init_pose([11.0, 7.0, 0.0]),
                                   r"^init_pose: expected a position in the map's free space, got \(11, 7\): "
                                   r"unknown space$"),
    "init pose in a wall": (lambda loc: loc.filter.init_pose([6.0, 5.0, 0.0]),
                            r"^init_pose: .*got \(6, 5\): an occupied cell$"),
    "NaN init pose": (lambda loc: loc.filter.init_pose([np.nan, 1.0, 0.0]),
                      r"^init_pose: expected 3 finite .*x is nan"),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_bad_inputs_are_refused_naming_the_argument(loc, case):
    call, message = REFUSED[case]
    before = loc.filter.particles.copy()
    with pytest.raises(RuntimeInputError, match=message) as err:
        call(loc)
    assert isinstance(err.value, SitelocError) and isinstance(err.value, ValueError)
    assert not loc.describer.seen  # nothing reached the describer
    np.testing.assert_array_equal(loc.filter.particles, before)  # nor the filter


def test_a_step_beyond_the_bound_is_refused_until_reset(loc, floor):
    scan = scan_at(floor, START)
    loc.update([0.0, 0.0, 0.0], scan)
    with pytest.raises(RuntimeInputError, match=r"^odometry: expected a step of at most 1000 m .*got \(5000, 0\): "
                                                r".*call reset\(\)"):
        loc.update([5000.0, 0.0, 0.0], scan)
    loc.update([STEP_LIMIT_M, 0.0, 0.0], scan)  # the bound itself is a step; the refused reading left no trace
    loc.reset()
    assert np.isfinite(loc.update([5000.0, 0.0, 0.0], scan).pose).all()  # a new start: any reading


def test_without_laser_beams_in_the_bundle_the_first_scan_sets_the_count(floor):
    loc = make_localizer(floor, beams_recorded=False)
    with pytest.raises(RuntimeInputError, match=r"^scan: expected 1 to 241 ranges \(a full turn "
                                                r"at the laser's 1.5 deg increment\), got 5000$"):
        loc.update(np.zeros(3), np.full(5000, 5.0))  # more beams than a full turn holds at this increment
    loc.update(np.zeros(3), scan_at(floor, START))
    with pytest.raises(RuntimeInputError, match=r"^scan: expected 181 ranges \(the first scan's; this bundle's "
                                                r"filter.yaml has no laser.beams\), got 180$"):
        loc.update(np.zeros(3), np.full(180, 5.0))


def test_no_return_beams_max_range_beams_and_scan_objects_still_work(loc, floor):
    """REP 117 as the sensor models read it: +inf no return, NaN and -inf skipped, >= range_max a max reading."""
    r = scan_at(floor, START)
    r[::7], r[1::7], r[2::7], r[3::7], r[4::7] = np.inf, np.nan, -np.inf, RANGE_MAX, 1e300
    r[5::7] = 0.0  # below range_min: skipped
    est = loc.update(np.zeros(3), r)
    assert np.isfinite(est.pose).all() and est.updated
    assert loc.update([0.3, 0.0, 0.0], np.full(BEAMS, np.inf)).updated  # nothing seen: an update all the same
    geometry = (floor[2].angle_min, floor[2].angle_increment, RANGE_MAX)
    loc.update([0.6, 0.0, 0.0], Scan(scan_at(floor, START)[:90], *geometry))  # a Scan carries its own beams
    with pytest.raises(RuntimeInputError, match=r"^scan: expected ranges >= 0 m .*got -1 at beam 3"):
        loc.update([0.6, 0.0, 0.0], Scan(ranges_with(3, -1.0), *geometry))
    with pytest.raises(RuntimeInputError, match=r"^scan: expected finite angle_min"):
        loc.update([0.6, 0.0, 0.0], Scan(np.full(BEAMS, 5.0), np.nan, floor[2].angle_increment, RANGE_MAX))
    assert isinstance(loc.scan(list(scan_at(floor, START))), Scan)  # a list of floats, float32: as before
    assert loc.scan(scan_at(floor, START).astype(np.float32)).ranges.dtype == np.float64


@pytest.mark.parametrize("image", [image_uint8(), image_float(), image_float().astype(np.float32), "frame.png"],
                         ids=["uint8 HWC", "float64 CHW", "float32 CHW", "a path"])
def test_the_accepted_image_layouts_reach_the_describer_unchanged(loc, image):
    with pytest.raises(Reached):
        loc.candidates(image)
    assert loc.describer.seen[-1] is image  # decoding and layout conversion stay the describer's
    loc.retrieved = lambda frame: np.array([[1.5, 1.5, 0.0], [4.0, 1.5, 0.0], [2.0, 5.0, 0.0], [9.0, 5.0, 0.0]])
    est = loc.update(np.zeros(3), np.full(BEAMS, 5.0), image=image)
    assert est.source == "image" and np.isfinite(est.pose).all()


def test_a_tracked_belief_driven_off_the_map_is_lost_not_tracking(floor):
    """Odometry within the bounds can carry a belief off the map; the filter then says lost, at once."""
    loc = make_localizer(floor)
    loc.filter.init_pose(START)
    loc.camera.started = True
    assert loc.update(np.zeros(3), scan_at(floor, START)).state == "tracking"
    est = loc.update([100.0, 0.0, 0.0], np.full(BEAMS, 5.0))
    assert not loc.map.known(*est.pose[:2]) and est.state == "lost"


def test_a_winning_hypothesis_in_unknown_space_relocalises(floor):
    """The camera path's winners skip the caller's check: off the known map they start a search instead."""
    lmap = make_localizer(floor).map
    f = AdaptiveMCL(lmap, FilterConfig(min_particles=100, max_particles=500), range_max=RANGE_MAX)
    f.init_pose([11.0, 7.0, 0.0], check=False)
    assert f.state == FilterState.RELOCALISING
    f.init_pose(START, check=False)
    assert f.state == FilterState.TRACKING


def test_localize_names_the_run_and_the_step(floor, tmp_path):
    from types import SimpleNamespace

    from pipeline.localize import replay_one

    loc = make_localizer(floor)
    sc = floor[2]
    odom = np.zeros((5, 3))
    odom[:, 0] = np.arange(5) * 0.3
    odom[3, 1] = np.inf
    ranges = np.tile(scan_at(floor, START), (5, 1))

    class Run(SimpleNamespace):
        def __len__(self):
            return len(self.odom)

    run = Run(name="corridor", odom=odom, ranges=ranges, gt=np.tile(START, (5, 1)), angle_min=sc.angle_min,
              angle_increment=sc.angle_increment, range_max=RANGE_MAX)
    with pytest.raises(RuntimeInputError, match=r"^run corridor, step 3 of 5: odometry: expected 3 finite values"):
        replay_one(run, loc.map, loc.filter_config, (0.0, 0.0, 0.0), "pose", 0)
    run.gt[0] = [500.0, 3.0, 0.0]
    with pytest.raises(RuntimeInputError, match=r"^run corridor, step 0 of 5 \(its ground-truth pose, --init pose\): "
                                                r"init_pose: expected a position on the map"):
        replay_one(run, loc.map, loc.filter_config, (0.0, 0.0, 0.0), "pose", 0)


def odometry_walks(min_steps: int, max_steps: int):
    """Odometry readings within the documented bounds: a start anywhere in them, then steps of up to the bound."""
    limit = ODOMETRY_LIMIT
    start = st.tuples(st.floats(-limit, limit), st.floats(-limit, limit), st.floats(-limit, limit))
    step = st.tuples(st.floats(-STEP_LIMIT_M, STEP_LIMIT_M), st.floats(-STEP_LIMIT_M, STEP_LIMIT_M),
                     st.floats(-10.0, 10.0))
    return st.tuples(start, st.lists(step, min_size=min_steps, max_size=max_steps))


SCANS = arrays(np.float64, BEAMS, elements=st.floats(0.0, 1e6, allow_nan=False, allow_infinity=False))


@pytest.fixture(scope="module")
def shared(floor):
    return make_localizer(floor)


@settings(max_examples=30, deadline=None)
@given(walk=odometry_walks(1, 4), scans=st.lists(SCANS, min_size=5, max_size=5), tracking=st.booleans(),
       seed=st.integers(0, 2**16))
def test_any_finite_input_within_the_bounds_gives_a_finite_pose_never_tracked_off_the_map(shared, walk, scans,
                                                                                         tracking, seed):
    loc = shared
    loc.reset(seed=seed)
    if tracking:  # a belief the caller trusts, which the odometry may then carry anywhere
        loc.filter.init_pose(START)
        loc.camera.started = True
    start, steps = walk
    odom = np.clip(np.array(start), -ODOMETRY_LIMIT, ODOMETRY_LIMIT)
    readings = [odom]
    for d in steps:
        odom = np.clip(odom + d, -ODOMETRY_LIMIT, ODOMETRY_LIMIT)
        readings.append(odom)
    for reading, ranges in zip(readings, scans, strict=False):
        est = loc.update(reading, ranges)
        assert np.isfinite(est.pose).all() and np.isfinite(est.covariance).all()
        assert not (est.state == "tracking" and not loc.map.known(est.pose[0], est.pose[1])), est
