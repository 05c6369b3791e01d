"""Stage `update`: a site database with new captures of the areas that changed, everything else untouched.

New stops replace every old stop of the areas they cover (pipeline.update.areas); stops listed in
`remove_stops` go too. Rows, boxes and image files of the other stops are kept as they were. New runs
are added (one of the same name replaces the old). The map is patched from the new runs' scans inside
the changed areas only (pipeline.update.map_patch). changelog.json says what changed against the parent.
Every problem is found before anything is written, and the output appears only when complete.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problems
from pipeline.io import tables
from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
from pipeline.io.map_yaml import OccupancyMap, read_map, write_map
from pipeline.io.site import Site, read_site, write_site
from pipeline.runtime.bundle import sha256_of
from pipeline.update.areas import Stops, assign_areas, cell_owners, stops_of

CHANGELOG_VERSION = 1


@dataclass
class SiteDb:
    root: Path
    site: Site
    occ_map: OccupancyMap
    images: pa.Table
    boxes: pa.Table
    runs: dict[str, pa.Table]


def read_site_db(root: Path) -> SiteDb:
    """An ingested site (the output of any `ingest*` stage or of `update`)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a site database", [_problem(root, "not a directory",
                                                                  "pass the --out of `siteloc ingest`")])
    site = read_site(root / "site.yaml")
    occ_map = read_map(root / "map.yaml")
    images = tables.read_table(root / "images.parquet", "images")
    boxes = tables.read_table(root / "boxes.parquet", "boxes")
    runs = {p.stem: tables.read_table(p, "runs") for p in sorted((root / "runs").glob("*.parquet"))}
    return SiteDb(root, site, occ_map, images, boxes, runs)


def _problem(path, message, fix=None):
    from pipeline.errors import Problem

    return Problem(str(path), message, fix=fix)


def check_compatible(old: SiteDb, new: SiteDb, problems: Problems) -> None:
    """New captures must share the old site's camera, rig, laser, classes and map frame."""
    for part in ("camera", "rig", "laser", "classes"):
        a, b = getattr(old.site, part), getattr(new.site, part)
        if a != b:
            problems.add(new.root / "site.yaml", f"its {part} differs from the site database's "
                         f"({_short(b)} against {_short(a)})", key=part,
                         fix="capture with the same sensors and rig, or build a new site database with `ingest`")
    m, n = old.occ_map, new.occ_map
    frame_a = (m.resolution, m.origin_x, m.origin_y, m.origin_yaw)
    frame_b = (n.resolution, n.origin_x, n.origin_y, n.origin_yaw)
    if not np.allclose(frame_a, frame_b, rtol=0, atol=1e-6):
        problems.add(new.root / "map.yaml", "its map frame (resolution, origin) differs from the site database's: "
                     f"{frame_b} against {frame_a}", fix="express the new captures in the site's map frame "
                     "(the same map.yaml), e.g. align them as `ingest-colmap` does")


def _short(value) -> str:
    text = value.model_dump_json() if hasattr(value, "model_dump_json") else repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def _relabel(images: pa.Table, labels: dict[str, tuple[str, str | None, str | None]]) -> pa.Table:
    """New rows with the room/area their stop was assigned (unchanged for labelled stops)."""
    stop = images.column("stop_id").to_pylist()
    room = pa.array([labels[s][1] for s in stop], pa.string())
    area = pa.array([labels[s][2] for s in stop], pa.string())
    images = images.set_column(images.schema.get_field_index("room"), images.schema.field("room"), room)
    return images.set_column(images.schema.get_field_index("area"), images.schema.field("area"), area)


def _image_ids(images: pa.Table, runs: dict[str, pa.Table]) -> set[str]:
    ids = set(images.column("image_id").to_pylist())
    for t in runs.values():
        ids |= {i for i in t.column("image_id").to_pylist() if i}
    return ids


