"""The `filter` section: the runtime filter and its camera path (docs/runtime.md)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.config.base import Strict
from pipeline.config.site import OdometryNoise


class SensorModelConfig(Strict):
    """Laser sensor model (Probabilistic Robotics ch. 6; nav2 amcl's parameter names)."""

    model: Literal["likelihood_field", "beam"] = Field("likelihood_field", description="the filter's sensor "
                                                      "model: nav2's likelihood field (smooth, cheap) or the beam "
                                                      "model (ray cast; Thrun et al. 6.3)")
    max_beams: int = Field(60, ge=2, description="beams used per update, evenly subsampled (nav2: max_beams)")
    z_hit: float = Field(0.9, ge=0, le=1, description="mixture weight of a hit (Gaussian around the expected range)")
    z_short: float = Field(0.05, ge=0, le=1, description="beam model only")
    z_max: float = Field(0.05, ge=0, le=1, description="beam model only")
    z_rand: float = Field(0.1, ge=0, le=1, description="mixture weight of a random reading (uniform over the range)")
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
                            "unmapped_margin_m). Without it, people walking along a corridor drag a tracked pose "
                            "with them")
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
    """KLD-sampling (Fox 2003): as many particles as a histogram of the belief needs for the bound."""

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
                               "them")
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
                      "sequence's Top-N) against the scan and seed or inject at the len(retrieval.candidate_weights) "
                      "that fit it best; 0: retrieval's own Top-4, unchecked (seed 000)")
    samples: int = Field(64, ge=1, description="poses drawn around each checked one (init_std_xy; the source's "
                         "heading spread); the best-fitting one is where particles go")
    rounds: int = Field(3, ge=1, description="refinement rounds: each draws `samples` poses around every "
                        "candidate's best so far at half the spread (the scan's likelihood peaks within cm; one "
                        "round of 0.5 m draws finds the peak along corridors, not at the right junction). "
                        "1: one round of draws, no refinement")
    rank_prior: float = Field(1.0, ge=0.0, description="order the checked poses by scan log-likelihood minus "
                              "rank_prior * log(1 + retrieval rank) (a Zipf prior of retrieval's precision at "
                              "rank): where a twin fits the scan as well as the right place, the image's order "
                              "decides; 0: by the scan alone")
    model: Literal["filter", "beam"] = Field("beam", description="the sensor model that scores checked poses "
                                             "(and the camera hypotheses'): the filter's own, or the beam model (the "
                                             "sensor settings, ray cast from sensor.ray_cast's table: about free "
                                             "cells x table_angles x 2 B, built once per map and cached on disk), "
                                             "which explains a person in front of the laser as a short reading "
                                             "where the likelihood field scores a miss, and penalises a scan that "
                                             "sees through a wall")


class CameraConfig(Strict):
    """How camera hypotheses enter the filter once it has started (`pipeline.runtime.camera`, docs/runtime.md):
    while the filter is not tracking, particles go around the proposals that fit the scan best
    (`scan_check`); while it is not lost, far poses that fit the scan collect evidence against the
    estimate, and one that reaches `threshold` replaces the belief."""

    every: int = Field(1, ge=0, description="weigh the hypotheses at every this many updates that come with an "
                       "image and a scan (each costs one scan check of the estimate, the hypotheses and the "
                       "pool's proposals); 0: off (seed 000: the camera only starts the filter and re-localizes "
                       "it once lost)")
    min_distance_m: float = Field(3.0, gt=0, description="a hypothesis is a pose at least this far from the estimate")
    distinct: float = Field(0.05, ge=0, description="the laser tells two poses apart when their fits differ by "
                            "more than this per beam (log-likelihood, each at its best-fitting pose): a hypothesis "
                            "that fits worse is dropped, one that fits better adds laser_nats")
    laser_nats: float = Field(3.0, ge=0, description="the evidence a check adds when the scan prefers the "
                              "hypothesis by `distinct` (0.05 x 60 beams: 3 nats); the camera's part is "
                              "log(1 + rank of the estimate) - log(1 + rank of the hypothesis)")
    threshold: float = Field(6.0, gt=0, description="evidence (nats) at which a hypothesis replaces the belief")
    settled_threshold: float = Field(12.0, gt=0, description="... once the belief is settled: tracked "
                                     "settled_updates updates without a jump (right after a re-localization the "
                                     "filter has often picked a twin of the place; a settled belief has been "
                                     "kidnapped unseen far more rarely)")
    settled_updates: int | None = Field(8, ge=1, description="updates after which a tracked belief is settled "
                                        "(null: never)")
    min_checks: int = Field(3, ge=1, description="a hypothesis wins only after this many checks, followed with "
                            "odometry in between (one scan can favour a far pose by chance: people)")
    rank_radius_m: float = Field(2.0, gt=0, description="a pose's camera rank is that of the first ranked view "
                                 "within this distance ...")
    rank_heading_deg: float = Field(45.0, gt=0, le=180, description="... and this heading of it")
    max_rank: int | None = Field(10, ge=1, description="a pose with no ranked view near it counts as this rank "
                                 "(null: the list's length): the truth's views are missed for a few frames at a "
                                 "time (people, a view unlike the mapping run's)")


class FilterConfig(Strict):
    """The runtime filter: adaptive Monte Carlo localization on the laser map (seed 000, section 3.2)."""

    method: Literal["amcl", "kld", "mcl", "mixture"] = Field(
        "amcl", description="amcl: augmented MCL + KLD; kld: KLD only; mcl: fixed count; mixture: mixture MCL"
    )
    seed: int = Field(0, description="seed of the filter's draws (trial t of a replay uses seed + t)")
    min_particles: int = Field(500, ge=10, description="KLD-sampling's lower bound on the particle count")
    max_particles: int = Field(5000, ge=10, description="KLD-sampling's upper bound (mcl: the fixed count)")
    max_particles_per_ha: float | None = Field(
        4500.0, gt=0, description="... raised to this many per hectare of the map's free space where that is more "
        "(a global search over a large site needs them; indoor floors of under 1.1 ha keep max_particles). "
        "null: max_particles")
    alpha_slow: float = Field(0.001, ge=0, le=1, description="augmented MCL: decay of the slow likelihood average")
    alpha_fast: float = Field(0.1, ge=0, le=1, description="... of the fast one; random particles come in while it "
                              "falls below the slow one")
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
    inject_particles: int = Field(1000, ge=0, description="particles injected around candidates per step when lost")
    inject_while_relocalising: bool = Field(
        True, description="keep injecting the image's candidates at every update with an image until the filter "
        "tracks again (with a sequence model: for as long as the sequence's are injected, both checked together), "
        "not only at the update it declares itself lost")
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
        "the robot's: at 180 the headings are nearly uniform and the laser picks")
    sequence_confirm_steps: int = Field(
        6, ge=0, description="keep injecting sequence candidates for this many steps after the filter tracks "
        "again: on a quasi-symmetric floor a wrong twin of the place can fit the laser and be tracked")
    mixture_share: float = Field(0.1, ge=0, le=1, description="mixture MCL: share drawn from the dual proposal")
    scan_check: ScanCheckConfig = ScanCheckConfig()
    camera: CameraConfig = CameraConfig()

    @model_validator(mode="after")
    def _counts(self) -> FilterConfig:
        if self.min_particles > self.max_particles:
            raise ValueError(f"min_particles {self.min_particles} > max_particles {self.max_particles}")
        return self
