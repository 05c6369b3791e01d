"""Stage `synth`: generate, render and write a reference site as a capture directory `siteloc ingest` takes.

Order of work: floor plan and objects (seeded) -> optional environment change -> occupancy map and
capture stops -> 6 rendered views per stop with COCO boxes from the instance buffer -> mapping and
query runs with laser scans (cast on the map plus unmapped people and moved chairs), noisy odometry,
an image per step and kidnappings -> site.yaml, captures.csv, annotations.json, runs/, a contact sheet
and a report. Everything goes to a temporary directory that becomes `out` only when complete.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from pipeline import __version__
from pipeline.io.atomic import atomic_dir, write_text_atomic
from pipeline.io.map_yaml import write_map
from pipeline.machine import machine_summary
from pipeline.sitegen.presets import SitePreset
from pipeline.sitegen.site_scene import build_scene, intrinsics_of

TIMING_FILE = "synth_timing.json"  # the one output that is not reproducible byte for byte


def site_yaml(preset: SitePreset, scene_name: str) -> dict:
    from pipeline.sitegen.camera_effects import site_distortion

    k = intrinsics_of(preset)
    views = preset.camera.views
    half = preset.laser.fov_deg / 2
    camera = {"width": k.width, "height": k.height, "fx": round(k.fx, 6), "fy": round(k.fy, 6), "cx": k.cx,
              "cy": k.cy}
    distortion = site_distortion(preset.camera.effects.distortion)
    if distortion is not None:  # the images are distorted: the camera model says how
        camera["distortion"] = distortion.model_dump(mode="json")
    return {
        "name": scene_name,
        "camera": camera,
        "rig": {"yaw_offsets_deg": [round(360.0 * v / views, 6) for v in range(views)]},
        "laser": {"angle_min_deg": -half, "angle_max_deg": half, "beams": preset.laser.beams,
                  "range_max": preset.laser.range_max},
        "classes": list(preset.furnishing.classes),
    }


def _lighting(preset: SitePreset, scene, rng, changed: bool):
    from pipeline.sitegen.change import ChangeSpec
    from pipeline.sitegen.render import Lighting

    r = preset.render
    exposure = rng.uniform(*r.exposure_range)
    tint = (1.0, 1.0, 1.0)
    if changed:
        spec = ChangeSpec()
        exposure *= spec.exposure_gain
        tint = spec.tint
    return Lighting(ambient=float(rng.uniform(*r.ambient_range)),
                    lights=tuple((lt.x, lt.y, lt.z, lt.intensity) for lt in scene.lights),
                    exposure=float(exposure), tint=tint)


def image_suffix(preset: SitePreset) -> str:
    """The suffix of the frames written: `.jpg`, or `.png` when `camera.effects.jpeg_quality` is None."""
    return ".jpg" if preset.camera.effects.jpeg_quality is not None else ".png"


def effects_record(preset: SitePreset) -> dict | None:
    """The camera effects in force, for config.yaml and synth_report.json; None when every effect is off
    (those files then stay byte for byte what synth wrote before camera effects)."""
    from pipeline.sitegen.camera_effects import CameraEffects

    effects = preset.camera.effects
    return None if effects == CameraEffects.off() else effects.model_dump(mode="json")


def preset_record(preset: SitePreset) -> dict:
    """The effective preset for config.yaml: all of it, but `camera.effects` only when some effect is on."""
    dump = preset.model_dump(mode="json")
    if effects_record(preset) is None:
        dump["camera"].pop("effects")
    return dump


def check_areas(scene, areas: tuple[str, ...], option: str) -> None:
    """Refuse area labels the site does not have, naming the option and the labels it has."""
    from pipeline.errors import InputError, Problem
    from pipeline.sitegen.change import area_keys

    unknown = sorted(set(areas) - area_keys(scene))
    if unknown:
        known = sorted(area_keys(scene))
        raise InputError(f"{option}: no such area {unknown}", [Problem(
            option, f"the site has no room or area {', '.join(unknown)}",
            fix=f"name a room or a room/area of the site: {', '.join(known[:12])}" + (" ..." if len(known) > 12
                                                                                     else ""))])


def run_synth(preset: SitePreset, *, outputs: dict[str, Path], seed: int = 0, change: bool = False,
              force: bool = False, progress: bool = True, allow_fallback: bool = True,
              workers: int | None = None, areas: tuple[str, ...] = (), change_areas: tuple[str, ...] = (),
              move_wall_m: float = 0.0, executor: str = "local", ray_address: str | None = None) -> Path:
    """Write the reference site of `preset` to `outputs['out']`; returns that directory. `workers`: rendering
    processes (`pipeline.sitegen.render_pool`; None: the usable cores, at most 4; 1: this process), or with
    `executor` "ray" Ray actors (None: a cluster's CPUs at `ray_address`). The site written depends on
    neither. `areas`: capture only the stops in these rooms or room/areas (a
    re-capture; stop ids and views stay the full site's). `change_areas`: the change happens only there (it
    implies `change`; the lighting stays the same, as it is the building's). `move_wall_m` > 0: the change also
    moves an interior wall that far (`change.choose_wall_move`; beside a room of `change_areas` when given; implies
    `change`); the map, the runs' laser world and the meshes show it, and the report says which wall moved. With
    `change_areas`, a stop of the building's plan that the moved wall now covers or crowds moves to the nearest
    place of its room with the stops' clearance, keeping its id (`_restop`; the report lists them)."""
    from pipeline.progress import progress_bar
    from pipeline.sitegen.assets import load_assets
    from pipeline.sitegen.laser import rasterise_map
    from pipeline.sitegen.render_pool import STASH, RenderPool, View, default_workers
    from pipeline.sitegen.trajectories import sample_stops

    t_start = time.perf_counter()
    areas, change_areas = tuple(areas), tuple(change_areas)
    change = change or bool(change_areas) or move_wall_m > 0
    relit = change and not change_areas
    base = build_scene(preset, seed, False)
    check_areas(base, areas, "--area")
    check_areas(base, change_areas, "--change-area")
    scene_change, wall_move = change, None  # what the scene is built with: the workers rebuild it from that
    if move_wall_m > 0:
        from pipeline.sitegen.change import ChangeSpec

        wall_move = _wall_move(base, seed, float(move_wall_m), change_areas)
        scene_change = ChangeSpec(move_wall_m=float(move_wall_m))
    scene = build_scene(preset, seed, scene_change, change_areas) if change else base
    library = load_assets(tuple(preset.furnishing.classes), allow_fallback=allow_fallback)
    occ_map = rasterise_map(scene, preset.map_resolution)
    # The capture plan: a change of some areas keeps the building's stops (the team re-captures them), so
    # their ids match the unchanged site's; a whole-building change resamples them on the new map.
    plan_scene, plan_map = (base, rasterise_map(base, preset.map_resolution)) if change_areas else (scene, occ_map)
    stops = sample_stops(plan_scene, plan_map, spacing=preset.stops.spacing, clearance=preset.stops.clearance,
                         jitter=preset.stops.jitter, seed=seed)
    moved_stops, walled = {}, set()
    if change_areas and wall_move is not None:  # the building's plan, with the stops the wall now crowds moved
        stops, moved_stops, walled = _restop(stops, occ_map, scene, base, wall_move.rooms, preset.stops.clearance)
    k = intrinsics_of(preset)
    rng = np.random.default_rng(seed + 31)
    out = Path(outputs["out"])
    if workers is None and executor == "ray" and ray_address:
        from pipeline.ray_engine import connect

        workers = max(1, int(connect(ray_address).available_resources().get("CPU", 1)))
    workers = default_workers() if workers is None else max(1, int(workers))
    suffix = image_suffix(preset)
    stats = {"images": 0, "render_s": 0.0, "effects_s": 0.0, "workers": workers}
    with atomic_dir(out, force=force, inputs=()) as tmp:  # generated from the preset: no input to protect
        with RenderPool(preset, seed, scene_change, allow_fallback, tmp, workers=workers, scene=scene,
                        library=library, change_areas=change_areas, engine=executor,
                        ray_address=ray_address) as pool:
            offsets = [2 * math.pi * v / preset.camera.views for v in range(preset.camera.views)]
            rows, coco_images, coco_anns, batches = [], [], [], []
            for s, (x, y, heading) in enumerate(stops):
                lighting = _lighting(preset, scene, rng, relit)  # drawn in stop order, whoever renders
                room, area = scene.room_at(x, y)
                if areas and room not in areas and f"{room}/{area}" not in areas or s in walled:
                    continue  # not re-captured: its lighting was drawn all the same, so the others keep theirs
                views = []
                for v, off in enumerate(offsets):
                    theta = math.atan2(math.sin(heading + off), math.cos(heading + off))
                    rel = f"images/stop{s:04d}_v{v}{suffix}"
                    views.append(View((x, y, preset.camera.height_m, theta), rel, True, frame=(0, int(change), s, v)))
                    rows.append({"image": rel, "stop_id": f"stop{s:04d}", "view": v, "x": round(x, 4),
                                 "y": round(y, 4), "theta": round(theta, 6), "room": room, "area": area})
                    coco_images.append({"id": len(coco_images) + 1, "file_name": rel, "width": k.width,
                                        "height": k.height})
                batches.append((lighting, views))
            if not batches:
                from pipeline.errors import InputError, Problem

                raise InputError(f"--area {', '.join(areas)}: no capture stop there", [Problem(
                    "--area", "no stop of the site lies in these areas", fix="name rooms the stops cover (see "
                    "the room and area columns of the full site's captures.csv)")])
            rendered = pool.map(batches)
            for image_id, r in enumerate(
                    (r for batch in progress_bar(rendered, total=len(batches), desc="rendering stops",
                                                 unit="stop", enabled=progress) for r in batch), start=1):
                stats["render_s"] += r.seconds
                stats["effects_s"] += r.effects_s
                stats["images"] += 1
                for b in r.boxes:
                    coco_anns.append({"id": len(coco_anns) + 1, "image_id": image_id,
                                      "category_id": preset.furnishing.classes.index(b.cls) + 1,
                                      "bbox": [b.x1, b.y1, b.x2 - b.x1, b.y2 - b.y1],
                                      "area": (b.x2 - b.x1) * (b.y2 - b.y1), "iscrowd": 0,
                                      "instance_id": b.instance_id, "visible_share": round(b.visible_share, 3)})
            run_stops = [st for s, st in enumerate(stops) if s not in walled]
            run_report = _write_runs(tmp, preset, scene, occ_map, run_stops, pool, rng, seed, change, stats,
                                     progress, relit)
        shutil.rmtree(tmp / STASH, ignore_errors=True)  # empty by now: every stashed frame was developed
        with (tmp / "captures.csv").open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=["image", "stop_id", "view", "x", "y", "theta", "room", "area"])
            writer.writeheader()
            writer.writerows(rows)
        categories = [{"id": i + 1, "name": c} for i, c in enumerate(preset.furnishing.classes)]
        write_text_atomic(tmp / "annotations.json",
                          json.dumps({"images": coco_images, "annotations": coco_anns, "categories": categories}))
        write_text_atomic(tmp / "site.yaml", yaml.safe_dump(site_yaml(preset, scene.name), sort_keys=False))
        write_map(tmp / "map.yaml", occ_map)
        write_contact_sheet(tmp / "contact_sheet.png", tmp, coco_images, coco_anns, preset.furnishing.classes, rng)
        write_text_atomic(tmp / "ATTRIBUTION.md", _attribution_md(library))
        report = {
            "site": scene.name, "preset": preset.name, "seed": seed, "changed": change,
            "change_areas": list(change_areas), "areas": list(areas),
            "stops": len(batches), "stops_of_the_site": len(stops), "capture_images": len(rows),
            "map": {"width_cells": int(occ_map.grid.shape[1]), "height_cells": int(occ_map.grid.shape[0]),
                    "resolution": occ_map.resolution},
            "objects_per_class": scene.class_counts(), "boxes_per_class": _count_boxes(coco_anns, preset),
            "runs": run_report, "assets_procedural": bool(library.procedural), "assets_missing": list(library.missing),
            "images_rendered": stats["images"],
        }
        if wall_move is not None:
            report["wall_moved"] = {
                **wall_move.record(),
                "stops_moved": {f"stop{s:04d}": [[round(v, 4) for v in p] for p in ends]
                                for s, ends in sorted(moved_stops.items())},
                "stops_not_captured": [f"stop{s:04d}" for s in sorted(walled)]}
        if effects_record(preset) is not None:
            report["camera_effects"] = effects_record(preset)
        write_text_atomic(tmp / "synth_report.json", json.dumps(report, indent=2) + "\n")
        # Timings differ from run to run, so they live apart from the reproducible outputs.
        # render_s: summed over the workers' frames (with several workers it exceeds the rendering's wall time).
        timing = {"render_images_per_s": round(stats["images"] / max(stats["render_s"], 1e-9), 2),
                  "render_s": round(stats["render_s"], 2), "render_workers": stats["workers"],
                  "render_engine": executor,
                  "camera_effects_s": round(stats["effects_s"], 2),
                  "wall_time_s": round(time.perf_counter() - t_start, 1),
                  "images_per_s": round(stats["images"] / max(time.perf_counter() - t_start, 1e-9), 2),
                  "machine": machine_summary()}
        write_text_atomic(tmp / "synth_timing.json", json.dumps(timing, indent=2) + "\n")
        config = {"stage": "synth", "siteloc_version": __version__, "seed": seed, "change": change,
                  "change_areas": list(change_areas), "areas": list(areas)}
        if wall_move is not None:
            config["move_wall_m"] = float(move_wall_m)
        write_text_atomic(tmp / "config.yaml", yaml.safe_dump({**config, "preset": preset_record(preset)},
                                                              sort_keys=False))
    return out


def _wall_move(base, seed: int, distance: float, change_areas: tuple[str, ...]):
    """The wall the change moves (what `change_scene` picks on the same scene), or a clear error if none may."""
    from pipeline.errors import InputError, Problem
    from pipeline.sitegen.wall_move import MIN_ROOM_M, choose_wall_move

    where = f" beside {', '.join(change_areas)}" if change_areas else ""
    move = choose_wall_move(base, seed, distance, change_areas)
    if move is None:
        raise InputError(f"--move-wall: no interior wall{where} can move by {distance} m", [Problem(
            "--move-wall-m", f"no partition{where} can move {distance} m and leave the room it moves into "
            f"{MIN_ROOM_M} m deep, without closing a door or meeting another wall at a door or window",
            fix="a smaller --move-wall-m, another seed, or other --change-area rooms (rooms along a "
                "partition; corridors only where a wall runs their whole length)")])
    return move


def _restop(stops, occ_map, scene, base, rooms: tuple[str, ...], clearance: float):
    """The building's capture plan (sampled on the unchanged map) after a wall moved: a stop in one of the wall's
    `rooms` with less than `clearance` in the changed map (the wall or what it pushed now stands there) moves to
    the nearest place inside its room that has it, keeping its id and heading. Returns (stops, {stop: (from, to)},
    stops that found no place: not captured)."""
    from pipeline.sitegen.routes import clearance_field

    clear = clearance_field(occ_map)
    rows, cols = np.nonzero(clear >= clearance)
    cx, cy = occ_map.cell_to_world(rows, cols)
    rects = {r.name: r.rect for r in scene.rooms}
    out, moved, lost = list(stops), {}, set()
    for s, (x, y, heading) in enumerate(stops):
        room = base.room_at(x, y)[0]
        r, c = (int(v) for v in occ_map.world_to_cell(x, y))
        if room not in rooms or clear[r, c] >= clearance:
            continue
        inside = rects[room].contains(cx, cy, margin=clearance)  # inside it, not in a doorway
        if not inside.any():
            lost.add(s)
            continue
        k = int(np.argmin(np.hypot(cx[inside] - x, cy[inside] - y)))
        out[s] = (float(cx[inside][k]), float(cy[inside][k]), heading)
        moved[s] = ((x, y), out[s][:2])
    return out, moved, lost


def _count_boxes(anns: list[dict], preset: SitePreset) -> dict[str, int]:
    counts = {c: 0 for c in preset.furnishing.classes}
    for a in anns:
        counts[preset.furnishing.classes[a["category_id"] - 1]] += 1
    return counts


def run_blurs(run, intrinsics, spec) -> list:
    """The motion blur of each frame of `run`: the yaw rate and forward speed of the ground-truth motion
    around the frame (the mean of the steps before and after it; a kidnapping is no motion)."""
    from pipeline.runtime.motion import wrap_angle
    from pipeline.sitegen.camera_effects import Blur, blur_from_motion

    n = len(run.gt)
    if not spec.enabled or spec.exposure_s == 0 or n < 2:
        return [Blur()] * n
    dt = np.diff(run.t)
    step = np.diff(run.gt[:, :2], axis=0)
    heading = run.gt[:-1, 2]
    yaw_rate = wrap_angle(np.diff(run.gt[:, 2])) / dt
    speed = (step[:, 0] * np.cos(heading) + step[:, 1] * np.sin(heading)) / dt
    moving = ~np.asarray(run.kidnapped[1:], bool)  # step i -> i + 1 is a teleport when i + 1 is flagged
    out = []
    for i in range(n):
        steps = [j for j in (i - 1, i) if 0 <= j < n - 1 and moving[j]]
        if not steps:
            out.append(Blur())
            continue
        out.append(blur_from_motion(intrinsics, spec, yaw_rate=float(np.mean(yaw_rate[steps])),
                                    speed=float(np.mean(speed[steps]))))
    return out


def _write_runs(tmp: Path, preset, scene, occ_map, stops, pool, rng, seed, change, stats, progress,
                relit: bool) -> dict:
    from pipeline.progress import progress_bar
    from pipeline.sitegen.camera_effects import AutoExposure
    from pipeline.sitegen.laser import LaserScanner, displace_furniture, laser_poses, laser_world_grid, walking_people
    from pipeline.sitegen.render_pool import View, chunks
    from pipeline.sitegen.trajectories import make_runs, reachable_mask, write_capture_run

    r, lz = preset.runs, preset.laser
    effects = preset.camera.effects
    # A run's gain follows its frames with a lag: the parent runs its AutoExposure over the frames' meters in
    # frame order, whichever worker rendered them, and the workers then finish the frames (render_pool).
    lagged = effects.auto_exposure.enabled and effects.auto_exposure.tau_frames > 0
    suffix = image_suffix(preset)
    k_site = intrinsics_of(preset)
    runs = make_runs(scene, occ_map, stops, n_mapping=r.mapping_runs, n_query=r.query_runs,
                     steps_per_run=r.steps_per_run, mapping_steps=r.mapping_steps, step=r.step_m,
                     kidnaps_per_query_run=r.kidnaps_per_query_run,
                     seed=seed, noise=r.odometry_noise)
    report = {}
    person_room = reachable_mask(scene, occ_map, clearance=0.35)  # where people can walk: the same every run

    def develop(run, ranges, views, rendered):
        """Wait for the run's renders; with a lagged exposure, hand its frames and their gains to `develop`."""
        meters = []
        for batch in rendered:
            stats["render_s"] += sum(x.seconds for x in batch)
            stats["effects_s"] += sum(x.effects_s for x in batch)
            stats["images"] += len(batch)
            meters += [x.meter for x in batch]
        developed = iter(())
        if lagged:
            ae = AutoExposure(effects.auto_exposure)  # one camera per run, settled on its first frame
            gains = [ae.update(m) for m in meters]
            developed = pool.develop([(c, gains[i:i + len(c)]) for i, c in zip(range(0, len(views), 10),
                                                                               chunks(views, 10), strict=True)])
        return run, ranges, views, developed

    def finish(run, ranges, views, developed) -> None:
        for batch in developed:
            stats["effects_s"] += sum(batch)
        write_capture_run(tmp / "runs" / run.name, run, ranges, [v.rel for v in views])

    pending = None  # the previous run, whose frames the workers render while this run's scans are cast
    developing = None  # the run before, whose stashed frames the workers finish
    for k, run in enumerate(progress_bar(runs, desc="runs", unit="run", enabled=progress)):
        run_seed = seed * 1000 + k
        # Unmapped obstacles: chairs pushed away from where the map has them, people walking past.
        moved, removed = displace_furniture(scene, occ_map, lz.moved_chairs_share, run_seed, keep_clear=run.gt[:, :2])
        world = laser_world_grid(scene, preset.map_resolution, extra_rects=moved, removed_ids=removed)
        people = walking_people(person_room, occ_map, lz.people, len(run.gt), run_seed, robot_xy=run.gt[:, :2])
        scanner = LaserScanner(world, beams=lz.beams, fov_deg=lz.fov_deg, range_max=lz.range_max,
                               noise_sigma=lz.noise_sigma, dropout=lz.dropout, seed=run_seed)
        ranges = scanner.cast_many(laser_poses(run.gt), discs=people)
        lighting = _lighting(preset, scene, rng, relit)
        blurs = run_blurs(run, k_site, effects.motion_blur)  # every run frame: the robot drives while exposing
        views = [View((float(x), float(y), preset.camera.height_m, float(theta)),
                      f"images/runs/{run.name}/{i:04d}{suffix}", False, frame=(1, int(change), k, i), blur=blurs[i],
                      lagged=lagged) for i, (x, y, theta) in enumerate(run.gt)]
        rendered = pool.map([(lighting, c) for c in chunks(views, 10)])
        if pending is not None:
            waiting = develop(*pending)
            if developing is not None:
                finish(*developing)
            developing = waiting
        pending = (run, ranges, views, rendered)
        report[run.name] = {"kind": run.kind, "steps": len(run.gt), "kidnappings": int(np.sum(run.kidnapped)),
                            "moved_chairs": len(moved), "people": lz.people}
    if pending is not None:
        waiting = develop(*pending)
        if developing is not None:
            finish(*developing)
        developing = waiting
    if developing is not None:
        finish(*developing)
    return report


def write_contact_sheet(path: Path, root: Path, images: list[dict], anns: list[dict], classes, rng,
                        n: int = 12, cols: int = 4, thumb_w: int = 320) -> Path:
    """A grid of sample views with their boxes and class names drawn, to judge realism at a glance."""
    from PIL import Image, ImageDraw

    from pipeline.io.images import open_image

    palette = [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
               (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 190)]
    by_image: dict[int, list[dict]] = {}
    for a in anns:
        by_image.setdefault(a["image_id"], []).append(a)
    # Prefer views with several boxes, so the sheet shows what the detector will learn from.
    ranked = sorted(images, key=lambda im: -len(by_image.get(im["id"], [])))
    pool = ranked[: max(n * 3, n)]
    chosen = [pool[i] for i in sorted(rng.choice(len(pool), size=min(n, len(pool)), replace=False))]
    tiles = []
    for im in chosen:
        tile = open_image(root / im["file_name"])
        scale = thumb_w / tile.width
        tile = tile.resize((thumb_w, round(tile.height * scale)))
        draw = ImageDraw.Draw(tile)
        for a in by_image.get(im["id"], []):
            x, y, w, h = (v * scale for v in a["bbox"])
            colour = palette[(a["category_id"] - 1) % len(palette)]
            draw.rectangle([x, y, x + w, y + h], outline=colour, width=2)
            draw.text((x + 2, y + 1), classes[a["category_id"] - 1], fill=colour)
        tiles.append(tile)
    rows = math.ceil(len(tiles) / cols)
    sheet = Image.new("RGB", (cols * thumb_w, rows * tiles[0].height), (255, 255, 255))
    for i, tile in enumerate(tiles):
        sheet.paste(tile, ((i % cols) * thumb_w, (i // cols) * tile.height))
    from pipeline.io.atomic import atomic_file

    with atomic_file(path, "wb") as fh:
        sheet.save(fh, format="PNG")
    return path


def _attribution_md(library) -> str:
    lines = ["# Attribution of the 3D models and textures used in this site", "",
             "Wall pictures, room plates, signs, notice boards and escape plans are drawn by siteloc "
             "(`pipeline.sitegen.pictures`, `pipeline.sitegen.signage`; CC0), partly from crops of the "
             "photographs listed below; their text is set in DejaVu Sans / Serif / Mono (matplotlib's copy; "
             "Bitstream Vera licence, public domain changes).", ""]
    if library.procedural:
        lines += ["Some classes use procedural fallback shapes: " + ", ".join(library.missing), ""]
    lines += ["| asset | creator | licence | source |", "| --- | --- | --- | --- |"]
    for a in library.attribution:
        cells = (a.get(k, "") for k in ("name", "creator", "license", "source"))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
