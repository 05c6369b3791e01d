"""Stage `check`: does a deployed bundle still fit the building? Per room / area, from new captures.

Retrieval and detector figures of the new images (pipeline.bundle.measure) are set beside the bundle's
baseline (the same measure on its held-out stops at export); the new runs' scans, at their known poses,
are set against the bundle's map: the share of scan endpoints on its occupied cells and the cells where
the scans see an obstacle the map lacks or pass through a wall the map has (each beyond
`check.endpoint_tolerance_m`, so wall edges are not counted as change, and only where most runs that
looked there found it: pipeline.update.map_patch.map_change). Each area gets a verdict and the
report a plain recommendation: which areas to re-capture, whether the map needs updating, whether the
detector needs retraining. Thresholds: `check.*` in the config.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io.map_yaml import FREE, OCCUPIED, OccupancyMap


def map_drift(occ_map: OccupancyMap, owner: np.ndarray, names: list[str], runs: list, base_from_laser,
              cfg: SitelocConfig, *, progress: bool = True) -> dict:
    """Per area: scan endpoints, their share on the map's walls, new obstacles and walls gone (cells, m2);
    plus the two (H, W) masks for the figure."""
    from scipy.ndimage import distance_transform_edt

    from pipeline.update.map_patch import map_change, scans_with_poses

    c = cfg.check
    found = scans_with_poses(runs, base_from_laser)
    none = np.zeros(occ_map.grid.shape, dtype=bool)
    if found is None:
        return {"scans": 0, "areas": {}, "new_obstacles": none, "walls_gone": none}
    poses, ranges, angle_min, angle_increment, range_max = found
    angles = angle_min + angle_increment * np.arange(ranges.shape[1])
    hit = np.isfinite(ranges) & (ranges > 0) & (ranges < range_max)
    ex = poses[:, :1] + ranges * np.cos(poses[:, 2:3] + angles)
    ey = poses[:, 1:2] + ranges * np.sin(poses[:, 2:3] + angles)
    row, col = occ_map.world_to_cell(ex[hit], ey[hit])
    inside = occ_map.contains(row, col)
    res = occ_map.resolution
    to_wall = distance_transform_edt(occ_map.grid != OCCUPIED) * res
    agree = np.zeros(len(row), dtype=bool)
    agree[inside] = to_wall[row[inside], col[inside]] <= c.endpoint_tolerance_m + 1e-9
    # Endpoints off the map belong to no area; they count as disagreeing with the whole site's map.
    ep_owner = np.full(len(row), -1, dtype=np.int64)
    ep_owner[inside] = owner[row[inside], col[inside]]

    change = map_change(occ_map, runs, base_from_laser, cfg.update.mapping, c.endpoint_tolerance_m,
                        progress=progress)
    new_obstacles, walls_gone = change.new_obstacles, change.walls_gone
    cell_m2 = res * res
    areas = {}
    for i, key in enumerate(names):
        mine = ep_owner == i
        n_new, n_gone = int((new_obstacles & (owner == i)).sum()), int((walls_gone & (owner == i)).sum())
        if not mine.any() and not n_new and not n_gone:
            continue
        areas[key] = {"endpoints": int(mine.sum()),
                      "endpoint_share_on_walls": float(agree[mine].mean()) if mine.any() else None,
                      "new_obstacle_cells": n_new, "walls_gone_cells": n_gone,
                      "changed_m2": round((n_new + n_gone) * cell_m2, 4)}
    return {"scans": int(len(poses)), "endpoints": int(len(row)),
            "endpoint_share_on_walls": float(agree.mean()) if len(agree) else None,
            "new_obstacle_cells": int(new_obstacles.sum()), "walls_gone_cells": int(walls_gone.sum()),
            "areas": areas, "new_obstacles": new_obstacles, "walls_gone": walls_gone}


def place_likeness(similarity: float, neighbour: float) -> float:
    """1 for a view identical to the bundle's at the same place, 0 for one no closer than the view of a
    neighbouring stop (`neighbour`: the baseline's neighbour similarity, on its held-out stops)."""
    if neighbour >= 1:
        return 1.0
    return float(np.clip((similarity - neighbour) / (1 - neighbour), 0, 1))


def changed_below(neighbour: float, c) -> float:
    """The similarity under which a view is changed: `place_likeness` under `c.min_place_likeness`."""
    return neighbour + c.min_place_likeness * (1 - neighbour)


def verdicts(images: dict, baseline: dict | None, mapd: dict, cfg: SitelocConfig) -> dict:
    """Per area: the figures side by side and what to do ('re-capture', 'update map', 'ok', 'too few data')."""
    c = cfg.check
    base_areas = (baseline or {}).get("areas", {})
    base_all = (baseline or {}).get("all") or {}
    out = {}
    for key in sorted(set(images.get("areas", {})) | set(mapd["areas"])):
        new, base, m = images.get("areas", {}).get(key), base_areas.get(key) or base_all, mapd["areas"].get(key)
        reasons, score = [], 0.0
        entry = {"new": new, "baseline": base_areas.get(key), "baseline_from": "area" if key in base_areas else
                 ("site" if base_all else None), "map": m}
        neighbour = base_all.get("neighbour_similarity")
        if new and new["images"] >= c.min_area_images and base:
            drop = base["recall_at_4"] - new["recall_at_4"]
            entry["recall_at_4_drop"] = round(drop, 4)
            score = max(score, drop / c.max_recall_drop)
            if drop > c.max_recall_drop:
                reasons.append(f"recall@4 {new['recall_at_4']:.2f} against {base['recall_at_4']:.2f}")
        if new and new["same_place_images"] >= c.min_area_images and neighbour is not None:
            entry["place_likeness"] = round(place_likeness(new["same_place_similarity"], neighbour), 4)
            changed = new.get("same_place_changed")
            if changed is not None:
                share = changed / new["same_place_images"]
                entry["changed_view_share"] = round(share, 4)
                score = max(score, share / c.max_changed_views)
                if share > c.max_changed_views:
                    reasons.append(f"{changed} of {new['same_place_images']} views ({share:.0%}) unlike the "
                                   f"bundle's at the same place (likeness under {c.min_place_likeness:.2f}: "
                                   f"similarity under {changed_below(neighbour, c):.2f}, 1.00 unchanged, "
                                   f"{neighbour:.2f} a neighbouring stop)")
        map_reasons = []
        if m and m["endpoints"] >= c.min_area_endpoints:
            share = m["endpoint_share_on_walls"]
            score = max(score, (1 - share) / (1 - c.min_endpoint_share),
                        m["changed_m2"] / c.map_change_m2 if c.map_change_m2 else 0.0)
            if share < c.min_endpoint_share:
                map_reasons.append(f"{share:.0%} of scan endpoints on the map's walls")
            if m["changed_m2"] > c.map_change_m2:
                map_reasons.append(f"{m['changed_m2']:.2f} m2 of new obstacles or walls gone")
        judged = ((new and new["images"] >= c.min_area_images and (base or neighbour is not None))
                  or (m and m["endpoints"] >= c.min_area_endpoints))
        entry["drift"] = round(float(score), 4)
        entry["actions"] = (["re-capture"] if reasons else []) + (["update map"] if map_reasons else [])
        entry["reasons"] = reasons + map_reasons
        entry["verdict"] = ", ".join(entry["actions"]) if entry["actions"] else ("ok" if judged else "too few data")
        out[key] = entry
    return out


def recommendation(areas: dict, images: dict, baseline: dict | None, cfg: SitelocConfig) -> dict:
    recapture = [k for k, e in areas.items() if "re-capture" in e["actions"]]
    remap = [k for k, e in areas.items() if "update map" in e["actions"]]
    new_map, base_map = (images.get("all") or {}).get("detector_map_50"), ((baseline or {}).get("all") or {}).get(
        "detector_map_50")
    retrain = new_map is not None and base_map is not None and base_map - new_map > cfg.check.max_map_drop
    lines = []
    lines.append("Re-capture " + ", ".join(recapture) + " (siteloc synth --area / a new capture of them, then "
                 "siteloc update)." if recapture else "No area needs re-capturing.")
    lines.append("Update the map in " + ", ".join(remap) + " (their new runs go into siteloc update)." if remap
                 else "The map still fits the scans.")
    if new_map is None or base_map is None:
        lines.append("Detector: not measured (the new images have no boxes, or the bundle has no baseline).")
    else:
        tol = cfg.check.max_map_drop
        lines.append(f"Retrain the detector: mAP@0.5 {new_map:.2f} on the new images against {base_map:.2f} at "
                     f"export, a drop beyond check.max_map_drop {tol:.2f} (train-detector --init-from)." if retrain
                     else f"The detector need not be retrained: mAP@0.5 {new_map:.2f} on the new images against "
                     f"{base_map:.2f} at export, within check.max_map_drop {tol:.2f}.")
    return {"recapture": recapture, "update_map": remap, "retrain_detector": bool(retrain), "text": lines}


def drift_figure(path: Path, occ_map: OccupancyMap, owner: np.ndarray, names: list[str], areas: dict,
                 mapd: dict) -> Path:
    """PNG: the bundle's map, each area tinted by its drift (green none, yellow at a threshold, red beyond),
    new obstacles in magenta and walls gone in blue; areas with a verdict other than ok are named."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LinearSegmentedColormap

    cmap = LinearSegmentedColormap.from_list("drift", [(0.2, 0.7, 0.3), (0.95, 0.85, 0.2), (0.85, 0.15, 0.15)])
    drift = np.full(len(names), np.nan)
    for i, key in enumerate(names):
        if key in areas and areas[key]["verdict"] != "too few data":
            drift[i] = areas[key]["drift"]
    grey = np.where(occ_map.grid == OCCUPIED, 0.15, np.where(occ_map.grid == FREE, 0.97, 0.7))
    rgb = np.repeat(grey[..., None], 3, axis=2)
    d = drift[owner]
    tint = np.isfinite(d) & (occ_map.grid == FREE)
    rgb[tint] = 0.45 * rgb[tint] + 0.55 * cmap(np.clip(d[tint] / 2.0, 0, 1))[:, :3]
    rgb[mapd["new_obstacles"]] = (0.85, 0.1, 0.85)
    rgb[mapd["walls_gone"]] = (0.1, 0.35, 0.95)
    h, w = occ_map.grid.shape
    fig, ax = plt.subplots(figsize=(min(14, 4 + w / 60), min(12, 3 + h / 60)), dpi=110)
    x0, y0 = occ_map.origin_x, occ_map.origin_y
    ax.imshow(rgb, origin="lower", extent=(x0, x0 + w * occ_map.resolution, y0, y0 + h * occ_map.resolution))
    for i, key in enumerate(names):
        e = areas.get(key)
        if not e or e["verdict"] in ("ok", "too few data"):
            continue
        rr, cc = np.nonzero(owner == i)
        x, y = occ_map.cell_to_world(int(np.median(rr)), int(np.median(cc)))
        ax.annotate(f"{key}\n{e['verdict']}", (float(x), float(y)), ha="center", fontsize=7,
                    bbox={"boxstyle": "round", "fc": "white", "alpha": 0.8})
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 2))
    fig.colorbar(sm, ax=ax, fraction=0.03, label="drift (1 = at a threshold)")
    ax.set_title("drift per area against the bundle (magenta: new obstacles, blue: walls gone)", fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def report_md(doc: dict) -> str:
    lines = [f"# Check of {doc['bundle']['name']} against {doc['data']}", "", *[f"- {t}" for t in
             doc["recommendation"]["text"]], "",
             "| area | verdict | images | recall@4 (baseline) | views changed | views like the bundle's (median) | "
             "endpoints on walls | changed m2 |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]

    def f(v, fmt="{:.2f}"):
        return "-" if v is None else fmt.format(v)

    for key, e in doc["areas"].items():
        n, m = e["new"] or {}, e["map"] or {}
        b = e["baseline"] or (doc.get("baseline_all") or {})
        star = "" if e["baseline"] else "*"
        lines.append(f"| {key} | {e['verdict']} | {n.get('images', 0)} | {f(n.get('recall_at_4'))} "
                     f"({f(b.get('recall_at_4'))}{star}) | {f(e.get('changed_view_share'), '{:.0%}')} | "
                     f"{f(e.get('place_likeness'), '{:.0%}')} | "
                     f"{f(m.get('endpoint_share_on_walls'), '{:.0%}')} | {f(m.get('changed_m2'))} |")
    lines += ["", "Baseline: the bundle's own figures at export, on its held-out stops; * the whole site's, for an "
              "area without held-out stops. Views like the bundle's: 100% identical, 0% no closer than a "
              "neighbouring stop's view; a view is changed under check.min_place_likeness, and an area is "
              "re-captured when more than check.max_changed_views of its views changed.", ""]
    if doc.get("localization"):
        lines.append(f"Localization on the new runs: {doc['localization']}")
    return "\n".join(lines) + "\n"


def _read_new(data: Path):
    """The new data's images, boxes, runs and site (each may be absent but not all)."""
    from pipeline.io import tables
    from pipeline.io.site import read_site

    images = tables.read_table(data / "images.parquet", "images") if (data / "images.parquet").is_file() else None
    boxes = tables.read_table(data / "boxes.parquet", "boxes") if (data / "boxes.parquet").is_file() else None
    runs = [tables.read_table(p, "runs") for p in sorted((data / "runs").glob("*.parquet"))]
    site = read_site(data / "site.yaml") if (data / "site.yaml").is_file() else None
    if images is None and not runs:
        raise InputError(f"{data}: nothing to check the bundle with", [Problem(
            str(data), "neither images.parquet nor runs/", fix="point NEW_DATA at the output of `siteloc ingest` (or "
            "ingest-bag / ingest-log / ingest-colmap / update) of the new captures")])
    return images, boxes, runs, site


def _check_inputs(root: Path, settings: dict, data: Path, images, runs, describer_hw) -> None:
    """New data of the bundle's site: its map frame and extent, laser and camera; a name may differ
    (a changed building is often captured under a new name), so the frame is what identifies the site."""
    from pipeline.errors import Problems
    from pipeline.io.map_yaml import read_map

    problems = Problems()
    if (data / "map.yaml").is_file():
        a, b = read_map(root / "map" / "map.yaml"), read_map(data / "map.yaml")
        fa = (a.width, a.height, a.resolution, a.origin_x, a.origin_y, a.origin_yaw)
        fb = (b.width, b.height, b.resolution, b.origin_x, b.origin_y, b.origin_yaw)
        if not np.allclose(fa, fb, rtol=0, atol=1e-6):
            problems.add(data / "map.yaml", f"map (width, height, resolution, origin) {fb}, the bundle's is {fa}: "
                         f"another site, or the new poses are in another frame",
                         fix="check a bundle against new captures of its own site, in its map frame")
    las = settings["laser"]
    for run in runs:
        got = tuple(float(run.column(k)[0].as_py()) for k in ("angle_min", "angle_increment", "range_max"))
        want = (las["angle_min"], las["angle_increment"], las["range_max"])
        if run.num_rows and not np.allclose(got, want, rtol=0, atol=1e-5):
            problems.add(data / "runs" / f"{run.column('run')[0].as_py()}.parquet", f"laser (angle_min, "
                         f"angle_increment, range_max) {got}, the bundle's is {want}",
                         fix="check with runs of the site's robot")
            break
    if images is not None and images.num_rows:
        sizes = set(zip(images.column("height").to_pylist(), images.column("width").to_pylist(), strict=True))
        other = sorted(s for s in sizes if tuple(s) != tuple(describer_hw))
        if other:
            problems.add(data / "images.parquet", f"images of {other[0][1]} x {other[0][0]} px; the bundle's camera "
                         f"is {describer_hw[1]} x {describer_hw[0]}", fix="capture with the site's camera")
    problems.raise_if_any(f"{data}: cannot check {root} with it; nothing was written")


def _read_baseline(root: Path, given: Path) -> dict:
    """evaluation/baseline.json of a verified bundle; a BundleError naming it (and the bundle given) unless it
    is the JSON object export writes (per-area figures and `all`)."""
    from pipeline.bundle.measure import BASELINE_FILE
    from pipeline.runtime.bundle import BundleError, shown

    where = shown(root, BASELINE_FILE, given if Path(given).is_file() else None)
    try:
        doc = json.loads((root / BASELINE_FILE).read_bytes())
    except (ValueError, RecursionError, OSError) as exc:
        raise BundleError(f"{where}: not readable JSON ({exc}); export the bundle again") from None
    areas = doc.get("areas", {}) if isinstance(doc, dict) else None
    if (not isinstance(areas, dict) or not all(isinstance(v, dict) for v in areas.values())
            or not isinstance(doc.get("all") or {}, dict)):
        raise BundleError(f"{where}: not the per-area figures export writes; export the bundle again")
    return doc


def run_check(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], localize: bool = True,
              force: bool = False, progress: bool = True) -> Path:
    """report.json / report.md / drift.png (and localization/ when the new data has query runs) in
    `outputs['out']`; returns it."""
    import math
    import tempfile

    from pipeline.bundle.measure import BASELINE_FILE, BundleRetriever, image_keys, measure
    from pipeline.io import tables
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.io.map_yaml import read_map
    from pipeline.runtime.bundle import BundleError, open_bundle, read_manifest, read_settings, shown
    from pipeline.update.areas import cell_owners, stops_of

    out, data = Path(outputs["out"]), Path(inputs["data"])
    check_output(out, force=force, inputs=inputs.values())
    with tempfile.TemporaryDirectory(prefix="siteloc-check-") as work:
        root = open_bundle(Path(inputs["bundle"]), Path(work) if Path(inputs["bundle"]).is_file() else None)
        manifest = read_manifest(root)
        if not (root / "db" / "images.parquet").is_file():
            given = Path(inputs["bundle"])
            raise BundleError(f"{shown(root, 'db/images.parquet', given if given.is_file() else None)}: missing; the "
                              f"bundle was exported before bundles named their stops: export it again with this "
                              f"siteloc to check it")
        images, boxes, runs, site = _read_new(data)
        settings = read_settings(root)  # checked by open_bundle already
        retriever = BundleRetriever.from_dir(root, settings["retrieval"])
        _check_inputs(root, settings, data, images, runs, retriever.describer.image_hw)
        bundle_images = tables.read_table(root / "db" / "images.parquet", "images")
        classes = list(site.classes) if site else list(json.loads(
            (root / "models" / "describer.json").read_text()).get("classes") or [])
        c = cfg.check
        figures = {"areas": {}, "all": None}
        baseline = _read_baseline(root, inputs["bundle"]) if (root / BASELINE_FILE).is_file() else None
        neighbour = ((baseline or {}).get("all") or {}).get("neighbour_similarity")
        if images is not None and images.num_rows:
            keys = image_keys(images, bundle_images, cfg.update.proximity_m)
            figures = measure(retriever, data, images, boxes, keys, check=c, classes=classes, progress=progress,
                              changed_below=None if neighbour is None else changed_below(neighbour, c))
        occ_map = read_map(root / "map" / "map.yaml")
        stops = stops_of(bundle_images)
        owner, names = cell_owners(occ_map, stops.xy, stops.keys())
        las = settings["laser"]
        mapd = map_drift(occ_map, owner, names, runs, tuple(las["base_from_laser"]), cfg, progress=progress)
        areas = verdicts(figures, baseline, mapd, cfg)
        rec = recommendation(areas, figures, baseline, cfg)
        has_queries = any(p.stem.startswith("query") for p in (data / "runs").glob("*.parquet"))
        doc = {"bundle": {"name": root.name if not Path(inputs["bundle"]).is_file() else Path(inputs["bundle"]).name,
                          "path": str(inputs["bundle"]), "site": manifest.get("site"),
                          "version": manifest.get("bundle_version")},
               "data": str(data), "baseline": baseline is not None, "recommendation": rec, "areas": areas,
               "images": figures.get("all"), "baseline_all": (baseline or {}).get("all"),
               "map": {k: v for k, v in mapd.items() if k not in ("new_obstacles", "walls_gone", "areas")},
               "thresholds": c.model_dump(mode="json"),
               "warnings": [f"{data / 'site.yaml'}: site '{site.name}', the bundle's is '{manifest.get('site')}'"]
               if site is not None and site.name != manifest.get("site") else []}
        with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
            if localize and has_queries:
                from pipeline.evaluation.report import run_evaluate

                run_evaluate(cfg, inputs={"bundle": root, "data": data}, outputs={"out": tmp / "localization"},
                             progress=progress)
                summary = json.loads((tmp / "localization" / "metrics.json").read_text()).get("summary")
                doc["localization"] = summary
            drift_figure(tmp / "drift.png", occ_map, owner, names, areas, mapd)
            text = json.dumps(doc, indent=2, default=lambda v: None if isinstance(v, float) and math.isnan(v) else v)
            write_text_atomic(tmp / "report.json", text + "\n")
            write_text_atomic(tmp / "report.md", report_md(doc))
            write_effective_config(cfg, tmp, stage="check", inputs=inputs)
    return out
