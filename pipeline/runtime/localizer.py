"""The thin runtime: a verified bundle in, poses out, from odometry, laser scans and camera images.

    loc = Localizer.from_bundle("bundles/office-0.1.0")
    est = loc.update(odometry, scan, image=None)   # -> Estimate(pose, covariance, state, n_particles, ...)

numpy, scipy, pyarrow and onnxruntime only: importing this module never imports torch (a test checks).
Seed 000's closed loop: at start, the first camera image is described (ONNX detector -> IPA + RPA),
retrieved against the bundle's database (IPA Top-N, RPA re-ranking) and its Top-4 poses, weighted
4:3:2:1, seed the adaptive MCL; without an image the filter starts uniform over the free space. Whenever
the filter declares itself lost and an image comes with the update, particles are injected around the
image's Top-4 (`filter.inject_particles` per step, the paper's 1000; with
`filter.inject_while_relocalising`, the default, at every step until it tracks again). With
`filter.scan_check.pool` (10 by default) the four are not retrieval's first four but the four of its
Top-pool that fit the update's scan best (`pipeline.runtime.scancheck`; scored by the beam model by
default, `filter.scan_check.model`), at their best-fitting pose;
while the filter tracks, `filter.challenge` (every 2nd update with an image) checks the image's Top-10
against the scan beside the estimate, and a far pose that fits better at several tests in a row
(`pipeline.runtime.scancheck.Rivals`) gets particles: a kidnapping the laser cannot see. Where the laser
cannot tell a twin of the place from the truth at all, `filter.evidence` (every update with an image,
tracking or relocalising; `pipeline.runtime.evidence`) keeps the image's evidence per far pose that
fits the scan as well as the estimate, and replaces the belief by one around a pose the camera keeps
preferring. With a bundle
exported with a sequence model and `filter.relocalise_with` `auto` (the default: `both` with a sequence
model, `image` without), `both` or `sequence`, every frame also goes into a ring buffer (`pipeline.runtime.sequence`);
when the filter is declared lost the buffer keeps only the frames since the kidnap rule started counting,
and once it holds `length` frames their sequence's Top-4 are injected at every step until the filter
tracks again (seed 000 section 3.3), headings spread by `filter.sequence_heading_std_deg`; `both` also
injects the single image's Top-4 from the step the filter declares itself lost (both sources' Top-pool
checked together once the sequence is ready), `sequence` does not.
A bundle exported with an area prior (`--prior`, seed 001; `pipeline.runtime.areaprior`) can instead
start the filter over the free space of the first image's most probable (room, area) classes
(`filter.seed_with: area_prior`), and with `filter.inject_areas` also inject over them once when lost.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pipeline.retrieval.search import weighted_candidates
from pipeline.runtime.bundle import BundleError, open_bundle


@dataclass(frozen=True)
class Estimate:
    pose: np.ndarray  # (3,) map_from_base x, y, theta (radians)
    covariance: np.ndarray  # (3, 3)
    state: str  # tracking | lost | relocalising
    n_particles: int
    updated: bool  # False when the filter held the update back (not enough travel)
    candidates: np.ndarray | None  # (K, 4) x, y, theta, weight when retrieval ran this step
    source: str | None  # what seeded or injected: image, sequence, sequence+image, challenge, evidence, area_prior, ...
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
        fcfg = FilterConfig.model_validate(settings["filter"])
        if seed is not None:
            fcfg = fcfg.model_copy(update={"seed": seed})
        las = settings["laser"]
        self.laser = LaserGeometry(las["angle_min"], las["angle_increment"], las["range_max"],
                                   tuple(las["base_from_laser"]))
        self.occupancy = read_map(root / "map" / "map.yaml")
        self.map = LaserMap.from_occupancy(self.occupancy, fcfg.sensor.max_distance)
        self.filter_config = fcfg
        if fcfg.scan_check.model == "beam":
            self.verifier  # noqa: B018 - its range table is built (or read from the cache) at load, not mid-run
        self.base_seed = fcfg.seed  # reset(seed=...) reseeds; replays count trials from this one
        self.reset()
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

    def reset(self, seed: int | None = None) -> None:
        """Forget the robot's pose: the next update starts afresh (a new filter, seeded `seed` if given)."""
        from pipeline.runtime.amcl import AdaptiveMCL

        if seed is not None:
            self.filter_config = self.filter_config.model_copy(update={"seed": seed})
        self.filter = AdaptiveMCL(self.map, self.filter_config, range_max=self.laser.range_max,
                                  base_from_laser=self.laser.base_from_laser)
        self.started = False
        self.seeded_by_retrieval = False
        self.awaiting_sequence = False  # lost, and the sequence has not yet brought the filter back
        self._was_lost = False
        self._confirmed = 0
        self._tracking_images = 0  # tracking updates with an image, for filter.challenge.every
        from pipeline.runtime.scancheck import Rivals

        self._rivals = Rivals()
        from pipeline.runtime.evidence import ImageEvidence

        self._evidence = ImageEvidence()
        # Its own stream: weighing evidence leaves the filter's draws as they would be without it.
        self._evidence_rng = np.random.default_rng((self.filter_config.seed, 0xE71D))
        self._evidence_images = 0  # updates with an image and a scan, for filter.evidence.every
        self._ranked_for, self._ranked = None, None
        if getattr(self, "sequence", None) is not None:
            self.sequence.keep_last(0)

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

        d = (describer or self.describer).describe(image)
        r = self.retrieval
        regions = d.rpa[d.query_rows(r["query_regions"])]
        found = query_database(self.database, d.ipa, regions, top_n=r["top_n"],
                               weights=tuple(r["candidate_weights"]), rerank=r.get("rerank", True))
        return self.database.db.poses[found.ranked]

    def _retrieved_now(self, image) -> np.ndarray:
        """`retrieved(image)`, computed once per update however many parts of it (proposals, challenge,
        evidence) ask for it."""
        if self._ranked_for is not image:
            self._ranked, self._ranked_for = self.retrieved(image), image
        return self._ranked

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
        """The sensor model that scores checked poses (`filter.scan_check.model`): the filter's, or a beam
        model on the same map and sensor settings (built once; its range table is cached on disk)."""
        if self.filter_config.scan_check.model == "filter":
            return self.filter.sensor
        from pipeline.runtime.sensor import make_sensor_model

        sensor = self.filter_config.sensor
        if getattr(self, "_verifier_for", None) != sensor:  # called at every check: rebuilt only on a change
            cfg = sensor.model_copy(update={"model": "beam", "beam_skip": False})
            self._verifier = make_sensor_model(self.map, cfg, self.laser.range_max, self.laser.base_from_laser)
            self._verifier_for = sensor
        return self._verifier

    def proposals(self, sources: tuple[str, ...], image, scan) -> tuple[np.ndarray, np.ndarray]:
        """Where particles go: (K, 4) x, y, theta, weight and (K,) each one's heading spread (radians).

        From retrieval's Top-K of the image ("image") or of the buffered frames ("sequence"; with both,
        each source's Top-K at half weight), or, with `filter.scan_check.pool`, the K (K =
        len(candidate_weights)) of the sources' Top-pool whose neighbourhood fits `scan` best (refined in
        `scan_check.rounds`, each source's rank as a prior: `scan_check.rank_prior`), at their best-fitting
        pose (`pipeline.runtime.scancheck`), weighted as retrieval's Top-K would be."""
        from pipeline.runtime.scancheck import check_candidates

        weights = self.retrieval["candidate_weights"]
        sc, fcfg = self.filter_config.scan_check, self.filter_config
        k = max(sc.pool, len(weights))
        pools, spreads, priors = [], [], []
        for source in sources:
            pool = self.sequence.ranked(k) if source == "sequence" else self._retrieved_now(image)
            deg = fcfg.sequence_heading_std_deg if source == "sequence" else None
            pools.append(pool[: sc.pool] if sc.pool else pool)
            spreads.append(np.full(len(pools[-1]), np.radians(deg if deg is not None else fcfg.init_std_theta_deg)))
            priors.append(-sc.rank_prior * np.log1p(np.arange(len(pools[-1]))))
        if sc.pool and scan is not None:
            pool, spread = np.vstack(pools), np.concatenate(spreads)
            checked = check_candidates(self.verifier, self.map, pool, scan, keep=len(weights),
                                       samples=sc.samples, std_xy=fcfg.init_std_xy, std_theta=spread,
                                       rng=self.filter.rng, log_prior=np.concatenate(priors), rounds=sc.rounds)
            if checked is not None:
                return weighted_candidates(checked.poses, weights), spread[checked.rank]
        cands = [weighted_candidates(p, weights) for p in pools]
        out = np.vstack(cands)
        out[:, 3] /= len(cands)
        return out, np.concatenate([sp[: len(c)] for sp, c in zip(spreads, cands, strict=True)])

    def _challenge(self, image, scan, estimate: np.ndarray) -> np.ndarray | None:
        """Test the tracked belief against the image (`filter.challenge`, `scancheck.Rivals`): the image's
        Top-pool, the rivals so far and the estimate are checked against the scan alike; a pose at least
        min_distance_m from the estimate that has fitted better by margin at `confirm` checks in a row
        gets `particles` particles. Returns those (K, 4: x, y, theta, weight) or None."""
        fcfg = self.filter_config
        ch = fcfg.challenge
        won = self._rivals.check(self.verifier, self.map, estimate, self._retrieved_now(image)[: ch.pool],
                                 scan, samples=fcfg.scan_check.samples, std_xy=fcfg.init_std_xy,
                                 std_theta=np.radians(fcfg.init_std_theta_deg), min_distance_m=ch.min_distance_m,
                                 margin=ch.margin, confirm=ch.confirm, rng=self.filter.rng,
                                 rounds=fcfg.scan_check.rounds)
        if not len(won):
            return None
        self.filter.inject(won, np.ones(len(won)), n=ch.particles * len(won), share=ch.share)
        return np.column_stack([won, np.full(len(won), 1.0 / len(won))])

    def _weigh_evidence(self, image, scan, estimate: np.ndarray, threshold: float) -> np.ndarray | None:
        """Check the image's hypotheses against the estimate (`filter.evidence`, `pipeline.runtime.evidence`);
        when one wins, the belief is replaced by one around it. Returns its (1, 4) x, y, theta, weight or None."""
        fcfg = self.filter_config
        ev = fcfg.evidence
        won = self._evidence.check(self.verifier, self.map, estimate, self._retrieved_now(image), scan, pool=ev.pool,
                                   samples=fcfg.scan_check.samples, std_xy=fcfg.init_std_xy,
                                   std_theta=np.radians(fcfg.init_std_theta_deg), min_distance_m=ev.min_distance_m,
                                   tolerance=ev.tolerance, min_fit=ev.min_fit, radius_m=ev.radius_m,
                                   heading_rad=np.radians(ev.heading_deg), max_rank=ev.max_rank, threshold=threshold,
                                   min_checks=ev.min_checks, rng=self._evidence_rng, rounds=fcfg.scan_check.rounds)
        if won is None:
            return None
        self.filter.init_pose(won)
        self.awaiting_sequence = False  # the evidence is the confirmation the sequence was waiting for
        self._rivals.clear()
        return np.r_[won, 1.0][None]

    def scan(self, ranges) -> object:
        from pipeline.runtime.sensor import Scan

        return Scan(np.asarray(ranges, dtype=np.float64), self.laser.angle_min, self.laser.angle_increment,
                    self.laser.range_max)

    def update(self, odometry, scan, image=None) -> Estimate:
        """One step: odometry (x, y, theta in the odometry frame), a scan (a `Scan`, or ranges in the
        bundle's laser geometry, or None) and optionally the camera image at this step."""
        from pipeline.runtime.amcl import FilterState
        from pipeline.runtime.sensor import Scan

        if scan is not None and not isinstance(scan, Scan):
            scan = self.scan(scan)
        self._ranked_for = None  # a new image: retrieval runs (at most) once in this update
        cands, source = None, None
        mode = self.relocalise_with
        use_sequence = mode != "image"
        state = self.filter.state  # as the last update left it
        if use_sequence and self.started and state == FilterState.LOST and not self._was_lost:
            # Just declared lost (the filter may stay lost for several updates until something is injected):
            # the frames seen while the kidnap rule was counting were taken where the robot is now.
            self.sequence.keep_last(self.filter_config.kidnap.updates)
            self.awaiting_sequence = True
        lost_before = self._was_lost
        self._was_lost = self.started and state == FilterState.LOST
        if use_sequence and image is not None:
            self.sequence.push(image)
        sources_now = ["start"] if not self.started else []
        if not self.started:
            if image is not None and self.filter_config.seed_with == "area_prior":
                # Seed 001: whole areas, not poses; retrieval still injects once the filter is lost.
                weights = self.area_prior.weights(self.area_prior.probabilities(image))
                self.filter.init_regions(self.area_prior.cells, weights)
                self.seeded_by_retrieval, source = True, "area_prior"
            elif image is not None:
                cands, spread = self.proposals(("image",), image, scan)
                self.filter.init_candidates(cands[:, :3], cands[:, 3], std_theta=spread)
                self.seeded_by_retrieval, source = True, "image"
            else:
                self.filter.init_uniform()
            self.started = True
        else:
            if self.awaiting_sequence and state == FilterState.TRACKING:
                # Tracking again, but a wrong twin of the place can fit the laser as well as the right one:
                # the sequence keeps proposing for `sequence_confirm_steps` more steps.
                self._confirmed += 1
                if self._confirmed > self.filter_config.sequence_confirm_steps:
                    self.awaiting_sequence = False
            elif self.awaiting_sequence:
                self._confirmed = 0
            fcfg = self.filter_config
            sources = []
            if self.awaiting_sequence and self.sequence.ready:
                sources.append("sequence")
            lost = state == FilterState.LOST
            if image is not None and (
                    (not sources and ((lost and mode != "sequence") or not self.seeded_by_retrieval))
                    or (fcfg.inject_while_relocalising and mode != "sequence"
                        and (state == FilterState.RELOCALISING or sources))):
                sources.append("image")
            sources_now = sources
            if sources:
                cands, spread = self.proposals(tuple(sources), image, scan)
                source = "+".join(sources)
                self.filter.inject(cands[:, :3], cands[:, 3], std_theta=spread)
                self.seeded_by_retrieval = True
            if (self.filter_config.inject_areas and image is not None and state == FilterState.LOST
                    and not lost_before):
                # Seed 001's prior names areas where the pose candidates may all be wrong twins.
                self.filter.inject_regions(self.area_prior.cells,
                                           self.area_prior.weights(self.area_prior.probabilities(image)))
                source = "image+area_prior" if source == "image" else (source or "area_prior")
        res = self.filter.update(odometry, scan)
        if self.filter_config.challenge.every and res.updated:
            if res.state != FilterState.TRACKING or sources_now or self.awaiting_sequence:
                self._rivals.clear()  # the belief is being rebuilt: nothing to challenge
            self._rivals.move(odometry)
            if (res.state == FilterState.TRACKING and image is not None and scan is not None and not sources_now
                    and not self.awaiting_sequence):
                self._tracking_images += 1
                if self._tracking_images % self.filter_config.challenge.every == 0:
                    cands = self._challenge(image, scan, res.pose)
                    source = "challenge" if cands is not None else None
        pose, covariance, state, particles = res.pose, res.covariance, res.state, res.particles
        ev = self.filter_config.evidence
        if ev.every and res.updated and sources_now != ["start"]:
            self._evidence.follow(odometry, res.pose, tracking=res.state == FilterState.TRACKING,
                                  jump_m=ev.min_distance_m)
            # Lost: the estimate is no hypothesis, but the ones held are followed on (one may be the truth).
            if res.state != FilterState.LOST and image is not None and scan is not None:
                self._evidence_images += 1
                if self._evidence_images % ev.every == 0:
                    settled = ev.settled_updates is not None and self._evidence.age >= ev.settled_updates
                    won = self._weigh_evidence(image, scan, res.pose,
                                               ev.settled_threshold if settled else ev.threshold)
                    if won is not None:  # the belief was replaced: report the new one
                        cands, source = won, "evidence"
                        est = self.filter.estimate
                        pose, covariance = est.pose.copy(), est.covariance.copy()
                        state, particles = self.filter.state, len(self.filter.particles)
        return Estimate(pose, covariance, state.value, particles, res.updated, cands, source, res.best_likelihood)