def plan_update(old: SiteDb, new: SiteDb, *, remove_stops: list[str], remove_runs: list[str], proximity_m: float,
                allow_new_areas: bool) -> dict:
    """What the update does, or one InputError listing every problem with the inputs."""
    problems = Problems()
    check_compatible(old, new, problems)
    old_stops, new_stops = stops_of(old.images), stops_of(new.images)
    labels = assign_areas(old_stops, new_stops, proximity_m=proximity_m, allow_new_areas=allow_new_areas,
                          where=str(new.root / "images.parquet"), problems=problems)
    old_keys = dict(zip(old_stops.stop_id, old_stops.keys(), strict=True))
    for s in remove_stops:
        if s not in old_keys:
            problems.add(old.root / "images.parquet", f"--remove-stop '{s}' is not a stop of the site database",
                         fix="name a stop_id of its images.parquet")
    for r in remove_runs:
        if r not in old.runs:
            problems.add(old.root / "runs", f"--remove-run '{r}' is not a run of the site database",
                         fix="name one of: " + (", ".join(old.runs) or "(it has none)"))
    changed = sorted({k for k, _, _ in labels.values()})
    replaced = [s for s, k in old_keys.items() if k in set(changed)]
    dropped = set(replaced) | set(remove_stops)
    kept_stops = [s for s in old_stops.stop_id if s not in dropped]
    clash = sorted(set(kept_stops) & set(new_stops.stop_id))
    if clash:
        problems.add(new.root / "images.parquet", f"stop ids {clash[:5]} are also untouched stops of the site "
                     "database (they lie in areas the new captures do not cover)",
                     fix="give the new stops ids of their own")
    kept_runs = {k: v for k, v in old.runs.items() if k not in set(remove_runs) and k not in new.runs}
    kept_images = old.images.filter(pc.invert(pc.is_in(old.images.column("stop_id"), pa.array(sorted(dropped),
                                                                                             pa.string()))))
    clash = sorted(_image_ids(kept_images, kept_runs) & _image_ids(new.images, new.runs))
    if clash:
        problems.add(new.root, f"{len(clash)} image paths of the new captures are also images the site database "
                     f"keeps (e.g. {clash[0]})", fix="store the new images under other names")
    problems.raise_if_any(f"{new.root}: cannot update {old.root} with it; nothing was written")
    return {"labels": labels, "changed_areas": changed, "replaced": replaced, "removed": sorted(remove_stops),
            "kept_images": kept_images, "kept_runs": kept_runs, "old_stops": old_stops, "new_stops": new_stops}


def _link_all(ids: set[str], src: Path, dst: Path, link: bool) -> None:
    from pipeline.ingest import _link_or_copy

    for rel in sorted(ids):
        _link_or_copy(src / rel, dst / rel, link)


def _db_report(site_name: str, images: pa.Table, boxes: pa.Table, runs: dict[str, pa.Table], occ_map: OccupancyMap,
               classes: tuple[str, ...]) -> dict:
    """The counts `ingest` reports, of the updated database."""
    from collections import Counter

    stops = dict(zip(images.column("stop_id").to_pylist(), images.column("split").to_pylist(), strict=True))
    rooms = images.column("room").to_pylist()
    names = boxes.column("class_name").to_pylist()
    return {
        "site": site_name, "images": images.num_rows, "stops": len(stops),
        "stops_per_split": dict(sorted(Counter(stops.values()).items())),
        "rooms": len({r for r in rooms if r}),
        "areas": len({(r, a) for r, a in zip(rooms, images.column("area").to_pylist(), strict=True) if a}),
        "boxes": boxes.num_rows, "boxes_per_class": {c: names.count(c) for c in classes},
        "runs": {k: {"steps": t.num_rows, "images": sum(i is not None for i in t.column("image_id").to_pylist()),
                     "with_ground_truth": int(t.column("gt_x").is_valid().to_numpy(zero_copy_only=False).sum())}
                 for k, t in runs.items()},
        "map": {"width_cells": occ_map.width, "height_cells": occ_map.height, "resolution": occ_map.resolution,
                "free_share": round(float(occ_map.free.mean()), 4)},
        "warnings": [],
    }


