"""What changed between two bundles of one site: stops per area, map cells, models and database.

Both bundles are read as they are on disk (`BundleView`); `export --parent` runs the same comparison
against its parent and ships the result as the new bundle's changelog, and `siteloc diff` prints it.
A stop is identified by its id and fingerprinted by its images' (image id, sha256) pairs, so a stop
re-captured under the same id shows as re-captured, not as kept. Map cells are counted per area of the
newer bundle's database stops on the older map (the geodesic partition `update` patches by). A model or
database is kept when the input it was exported from has the same content hash (manifest `provenance`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.errors import SitelocError
from pipeline.io.map_yaml import OccupancyMap

DIFF_VERSION = 1
STOPS_FILE = "db/images.parquet"  # the database images' rows of the ingest: stop, labels, pose, sha256
COMPONENTS = ("model", "index", "data", "sequence", "prior")


class DiffError(SitelocError):
    """Two bundles that cannot be compared (another site, no stop table)."""


@dataclass
class BundleView:
    """A bundle's parts the comparison reads: its manifest entries, database stops and map."""

    root: Path
    name: str
    site: str
    version: str
    provenance: dict
    files: dict[str, str]  # relative path -> sha256
    images: pa.Table
    occ_map: OccupancyMap


def read_view(root: Path, manifest: dict, files: dict[str, str] | None = None) -> BundleView:
    """The view of a bundle directory; `files` overrides the manifest's (a bundle being written)."""
    from pipeline.io import tables
    from pipeline.io.map_yaml import read_map

    root = Path(root)
    if not (root / STOPS_FILE).is_file():
        raise DiffError(f"{root / STOPS_FILE}: missing; the bundle was exported before bundles named their stops: "
                        f"export it again with this siteloc to compare it")
    listed = files if files is not None else {k: v["sha256"] for k, v in manifest["files"].items()}
    return BundleView(root=root, name=root.name, site=str(manifest.get("site")),
                      version=str(manifest.get("bundle_version")), provenance=manifest.get("provenance") or {},
                      files=listed, images=tables.read_table(root / STOPS_FILE, "images"),
                      occ_map=read_map(root / "map" / "map.yaml"))


def stop_fingerprints(images: pa.Table) -> dict[str, tuple[str, str]]:
    """{stop_id: (area key, sha256 over its sorted (image_id, image sha256) pairs)}."""
    from pipeline.update.areas import area_key

    cols = images.select(["stop_id", "image_id", "sha256", "room", "area"]).to_pydict()
    pairs: dict[str, list[tuple[str, str]]] = {}
    keys: dict[str, str] = {}
    for sid, iid, sha, room, area in zip(*cols.values(), strict=True):
        pairs.setdefault(sid, []).append((iid, sha))
        keys.setdefault(sid, area_key(room, area, sid))
    out = {}
    for sid, p in pairs.items():
        h = hashlib.sha256("".join(f"{i}\0{s}\n" for i, s in sorted(p)).encode()).hexdigest()
        out[sid] = (keys[sid], h)
    return out


def _areas(a: BundleView, b: BundleView) -> dict[str, dict]:
    fa, fb = stop_fingerprints(a.images), stop_fingerprints(b.images)
    per: dict[str, dict] = {}

    def entry(key: str) -> dict:
        return per.setdefault(key, {"stops_kept": 0, "stops_added": [], "stops_removed": [], "stops_recaptured": []})

    for sid, (key, h) in fa.items():
        if sid not in fb:
            entry(key)["stops_removed"].append(sid)
        elif fb[sid][1] != h:
            entry(fb[sid][0])["stops_recaptured"].append(sid)
        else:
            entry(fb[sid][0])["stops_kept"] += 1
    for sid, (key, _) in fb.items():
        if sid not in fa:
            entry(key)["stops_added"].append(sid)
    for e in per.values():
        changed = e["stops_added"] or e["stops_removed"] or e["stops_recaptured"]
        e["status"] = ("new" if not e["stops_kept"] and not e["stops_removed"] and not e["stops_recaptured"]
                       else "gone" if not e["stops_kept"] and not e["stops_added"] and not e["stops_recaptured"]
                       else "re-captured" if changed else "unchanged")
    return dict(sorted(per.items()))


