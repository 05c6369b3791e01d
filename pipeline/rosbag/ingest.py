"""Stage `ingest-bag`: robot recordings -> a site capture directory that `siteloc ingest` takes unchanged.

Each recording is one drive (`pipeline.rosbag.drive`): its camera frames give the capture stops and its
scans, when it has any, `runs/<name>/` (a step per scan with odometry, the reference where tf has one, the
nearest camera frame, kidnappings flagged). site.yaml comes from CameraInfo (K, and a plumb_bob D as the
camera's distortion; none for a laser-only drive), the first scan and tf_static; the map from `/map` or
`map_yaml`. What is dropped, and why, and how each recording was read, is in bag_report.json / .md.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io.atomic import atomic_dir, check_output, write_bytes_atomic, write_text_atomic
from pipeline.io.capture_runs import write_run
from pipeline.rosbag.drive import (
    BagOptions,
    Drive,
    extract_drive,
    kept_frames,
    map_of,
    notes_text,
    recording_notes,
    site_of,
    start_stamp,
)
from pipeline.rosbag.read import load_frames, read_recording


def _write_runs(tmp: Path, drives: list[Drive], site) -> dict:
    out = {}
    for d in drives:
        if d.run is None:
            continue
        run, name = d.run, d.rec.name
        images = []
        for k, fi in enumerate(run["image"]):
            if fi is None:
                images.append(None)
                continue
            _, _, data, fmt = d.rec.frames[fi]
            images.append(f"images/runs/{name}/{k:04d}.{'jpg' if fmt == 'jpeg' else 'png'}")
            write_bytes_atomic(tmp / images[-1], data)
        write_run(tmp / "runs" / name, run["t"], run["odom"], run["gt"], run["ranges"], images, run["kidnapped"])
        out[name] = {"steps": len(images), "images": sum(i is not None for i in images),
                     "kidnapped_steps": int(np.sum(run["kidnapped"]))}
    return out


def _write_captures(tmp: Path, drives: list[Drive], site) -> int:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["image", "stop_id", "view", "x", "y", "theta", "room", "area"])
    n = 0
    for d in drives:
        cam = d.report.get("cam_poses")
        for s in d.stops:
            stop_id = f"stop{n:04d}"
            for view, fi in enumerate(s.frames):
                _, _, data, fmt = d.rec.frames[fi]
                rel = f"images/{stop_id}_v{view}.{'jpg' if fmt == 'jpeg' else 'png'}"
                write_bytes_atomic(tmp / rel, data)
                x, y, th = (round(float(v), 6) for v in cam[fi])
                w.writerow([rel, stop_id, view, x, y, th, "", ""])
            n += 1
    write_text_atomic(tmp / "captures.csv", buf.getvalue())
    return n


def _annotations(src: Path, tmp: Path) -> dict:
    """COCO boxes for the written stop images: entries are matched by file name, or else by the bytes of the
    file they name (beside the COCO file), so boxes drawn on an earlier extraction carry over."""
    import hashlib

    try:
        doc = json.loads(Path(src).read_text())
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise InputError(f"{src}: annotations are not JSON", [Problem(str(src), str(exc),
                                                                     fix="pass a COCO annotations.json")]) from None
    if not isinstance(doc, dict):
        raise InputError(f"{src}: annotations are not a COCO file", [Problem(
            str(src), "top level must be an object with 'images' and 'annotations'",
            fix="pass a COCO annotations.json")])
    ours = {}
    for p in sorted((tmp / "images").glob("stop*")):
        ours[hashlib.sha256(p.read_bytes()).hexdigest()] = p.relative_to(tmp).as_posix()
    names = set(ours.values())
    kept, by_content, missing = [], 0, []
    for im in doc.get("images", []):
        name = im.get("file_name", "")
        if name in names:
            kept.append(im)
            continue
        f = Path(src).parent / name
        digest = hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else None
        if digest in ours:
            kept.append({**im, "file_name": ours[digest]})
            by_content += 1
        else:
            missing.append(name)
    ids = {im["id"] for im in kept}
    doc = {**doc, "images": kept, "annotations": [a for a in doc.get("annotations", []) if a.get("image_id") in ids]}
    write_text_atomic(tmp / "annotations.json", json.dumps(doc, indent=1) + "\n")
    return {"images": len(kept), "matched_by_content": by_content, "not_in_the_recordings": len(missing),
            "boxes": len(doc["annotations"])}


def _report_md(rep: dict) -> str:
    lines = [f"# Bag ingest report: {rep['site']}", "", f"{rep['stops']} stops from {len(rep['recordings'])} "
             f"recordings ({rep['messages']} messages in {rep['seconds']:.1f} s, {rep['messages_per_s']:.0f} msg/s).",
             "", "| recording | frames | scans | stops | incomplete stops | dropped |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, r in rep["recordings"].items():
        drop = ", ".join(f"{k} {v}" for k, v in r["dropped"].items() if isinstance(v, int) and v) or "none"
        lines.append(f"| {name} | {r['frames']} | {r['scans']} | {r['stops']} | {len(r['incomplete_stops'])} | "
                     f"{drop} |")
    for name, r in rep["recordings"].items():
        for g in r["dropped"].get("stream_gaps", []):
            lines.append(f"\n- {name}: {g['topic']} is silent from {g['from_s']} s to {g['to_s']} s ({g['gap_s']} s, "
                         f"typically {g['typical_period_s']} s between messages): a stall or a clock jump")
        for g in r["dropped"].get("tf_gaps", []):
            lines.append(f"\n- {name}: tf {g['edge']} has no message from {g['from_s']} s to {g['to_s']} s "
                         f"({g['gap_s']} s); {g['stamps_inside']} scans and frames in it have no pose")
        for s in r["incomplete_stops"]:
            lines.append(f"\n- {name}: at ({s['at'][0]:.2f}, {s['at'][1]:.2f}) t={s['t']:.1f} s: {s['why']}"
                         + (f" (views {s['missing_views']})" if s["missing_views"] else ""))
    for name, r in rep["recordings"].items():
        lines += [f"\n- {name}: {note}" for note in notes_text(r)]
    if rep.get("ingest_needs"):
        lines += ["", f"`siteloc ingest` needs: {rep['ingest_needs']}"]
    return "\n".join(lines) + "\n"


def run_ingest_bag(cfg: SitelocConfig, *, inputs: dict, outputs: dict[str, Path], options: BagOptions | None = None,
                   force: bool = False, progress: bool = True) -> Path:
    """Read `inputs['bags']` (paths) and write the capture directory `outputs['out']` (see module docstring)."""
    from pipeline.ingest import validate_site_dir
    from pipeline.io.map_yaml import write_map
    from pipeline.io.site import DEFAULT_CLASSES, Rig, write_site
    from pipeline.rosbag.bagfile import find_bags

    opts = options or BagOptions()
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    ann_path = inputs.get("annotations")
    if ann_path is not None and not Path(ann_path).is_file():
        raise InputError(f"{ann_path}: annotations not found", [Problem(
            str(ann_path), "file is missing", fix="pass the COCO file of the stop images, or leave --annotations out")])
    bags = find_bags(inputs["bags"])
    unknown = [n for n in opts.stops_from if n not in {p.stem if p.is_file() else p.name for p in bags}]
    if unknown:
        raise InputError("--stops-from names no recording", [Problem(str(out), f"no recording named '{n}'")
                                                              for n in unknown])
    t_start = time.perf_counter()
    recs = [read_recording(p, opts.roles, opts.offsets, opts.tf_max_gap_s, opts.sync_tolerance_s, progress)
            for p in bags]
    n_msgs = sum(r.messages for r in recs)
    offsets = Rig().yaw_offsets
    tol_deg = opts.view_tolerance_deg or (15.0 if opts.stops == "every" else cfg.ingest.heading_tolerance_deg)
    drives = [extract_drive(r, offsets, opts, tol_deg, not opts.stops_from or r.name in opts.stops_from) for r in recs]
    for d in drives:
        load_frames(d.rec, kept_frames(d))
    name = opts.name or "".join(c if c.isalnum() or c in "_.-" else "_" for c in out.name) or "site"
    site = site_of(recs, drives, name, opts)
    occ = map_of(recs, inputs.get("map"))
    n_stops = sum(len(d.stops) for d in drives)
    if n_stops == 0 and site.camera is not None:
        raise InputError("no capture stops", [Problem(str(d.rec.path), f"{len(d.incomplete)} incomplete stops, none "
                                                      "complete", fix="turn in place through 360 deg at each stop, "
                                                      "or use --stops every for a continuous drive") for d in drives])
    if n_stops == 0 and not any(d.run is not None and len(d.run["t"]) for d in drives):
        raise InputError("nothing to ingest", [Problem(str(d.rec.path), "no camera stops and no scan with odometry",
                                                       fix="record /scan with /odom or odom -> base_link in /tf")
                                               for d in drives])
    spread = max((s.spread for d in drives for s in d.stops), default=0.0)
    head = math.degrees(max((s.heading_error for d in drives for s in d.stops), default=0.0))
    needs = []
    if spread > cfg.ingest.position_tolerance_m:
        needs.append(f"--set ingest.position_tolerance_m={math.ceil(spread * 100) / 100 + 0.01:.2f}")
    if head > cfg.ingest.heading_tolerance_deg:
        needs.append(f"--set ingest.heading_tolerance_deg={math.ceil(head) + 1}")
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        write_site(tmp / "site.yaml", site.model_copy(update={"classes": DEFAULT_CLASSES}))
        write_map(tmp / "map.yaml", occ)
        stops = _write_captures(tmp, drives, site)
        runs = _write_runs(tmp, drives, site)
        ann = _annotations(inputs["annotations"], tmp) if inputs.get("annotations") else None
        seconds = time.perf_counter() - t_start
        total = sum(len(r.frames) for r in recs)
        rep = {"site": name, "stops": stops, "runs": runs, "messages": n_msgs, "seconds": round(seconds, 2),
               "messages_per_s": round(n_msgs / max(seconds, 1e-9), 1), "frames": total,
               "stop_spread_m": round(spread, 4), "stop_heading_error_deg": round(head, 3),
               "ingest_needs": " ".join(needs), "annotations": ann, "options": asdict(opts), "recordings": {}}
        for d in drives:
            r = d.rec
            rep["recordings"][r.name] = {
                "path": str(r.path), "topics": r.topics, "frames": len(r.frames),
                "scans": 0 if r.ranges is None else len(r.ranges), "stops": len(d.stops),
                "incomplete_stops": [{"at": list(s.at), "t": round(s.stamp - start_stamp(r), 3), "missing_views":
                                      s.missing_views, "why": s.why} for s in d.incomplete],
                "dropped": d.report["dropped"], **recording_notes(d)}
        write_text_atomic(tmp / "bag_report.json", json.dumps(rep, indent=2) + "\n")
        write_text_atomic(tmp / "bag_report.md", _report_md(rep))
        write_effective_config(cfg, tmp, stage="ingest_bag", inputs={"bags": ",".join(map(str, bags))})
        icfg = cfg.ingest.model_copy(update={
            "position_tolerance_m": max(cfg.ingest.position_tolerance_m, spread + 0.01),
            "heading_tolerance_deg": max(cfg.ingest.heading_tolerance_deg, head + 1.0)})
        try:  # what `siteloc ingest` will check, before anything is kept
            validate_site_dir(tmp, icfg, progress=False)
        except InputError as exc:  # name the output, not the temporary directory that is about to go
            def named(text: str) -> str:
                return text.replace(str(tmp), str(out))

            raise InputError(named(exc.summary), [replace(p, file=named(p.file), message=named(p.message))
                                                  for p in exc.problems]) from None
    return out