def run_update(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
               remove_stops: list[str] | None = None, remove_runs: list[str] | None = None,
               allow_new_areas: bool = False, force: bool = False, progress: bool = True) -> Path:
    """`inputs['site_db']` updated with `inputs['new_data']` (both ingested) into `outputs['out']`."""
    from pipeline.ingest import _report_md
    from pipeline.io.map_yaml import OCCUPIED
    from pipeline.update.map_patch import patch_figure, patch_map

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    old, new = read_site_db(inputs["site_db"]), read_site_db(inputs["new_data"])
    plan = plan_update(old, new, remove_stops=list(remove_stops or []), remove_runs=list(remove_runs or []),
                       proximity_m=cfg.update.proximity_m, allow_new_areas=allow_new_areas)
    labels, changed = plan["labels"], plan["changed_areas"]
    kept_images, kept_runs = plan["kept_images"], plan["kept_runs"]
    old_stops: Stops = plan["old_stops"]
    new_images = _relabel(new.images, labels)
    images = pa.concat_tables([kept_images, new_images.cast(kept_images.schema)])
    kept_ids = set(kept_images.column("image_id").to_pylist())
    old_boxes = old.boxes.filter(pc.is_in(old.boxes.column("image_id"), pa.array(sorted(kept_ids), pa.string())))
    boxes = pa.concat_tables([old_boxes, new.boxes.cast(old_boxes.schema)])
    runs = {**kept_runs, **new.runs}

    # The map: every cell belongs to the area of its nearest stop (of the updated database).
    stop_keys = {s: k for s, k in zip(old_stops.stop_id, old_stops.keys(), strict=True)}
    stop_keys.update({s: k for s, (k, _, _) in labels.items()})
    all_stops = stops_of(images)
    owner, names = cell_owners(old.occ_map, all_stops.xy, [stop_keys[s] for s in all_stops.stop_id])
    region = np.isin(owner, [names.index(k) for k in changed if k in names])
    mount = old.site.laser.mount
    patch = patch_map(old.occ_map, list(new.runs.values()), (mount.x, mount.y, np.radians(mount.yaw_deg)), region,
                      cfg.update.mapping, tolerance_m=cfg.update.map_tolerance_m, progress=progress)
    changed_cells = np.bincount(owner[patch.changed], minlength=len(names))
    observed_cells = np.bincount(owner[patch.observed], minlength=len(names))

    new_stops = plan["new_stops"]
    per_old = dict(zip(*np.unique(old.images.column("stop_id").to_numpy(zero_copy_only=False), return_counts=True),
                       strict=True))
    per_new = dict(zip(*np.unique(new.images.column("stop_id").to_numpy(zero_copy_only=False), return_counts=True),
                       strict=True))
    areas = {}
    for key in sorted(set(changed) | {old_stops.key(old_stops.stop_id.index(s)) for s in plan["removed"]}):
        removed = [s for s in old_stops.stop_id if stop_keys[s] == key and (s in plan["replaced"] or
                                                                           s in plan["removed"])]
        added = [s for s in new_stops.stop_id if labels[s][0] == key]
        i = names.index(key) if key in names else None
        areas[key] = {"stops_removed": removed, "stops_added": added,
                      "images_removed": int(sum(per_old[s] for s in removed)),
                      "images_added": int(sum(per_new[s] for s in added)),
                      "map_cells_observed": int(observed_cells[i]) if i is not None else 0,
                      "map_cells_changed": int(changed_cells[i]) if i is not None else 0}
    map_image = old.root / read_map_image_name(old.root / "map.yaml")
    changelog = {
        "changelog_version": CHANGELOG_VERSION,
        "parent": {"path": str(old.root), "site": old.site.name,
                   "images_sha256": sha256_of(old.root / "images.parquet"), "map_sha256": sha256_of(map_image)},
        "new_data": {"path": str(new.root), "site": new.site.name,
                     "images_sha256": sha256_of(new.root / "images.parquet")},
        "changed_areas": changed,
        "areas": areas,
        "stops_removed_explicitly": plan["removed"],
        "runs": {"added": sorted(set(new.runs) - set(old.runs)), "replaced": sorted(set(new.runs) & set(old.runs)),
                 "removed": sorted(set(old.runs) - set(kept_runs) - set(new.runs)), "kept": sorted(kept_runs)},
        "map": {"patched": bool(patch.changed.any()), "scans_used": patch.scans,
                "cells_in_changed_areas": int(region.sum()), "cells_observed": int(patch.observed.sum()),
                "cells_changed": int(patch.changed.sum()),
                "cells_now_occupied": int((patch.changed & (patch.occ_map.grid == OCCUPIED)).sum()),
                "cells_no_longer_occupied": int((patch.changed & (old.occ_map.grid == OCCUPIED)).sum())},
        "totals": {"stops_kept": len(stops_of(kept_images).stop_id), "stops_added": len(new_stops.stop_id),
                   "images_kept": kept_images.num_rows, "images_added": new_images.num_rows,
                   "images": images.num_rows},
    }
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        link = cfg.ingest.link_images
        _link_all(_image_ids(kept_images, kept_runs), old.root, tmp, link)
        _link_all(_image_ids(new.images, new.runs), new.root, tmp, link)
        meta = {"site": old.site.name}
        tables.write_table(tmp / "images.parquet", images, "images", meta)
        tables.write_table(tmp / "boxes.parquet", boxes, "boxes", meta)
        for name, t in runs.items():
            tables.write_table(tmp / "runs" / f"{name}.parquet", t, "runs")
        write_map(tmp / "map.yaml", patch.occ_map)
        write_site(tmp / "site.yaml", old.site)
        patch_figure(tmp / "map_patch.png", old.occ_map, patch, region)
        rep = _db_report(old.site.name, images, boxes, runs, patch.occ_map, old.site.classes)
        write_text_atomic(tmp / "report.json", json.dumps(rep, indent=2) + "\n")
        write_text_atomic(tmp / "report.md", _report_md(rep))
        write_text_atomic(tmp / "changelog.json", json.dumps(changelog, indent=2) + "\n")
        write_text_atomic(tmp / "changelog.md", changelog_md(changelog))
        write_effective_config(cfg, tmp, stage="update", inputs=inputs)
    return out