def _map(a: BundleView, b: BundleView) -> dict:
    from pipeline.io.map_yaml import OCCUPIED
    from pipeline.update.areas import cell_owners, stops_of

    m, n = a.occ_map, b.occ_map
    if (m.width, m.height) != (n.width, n.height) or not np.allclose(
            (m.resolution, m.origin_x, m.origin_y, m.origin_yaw), (n.resolution, n.origin_x, n.origin_y, n.origin_yaw),
            rtol=0, atol=1e-6):
        return {"same_frame": False, "cells_changed": None, "per_area": {}}
    changed = m.grid != n.grid
    stops = stops_of(b.images)
    per_area: dict[str, int] = {}
    if changed.any() and stops.stop_id:
        owner, names = cell_owners(m, stops.xy, stops.keys())  # as `update` splits the map it patches
        counts = np.bincount(owner[changed], minlength=len(names))
        per_area = {names[i]: int(c) for i, c in enumerate(counts) if c}
    return {"same_frame": True, "cells_changed": int(changed.sum()),
            "cells_now_occupied": int((changed & (n.grid == OCCUPIED)).sum()),
            "cells_no_longer_occupied": int((changed & (m.grid == OCCUPIED)).sum()),
            "per_area": dict(sorted(per_area.items()))}


def _components(a: BundleView, b: BundleView) -> dict[str, str]:
    """Each input the bundles were exported from: kept, changed, added or removed (by content hash)."""
    ia, ib = a.provenance.get("inputs") or {}, b.provenance.get("inputs") or {}
    out = {}
    for name in COMPONENTS:
        ha, hb = (ia.get(name) or {}).get("sha256"), (ib.get(name) or {}).get("sha256")
        if ha is None and hb is None:
            continue
        out[name] = ("added" if ha is None else "removed" if hb is None else "kept" if ha == hb else "changed")
    return out


def _files(a: BundleView, b: BundleView) -> dict[str, list[str]]:
    fa, fb = a.files, b.files
    return {"changed": sorted(k for k in fa.keys() & fb.keys() if fa[k] != fb[k]),
            "added": sorted(fb.keys() - fa.keys()), "removed": sorted(fa.keys() - fb.keys()),
            "same": sorted(k for k in fa.keys() & fb.keys() if fa[k] == fb[k])}


def diff_bundles(a: BundleView, b: BundleView) -> dict:
    """What `b` changed against `a` (both bundles of one site)."""
    if a.site != b.site:
        raise DiffError(f"{b.root}: a bundle of site '{b.site}', {a.root} is of '{a.site}'; compare bundles of one "
                        f"site (a bundle of another site shares no stops or map with it)")
    areas = _areas(a, b)
    totals = {k: sum(len(e[k]) for e in areas.values()) for k in ("stops_added", "stops_removed", "stops_recaptured")}
    totals["stops_kept"] = sum(e["stops_kept"] for e in areas.values())
    return {
        "diff_version": DIFF_VERSION,
        "from": {"name": a.name, "version": a.version}, "to": {"name": b.name, "version": b.version},
        "areas_changed": [k for k, e in areas.items() if e["status"] != "unchanged"],
        "areas": areas, "stops": totals, "map": _map(a, b), "components": _components(a, b), "files": _files(a, b),
    }


