"""Sections of the stages that make and read site data: `synth`, `ingest`, `ingest-log`."""

from __future__ import annotations

from typing import Any

from pydantic import Field, model_validator

from pipeline.config.base import Strict


class SplitConfig(Strict):
    """The train / test split of an ingested site, by whole stops (all views of a stop on one side)."""

    test_fraction: float = Field(0.2, ge=0.0, lt=1.0, description="share of whole stops held out for testing")
    seed: int = Field(0, description="seed of the stop-level shuffle")


class IngestConfig(Strict):
    """`siteloc ingest`: how a capture directory is checked and normalised into the site database."""

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
    log_odds_hit: float = Field(0.85, gt=0, description="log-odds added to a cell a beam ends in")
    log_odds_miss: float = Field(0.4, gt=0, description="log-odds taken from each cell a beam passes through")
    log_odds_clamp: float = Field(5.0, gt=0, description="log-odds are kept within +-this (a map that can change)")
    occupied_thresh: float = Field(0.65, gt=0, lt=1, description="occupancy probability above which a cell is "
                                   "occupied (map.yaml's occupied_thresh)")
    free_thresh: float = Field(0.196, gt=0, lt=1, description="... below which it is free (map.yaml's free_thresh); "
                               "between the two: unknown")
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
    """`siteloc ingest-log`: a CARMEN laser log to a runs table and an occupancy map."""

    seed: int = Field(0, description="seed of the synthesised odometry noise")
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