def read_map_image_name(yaml_path: Path) -> str:
    import yaml

    return str(yaml.safe_load(Path(yaml_path).read_text())["image"])


def changelog_md(c: dict) -> str:
    """The changelog as a short Markdown page."""
    lines = [f"# Update of {c['parent']['site']}", "",
             f"Parent: `{c['parent']['path']}`; new captures: `{c['new_data']['path']}`.", "",
             "| area | stops removed | stops added | images removed | images added | map cells changed |",
             "| --- | --- | --- | --- | --- | --- |"]
    for key, a in c["areas"].items():
        lines.append(f"| {key} | {len(a['stops_removed'])} | {len(a['stops_added'])} | {a['images_removed']} | "
                     f"{a['images_added']} | {a['map_cells_changed']} |")
    m, r, t = c["map"], c["runs"], c["totals"]
    lines += ["", f"Map: {m['cells_changed']} cells changed ({m['cells_now_occupied']} now occupied, "
              f"{m['cells_no_longer_occupied']} no longer occupied) from {m['scans_used']} scans; "
              f"{m['cells_observed']} of the {m['cells_in_changed_areas']} cells of the changed areas were observed.",
              "", f"Runs: added {r['added'] or 'none'}, replaced {r['replaced'] or 'none'}, removed "
              f"{r['removed'] or 'none'}.", "",
              f"Kept {t['stops_kept']} stops ({t['images_kept']} images) untouched; added {t['stops_added']} stops "
              f"({t['images_added']} images)."]
    if c["stops_removed_explicitly"]:
        lines += ["", "Removed on request: " + ", ".join(c["stops_removed_explicitly"]) + "."]
    return "\n".join(lines) + "\n"
