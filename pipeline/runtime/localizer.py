"""The thin runtime: a verified bundle in, poses out, from odometry, laser scans and camera images.

    loc = Localizer.from_bundle("bundles/office-0.1.0")
    est = loc.update(odometry, scan, image=None)   # -> Estimate(pose, covariance, state, n_particles, ...)

numpy, scipy, pyarrow and onnxruntime only: importing this module never imports torch (a test checks).
The bundle gives the laser map, the retrieval database and the ONNX describer (and, when exported with
them, the sequence model and seed 001's area prior); the filter is `amcl.AdaptiveMCL` and the camera
enters it through one path, `camera.CameraPath` (docs/runtime.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from pydantic import ValidationError

from pipeline.errors import excerpt
from pipeline.retrieval.search import weighted_candidates
from pipeline.runtime import inputs
from pipeline.runtime.bundle import BundleError, open_bundle


@dataclass(frozen=True)
class Estimate:
    pose: np.ndarray  # (3,) map_from_base x, y, theta (radians)
    covariance: np.ndarray  # (3, 3)
    state: str  # tracking | lost | relocalising
    n_particles: int
    updated: bool  # False when the filter held the update back (not enough travel)
    candidates: np.ndarray | None  # (K, 4) x, y, theta, weight when retrieval ran this step
    source: str | None  # what seeded or injected: image, sequence, sequence+image, hypothesis, area_prior, ...
    best_likelihood: float  # per-beam relative likelihood of the best particle, (0, 1]


@dataclass(frozen=True)
class LaserGeometry:
    angle_min: float
    angle_increment: float
    range_max: float
    base_from_laser: tuple[float, float, float]


class Localizer:
    def __init__(self, root: Path, manifest: dict, settings: dict, *, seed: int | None = None,
                 describer_threads: int | None = None):
        from pipeline.config import FilterConfig
        from pipeline.io.map_yaml import read_map
        from pipeline.retrieval.database import load_database
        from pipeline.runtime.describer import OnnxDescriber
        from pipeline.runtime.grid import LaserMap

        self.root, self.manifest, self.settings = root, manifest, settings
        try:
            fcfg = FilterConfig.model_validate(settings["filter"])
        except ValidationError as err:  # an older or hand-edited bundle: name the file, the key and the fix
            from pipeline.config import format_validation_error

            raise BundleError(format_validation_error(f"{root / 'filter.yaml'}, section filter", err, FilterConfig)
                              + "\n  fix: export the bundle again with this version of siteloc "
                              "(`siteloc config show --explain filter` lists the settings)") from None
        if seed is not None:
            fcfg = fcfg.model_copy(update={"seed": seed})
        las = settings["laser"]
        self.laser = LaserGeometry(las["angle_min"], las["angle_increment"], las["range_max"],
                                   tuple(las["base_from_laser"]))
        # Scans given as ranges must have the laser's beam count: the bundle's when filter.yaml records it,
        # else the first scan's (`scan`).
        self.beams: int | None = las.get("beams")
        if self.beams is not None and (isinstance(self.beams, bool) or not isinstance(self.beams, int)
                                       or self.beams < 1):
            raise BundleError(f"{root / 'filter.yaml'}, section laser: beams is {excerpt(self.beams)}, not a "
                              f"positive integer; export the bundle again")
        self._beams_from = ("the bundle's laser" if self.beams is not None
                            else "the first scan's; this bundle's filter.yaml has no laser.beams")
        self.occupancy = read_map(root / "map" / "map.yaml")
        self.map = LaserMap.from_occupancy(self.occupancy, fcfg.sensor.max_distance)
        self.filter_config = fcfg
        self.base_seed = fcfg.seed  # reset(seed=...) reseeds; replays count trials from this one
        self.database = load_database(root / "db")
        self.describer = OnnxDescriber(root / "models" / "describer.onnx", root / "models" / "describer.json",
                                       threads=describer_threads)
        self.retrieval = settings["retrieval"]
        from pipeline.runtime.sequence import SequenceRelocaliser, has_sequence

        self.sequence = SequenceRelocaliser(root, threads=describer_threads) if has_sequence(root) else None
        from pipeline.runtime.areaprior import AreaPriorSeeder, has_prior

        self.area_prior = None
        if has_prior(root):
            from pipeline.config import PriorConfig

            ps = {**PriorConfig().model_dump(), **(settings.get("prior") or {})}
            self.area_prior = AreaPriorSeeder(root, self.map, area_radius_m=ps["area_radius_m"],
                                              max_areas=ps["max_areas"], threads=describer_threads)
        if fcfg.seed_with == "area_prior" and self.area_prior is None:
            raise BundleError(f"{root}: filter.seed_with is 'area_prior' but the bundle has no area prior; export "
                              f"it with --prior or set filter.seed_with=candidates")
        if fcfg.inject_areas and self.area_prior is None:
            raise BundleError(f"{root}: filter.inject_areas is set but the bundle has no area prior; export it with "
                              f"--prior or set filter.inject_areas=false")
        if fcfg.relocalise_with in ("sequence", "both") and self.sequence is None:
            raise BundleError(f"{root}: filter.relocalise_with is '{fcfg.relocalise_with}' but the bundle has no "
                              f"sequence model; export it with --sequence or set filter.relocalise_with=image")
        self.camera = None
        self.reset()
        if fcfg.scan_check.model == "beam":
            self.verifier  # noqa: B018 - its range table is built (or read from the cache) at load, not mid-run

    def reset(self, seed: int | None = None) -> None:
        """Forget the robot's pose: the next update starts afresh (a new filter, seeded `seed` if given)."""
        from pipeline.runtime.amcl import AdaptiveMCL
        from pipeline.runtime.camera import CameraPath

        if seed is not None:
            self.filter_config = self.filter_config.model_copy(update={"seed": seed})
        self._odometry = None  # the last reading accepted: the next one's step is bounded from it
        filt = AdaptiveMCL(self.map, self.filter_config, range_max=self.laser.range_max,
                           base_from_laser=self.laser.base_from_laser)
        if self.camera is None:
            areas = None
            if self.area_prior is not None:
                prior = self.area_prior
                areas = lambda frame: (prior.cells, prior.weights(prior.probabilities(frame)))  # noqa: E731
            self.camera = CameraPath(filt, self.filter_config, self.retrieval["candidate_weights"],
                                     rank_image=lambda frame: self.retrieved(frame), range_max=self.laser.range_max,
                                     base_from_laser=self.laser.base_from_laser, mode=self.relocalise_with,
                                     sequence=self.sequence, areas=areas)
        else:  # the settings may have changed since (filter_config is public)
            self.camera.reset(filt, self.filter_config, mode=self.relocalise_with)

    @property
    def filter(self):
        """The current `AdaptiveMCL` (replaced by `reset`)."""
        return self.camera.filter

    @classmethod
    def from_bundle(cls, path: Path, *, seed: int | None = None, workdir: Path | None = None,
                    describer_threads: int | None = None) -> Localizer:
        """Verify every file of the bundle (directory or .tar.gz), then load it. An archive is unpacked
        into `workdir`, or into a temporary directory removed with the Localizer."""
        import tempfile

        from pipeline.runtime.bundle import read_manifest

        unpacked = None
        if workdir is None and Path(path).is_file():
            unpacked = tempfile.TemporaryDirectory(prefix="siteloc-bundle-")
            workdir = Path(unpacked.name)
        root = open_bundle(Path(path), workdir)

        manifest = read_manifest(root)
        try:
            settings = yaml.safe_load((root / "filter.yaml").read_text())
        except yaml.YAMLError as exc:
            raise BundleError(f"{root / 'filter.yaml'}: not valid YAML ({exc}); export the bundle again") from None
        for key in ("filter", "retrieval", "laser"):
            if not isinstance(settings, dict) or key not in settings:
                raise BundleError(f"{root / 'filter.yaml'}: no '{key}' section; export the bundle again")
        loc = cls(root, manifest, settings, seed=seed, describer_threads=describer_threads)
        loc._unpacked = unpacked  # lives as long as the Localizer
        return loc

    def retrieved(self, image, *, describer=None) -> np.ndarray:
        """(N, 3) x, y, theta: the image's Top-N database poses (N = retrieval.top_n), best first, after IPA
        retrieval and RPA re-ranking. `describer`: another session of the bundle's detector graph (threads
        describing frames side by side each use their own)."""
        from pipeline.retrieval.database import query_database

        d = (describer or self.describer).describe(inputs.image(image))
        r = self.retrieval
        regions = d.rpa[d.query_rows(r["query_regions"])]
        found = query_database(self.database, d.ipa, regions, top_n=r["top_n"],
                               weights=tuple(r["candidate_weights"]), rerank=r.get("rerank", True))
        return self.database.db.poses[found.ranked]

    def candidates(self, image) -> np.ndarray:
        """(K, 4) x, y, theta, weight: the image's Top-K poses (K = len(candidate_weights)), weights normalised."""
        return weighted_candidates(self.retrieved(image), self.retrieval["candidate_weights"])

    @property
    def relocalise_with(self) -> str:
        """The re-localization in effect: filter.relocalise_with, with auto resolved for this bundle."""
        mode = self.filter_config.relocalise_with
        if mode == "auto":
            return "both" if self.sequence is not None else "image"
        return mode

    @property
    def verifier(self):
        """The sensor model that scores checked poses (`filter.scan_check.model`; `CameraPath.verifier`)."""
        return self.camera.verifier

    def proposals(self, sources: tuple[str, ...], image, scan) -> tuple[np.ndarray, np.ndarray]:
        """Where particles would go now (`CameraPath.proposals`): (K, 4) x, y, theta, weight and (K,)
        heading spreads, from the image's ("image") or the buffered frames' ("sequence") ranked poses."""
        return self.camera.proposals(sources, inputs.image(image), self._checked_scan(scan))

    def scan(self, ranges) -> object:
        """A `Scan` of ranges (m) in the bundle's laser geometry: 1-D, the laser's beam count, none negative
        (+inf: no return; NaN: invalid); a RuntimeInputError otherwise (docs/runtime.md, "Inputs")."""
        from pipeline.runtime.sensor import Scan

        r = inputs.ranges(ranges, self.beams, self.laser.angle_increment, beams_from=self._beams_from)
        if self.beams is None:
            self.beams = len(r)
        return Scan(r, self.laser.angle_min, self.laser.angle_increment, self.laser.range_max)

    def _checked_scan(self, scan):
        """`scan` checked: None, a `Scan` (its own geometry) or ranges (`scan`)."""
        from pipeline.runtime.sensor import Scan

        if scan is None:
            return None
        if isinstance(scan, Scan):
            inputs.scan_geometry(scan)
            return scan
        return self.scan(scan)

    def update(self, odometry, scan, image=None) -> Estimate:
        """One step: odometry (x, y, theta in the odometry frame), a scan (a `Scan`, or ranges in the
        bundle's laser geometry, or None) and optionally the camera image at this step. Each is checked
        first (`inputs`): a bad one raises RuntimeInputError and leaves the filter as it was."""
        odometry = inputs.odometry(odometry, self._odometry)
        image = inputs.image(image)
        scan = self._checked_scan(scan)  # last: the first scan a bundle without laser.beams sees sets the count
        self._odometry = odometry
        step = self.camera.step(odometry, scan, image)
        res = step.result
        return Estimate(res.pose, res.covariance, res.state.value, res.particles, res.updated, step.candidates,
                        step.source, res.best_likelihood)
