"""The report of `ingest-colmap`: report.json (what was read, the alignment, what was left out and why) and
report.md, and the warnings a suspicious alignment deserves. Distances in metres, angles in degrees."""

from __future__ import annotations

import numpy as np

from pipeline.colmap.align import Alignment
from pipeline.config import IngestConfig

HEIGHT_SPREAD_WARN_M = 0.5  # camera centres spread more than this in height: the up axis is probably off


def alignment_warnings(
    alignment: Alignment, views, ing: IngestConfig, upside_down: int, n_left_out: int, n_stops: int
) -> list[str]:
    """Anchors the alignment does not meet within the ingest tolerances, cameras at several heights or upside down,
    stops left out."""
    warnings = []
    summary = alignment.summary()
    pos_max, head_max = summary["position_error_m"]["max"], summary["heading_error_deg"]["max"]
    if pos_max is not None and pos_max > ing.position_tolerance_m:
        warnings.append(
            f"anchor position error up to {pos_max:.3f} m "
            f"(ingest.position_tolerance_m {ing.position_tolerance_m} m): check the anchors"
        )
    if head_max is not None and head_max > ing.heading_tolerance_deg:
        warnings.append(
            f"anchor heading error up to {head_max:.1f} deg (ingest.heading_tolerance_deg "
            f"{ing.heading_tolerance_deg} deg): the model's up axis or the anchors' theta may be off"
        )
    z = [v.xyz[2] for v in views]
    if max(z) - min(z) > HEIGHT_SPREAD_WARN_M:
        warnings.append(
            f"camera heights in the map frame spread over {max(z) - min(z):.2f} m: "
            "the up axis may be off (the cameras of a capture rig share one height)"
        )
    if upside_down:
        warnings.append(f"{upside_down} cameras are upside down in the map frame: is the model's z axis up?")
    if n_left_out:
        warnings.append(f"{n_left_out} of {n_stops} stops left out (see stops_left_out)")
    return warnings


def build_report(
    site_name: str,
    rec,
    grouping: str,
    alignment: Alignment,
    kept,
    left_out,
    skipped: list[dict],
    views,
    upside_down: int,
    warnings: list[str],
) -> dict:
    """report.json: `kept` and `left_out` are the stops (pipeline.colmap.ingest.Stop), `views` every posed image."""
    z = np.array([v.xyz[2] for v in views])
    return {
        "site": site_name,
        "model": {
            "cameras": rec.num_cameras(),
            "images": rec.num_images(),
            "frames": rec.num_frames(),
            "rigs": rec.num_rigs(),
            "points3D": rec.num_points3D(),
        },
        "grouping": grouping,
        "alignment": alignment.summary(),
        "camera_z_m": {"min": float(z.min()), "max": float(z.max())},
        "cameras_upside_down": upside_down,
        "stops": len(kept),
        "images": sum(len(s.views) for s in kept),
        "stops_left_out": [
            {
                "stop": s.stop_id,
                "frame_id": s.frame_id,
                "images": sorted(v.name for _, v in s.views),
                "reasons": s.reasons,
            }
            for s in left_out
        ],
        "images_left_out": skipped,
        "warnings": warnings,
    }


def report_md(rep: dict) -> str:
    """report.md: the same as report.json, as tables."""
    a = rep["alignment"]

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    lines = [
        f"# ingest-colmap report: {rep['site']}",
        "",
        "| what | value |",
        "| --- | --- |",
        f"| model | {rep['model']['images']} images, {rep['model']['frames']} frames, "
        f"{rep['model']['points3D']} points |",
        f"| stops written | {rep['stops']} ({rep['images']} images), grouped by {rep['grouping']} |",
        f"| stops left out | {len(rep['stops_left_out'])} |",
        f"| images left out | {len(rep['images_left_out'])} |",
        f"| alignment | {a['method']}, scale {a['scale']:.6g} |",
        f"| anchor position error | RMS {num(a['position_error_m']['rms'], '.4f')} m, "
        f"max {num(a['position_error_m']['max'], '.4f')} m |",
        f"| anchor heading error | RMS {num(a['heading_error_deg']['rms'], '.3f')} deg, "
        f"max {num(a['heading_error_deg']['max'], '.3f')} deg |",
    ]
    if a["anchors"]:
        lines += ["", "## Anchors", "", "| image | position error (m) | heading error (deg) |", "| --- | --- | --- |"]
        lines += [
            f"| {r['image']} | {r['position_error_m']:.4f} | {num(r['heading_error_deg'], '.3f')} |"
            for r in a["anchors"]
        ]
    if rep["stops_left_out"]:
        lines += ["", "## Stops left out", "", "| stop | frame | images | why |", "| --- | --- | --- | --- |"]
        lines += [
            f"| {s['stop']} | {s['frame_id'] or '-'} | {len(s['images'])} | {'; '.join(s['reasons'])} |"
            for s in rep["stops_left_out"]
        ]
    if rep["images_left_out"]:
        lines += ["", "## Images left out", ""] + [f"- {i['image']}: {i['reason']}" for i in rep["images_left_out"]]
    if rep["warnings"]:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in rep["warnings"]]
    return "\n".join(lines) + "\n"
