"""The micro reference site the sitegen tests render: the tiny preset shrunk to a few seconds."""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

from pipeline.sitegen.presets import load_site_preset
from pipeline.sitegen.synth import TIMING_FILE, run_synth

# The tiny preset shrunk so that one synth takes a few seconds: a smaller floor, sparser stops, small views.
MICRO = {
    "floor.size": [14.0, 13.0], "floor.band_depth": 3.2, "stops.spacing": 2.5, "camera.width": 96,
    "camera.height": 72, "runs.steps_per_run": 14, "runs.kidnaps_per_query_run": 1,
    # Every identity cue, so the capture contract, boxes and change are checked with them.
    "identity.wings": 2, "identity.wing_colours": True, "identity.room_plates": True,
    "identity.unique_pictures": True, "identity.notice_boards": True, "identity.escape_plans": True,
    "identity.signs": True, "identity.room_types": True, "identity.desk_clutter": True,
    "identity.outside_views": True, "identity.painted_walls": True, "identity.room_boards": True,
}


def micro(**extra):
    return load_site_preset("tiny", {**MICRO, **extra})


def synth(out: Path, seed: int = 3, preset=None, **kwargs) -> Path:
    return run_synth(preset or micro(), outputs={"out": out}, seed=seed, progress=False, **kwargs)


def digests(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != TIMING_FILE}


def captures(site: Path) -> list[dict]:
    with (site / "captures.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))