def diff_md(d: dict) -> str:
    """The diff as a short Markdown page."""
    s, m = d["stops"], d["map"]
    lines = [f"# {d['to']['name']} against {d['from']['name']}", "",
             f"Stops: {s['stops_kept']} kept, {s['stops_added']} added, {s['stops_removed']} removed, "
             f"{s['stops_recaptured']} re-captured under the same id.", ""]
    changed = [(k, e) for k, e in d["areas"].items() if e["status"] != "unchanged"]
    if changed:
        lines += ["| area | status | kept | added | removed | re-captured | map cells changed |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for k, e in changed:
            lines.append(f"| {k} | {e['status']} | {e['stops_kept']} | {len(e['stops_added'])} | "
                         f"{len(e['stops_removed'])} | {len(e['stops_recaptured'])} | {m['per_area'].get(k, 0)} |")
    else:
        lines.append("No area changed.")
    lines.append("")
    if not m["same_frame"]:
        lines.append("Map: another frame or size; cells are not compared.")
    else:
        lines.append(f"Map: {m['cells_changed']} cells changed ({m['cells_now_occupied']} now occupied, "
                     f"{m['cells_no_longer_occupied']} no longer occupied).")
        outside = {k: v for k, v in m["per_area"].items() if k not in d["areas_changed"]}
        if outside:
            lines.append(f"Of them in areas whose stops did not change: {json.dumps(outside)} (cells go to the area "
                         "of the nearest database stop, so a changed area's edge can fall in its neighbour).")
    lines += ["", "Inputs: " + (", ".join(f"{k} {v}" for k, v in d["components"].items()) or "not recorded") + "."]
    f = d["files"]
    lines += ["", f"Files: {len(f['same'])} identical, {len(f['changed'])} changed, {len(f['added'])} added, "
              f"{len(f['removed'])} removed."]
    return "\n".join(lines) + "\n"


def next_version(version: str) -> str:
    """The parent's version with its last number raised by one (0.1.0 -> 0.1.1, v3 -> v4)."""
    import re

    found = list(re.finditer(r"\d+", version))
    if not found:
        return f"{version}.1"
    last = found[-1]
    return f"{version[:last.start()]}{int(last.group()) + 1}{version[last.end():]}"


def figures_on(root: Path, data: Path, cfg, *, progress: bool = True) -> dict:
    """`pipeline.bundle.measure` of the bundle at `root` on the images of the ingested site `data`."""
    from pipeline.bundle.measure import BundleRetriever, image_keys, measure
    from pipeline.io import tables
    from pipeline.io.site import read_site
    from pipeline.runtime.bundle import read_settings

    images = tables.read_table(data / "images.parquet", "images")
    boxes = tables.read_table(data / "boxes.parquet", "boxes") if (data / "boxes.parquet").is_file() else None
    settings = read_settings(root)
    keys = image_keys(images, tables.read_table(root / STOPS_FILE, "images"), cfg.update.proximity_m)
    return measure(BundleRetriever.from_dir(root, settings["retrieval"]), data, images, boxes, keys,
                   check=cfg.check, classes=list(read_site(data / "site.yaml").classes), progress=progress)


def figures_md(fa: dict, fb: dict, a: str, b: str) -> str:
    lines = ["", f"## On the same images: {a} | {b}", "",
             "| area | images | recall@1 | recall@4 | same-place similarity | detector mAP@0.5 |",
             "| --- | --- | --- | --- | --- | --- |"]

    def f(v):
        return "-" if v is None else f"{v:.2f}"

    def pair(x, y, k):
        return f"{f((x or {}).get(k))} / {f((y or {}).get(k))}"

    for key in sorted(set(fa["areas"]) | set(fb["areas"])) + ["all"]:
        x, y = (fa.get("all"), fb.get("all")) if key == "all" else (fa["areas"].get(key), fb["areas"].get(key))
        lines.append(f"| {key} | {(x or y or {}).get('images', 0)} | {pair(x, y, 'recall_at_1')} | "
                     f"{pair(x, y, 'recall_at_4')} | {pair(x, y, 'same_place_similarity')} | "
                     f"{pair(x, y, 'detector_map_50')} |")
    return "\n".join(lines) + "\n"


def run_diff(cfg, *, inputs: dict[str, Path], outputs: dict[str, Path], force: bool = False,
             progress: bool = True) -> dict:
    """The diff of inputs['a'] -> inputs['b'] (bundles, directory or .tar.gz), with both bundles' figures on
    inputs['data'] when given; written as diff.json / diff.md into outputs['out'] when given."""
    import tempfile

    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.runtime.bundle import open_bundle, read_manifest

    out = outputs.get("out")
    if out is not None:
        check_output(Path(out), force=force, inputs=inputs.values())
    with tempfile.TemporaryDirectory(prefix="siteloc-diff-") as work:
        roots = []
        for i, key in enumerate(("a", "b")):
            p = Path(inputs[key])
            roots.append(open_bundle(p, Path(work) / str(i) if p.is_file() else None))
        views = [read_view(r, read_manifest(r)) for r in roots]  # both verified by open_bundle
        for v, key in zip(views, ("a", "b"), strict=True):
            if Path(inputs[key]).is_file():
                v.name = Path(inputs[key]).name.removesuffix(".tar.gz").removesuffix(".tgz")
        d = diff_bundles(*views)
        text = diff_md(d)
        if inputs.get("data") is not None:
            data = Path(inputs["data"])
            fa, fb = (figures_on(r, data, cfg, progress=progress) for r in roots)
            d["figures"] = {"data": str(data), "a": fa, "b": fb}
            text += figures_md(fa, fb, views[0].name, views[1].name)
    d["markdown"] = text
    if out is not None:
        with atomic_dir(Path(out), force=force, inputs=inputs.values()) as tmp:
            write_text_atomic(tmp / "diff.json", json.dumps({k: v for k, v in d.items() if k != "markdown"},
                                                            indent=2) + "\n")
            write_text_atomic(tmp / "diff.md", text)
    return d
