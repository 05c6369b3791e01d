"""Stages `prior build`, `prior append` and `prior query`: seed 001's model database as a product.

- `build`: fit each layer's compression on the database images (`train` split, or every image), index
  them, fit the per-(room, area) Gaussians; writes the prior directory (`AreaPrior.save`), report.json
  and config.yaml.
- `append`: a new area's (or a changed area's) images into a copy of a prior, with its fitted
  compressions; nothing else is refitted (the paper's scalability argument).
- `update`: a copy of a prior brought to the images of a newer `prior features` output (after `siteloc
  update`): rows whose image bytes are gone are dropped, new images appended, the rest kept bit for bit.
- `query`: camera images to (room, area) probabilities.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem


def _report(prior, extra: dict) -> str:
    return json.dumps({"images": len(prior.labels), "classes": len(prior.classes),
                       "layers": {n: int(prior.vectors[n].shape[1]) for n in prior.layers},
                       "memory_kb": {n: round(v / 1024, 1) for n, v in prior.nbytes().items()},
                       "encoder": prior.encoder, **extra}, indent=2) + "\n"


def run_prior_build(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], all_images: bool = False,
                    force: bool = False) -> Path:
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.prior.evaluate import build_prior
    from pipeline.prior.features import read_layers, select

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    meta, raw, rep = read_layers(Path(inputs["features"]))
    keep = np.ones(len(meta["image_id"]), bool) if all_images else np.asarray(meta["split"]) == "train"
    if keep.sum() < 2:
        raise InputError(f"{inputs['features']}: too few database images", [Problem(
            str(inputs["features"]), f"{int(keep.sum())} images in the database", fix="use --all, or more captures")])
    sha = _feature_hashes(Path(inputs["features"]))
    meta, raw = select(meta, raw, keep)
    prior = build_prior(cfg, meta, raw, rep["encoder"])
    comps = {n: {"kind": prior.compressors[n].KIND, "dims": int(prior.compressors[n].n_components_),
                 "cap": prior.compressors[n].cap_reason_} for n in prior.layers}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        prior.save(tmp)
        _write_prior_hashes(tmp, prior, sha)
        write_text_atomic(tmp / "report.json", _report(prior, {
            "database": "all" if all_images else "train", "compression": comps, "appended": []}))
        write_effective_config(cfg, tmp, stage="prior-build", inputs=inputs)
    return out


def run_prior_append(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                     rooms: list[str] | None = None, force: bool = False) -> Path:
    """A copy of `inputs['prior']` with the images of `inputs['features']` (those of `rooms` if given) added."""
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.prior.features import read_layers, select
    from pipeline.prior.model import AreaPrior

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    src = Path(inputs["prior"])
    prior = AreaPrior.load(src)
    meta, raw, rep = read_layers(Path(inputs["features"]))
    feats = Path(inputs["features"])
    _require_same_encoder(prior, rep, feats)
    keep = np.ones(len(meta["image_id"]), bool) if not rooms else np.isin(meta["room"], rooms)
    if not keep.any():
        raise InputError(f"{feats}: nothing to append", [Problem(
            str(feats), f"no image in rooms {rooms}", fix=f"rooms there: {sorted(set(meta['room']))[:20]}")])
    meta, raw = select(meta, raw, keep)
    known = set(prior.rows["image_id"])
    dup = [i for i, m in enumerate(meta["image_id"]) if m in known]
    if dup:
        raise InputError(f"{feats}: {len(dup)} images are in the prior already", [Problem(
            str(feats), f"image '{meta['image_id'][i]}'", fix="append only new images (--room picks rooms)")
            for i in dup[:10]])
    before = len(prior.classes)
    touched = prior.append(meta, raw)
    doc = json.loads((src / "report.json").read_text()) if (src / "report.json").is_file() else {}
    appended = doc.get("appended", []) + [{"features": str(feats), "images": len(meta["image_id"]),
                                           "new_classes": len(prior.classes) - before,
                                           "refitted_classes": len([k for k in touched if k < before])}]
    sha = {**_prior_hashes(src, required=False), **_feature_hashes(feats)}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        prior.save(tmp)
        _write_prior_hashes(tmp, prior, sha)
        extra = {k: doc[k] for k in ("database", "updated") if k in doc}
        extra |= {"compression": doc.get("compression"), "appended": appended}
        write_text_atomic(tmp / "report.json", _report(prior, extra))
        if (src / "config.yaml").is_file():
            shutil.copyfile(src / "config.yaml", tmp / "build_config.yaml")
        write_effective_config(cfg, tmp, stage="prior-append", inputs=inputs)
    return out


def _require_same_encoder(prior, report: dict, feats: Path) -> None:
    """Features can join a prior only when encoded as its own images were."""
    if report["encoder"] != prior.encoder:
        raise InputError(f"{feats}: encoded otherwise than the prior", [Problem(
            str(feats / "report.json"), f"encoder {report['encoder']}, the prior's {prior.encoder}",
            fix="run `siteloc prior features` with the config the prior was built with")])


def _feature_hashes(features: Path) -> dict[str, str]:
    """{image_id: sha256} of a `prior features` output ({} for one written before hashes were kept)."""
    from pipeline.io import tables
    from pipeline.io.image_reuse import HASHES_FILE

    if not (Path(features) / HASHES_FILE).is_file():
        return {}
    t = tables.read_table(Path(features) / HASHES_FILE, "image_hashes").to_pydict()
    return dict(zip(t["image_id"], t["sha256"], strict=True))


def _prior_hashes(prior_dir: Path, *, required: bool = True) -> dict[str, str]:
    from pipeline.io.image_reuse import HASHES_FILE

    sha = _feature_hashes(prior_dir)
    if required and not sha:
        raise InputError(f"{prior_dir}: the prior does not record its images' sha256", [Problem(
            str(Path(prior_dir) / HASHES_FILE), "missing (a prior built before image hashes were kept)",
            fix="rebuild it: `siteloc prior features DATA --out F` then `siteloc prior build F --out PRIOR`")])
    return sha


def _write_prior_hashes(tmp: Path, prior, sha: dict[str, str]) -> None:
    """The prior's own image_sha256.parquet, when every row's hash is known (what `prior update` compares)."""
    from pipeline.io.image_reuse import write_hashes

    ids = prior.rows["image_id"]
    if ids and all(i in sha for i in ids):
        write_hashes(tmp, sha, ids)


def run_prior_update(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                     force: bool = False) -> Path:
    """A copy of `inputs['prior']` brought to the database images of `inputs['features']` (same encoder).

    An image is the same when its id and sha256 are; the prior's rows of images gone or changed are
    dropped, the new ones compressed with the fitted compressions and added. Nothing else is refitted."""
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.prior.features import read_layers, select
    from pipeline.prior.model import AreaPrior

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    src, feats = Path(inputs["prior"]), Path(inputs["features"])
    prior = AreaPrior.load(src)
    old_sha = _prior_hashes(src)
    meta, raw, rep = read_layers(feats)
    _require_same_encoder(prior, rep, feats)
    new_sha = _feature_hashes(feats)
    if not new_sha:
        raise InputError(f"{feats}: no image hashes", [Problem(
            str(feats), "written before image hashes were kept", fix="run `siteloc prior features` again")])
    doc = json.loads((src / "report.json").read_text()) if (src / "report.json").is_file() else {}
    database = doc.get("database", "train")
    in_db = np.ones(len(meta["image_id"]), bool) if database == "all" else np.asarray(meta["split"]) == "train"
    now = {(i, new_sha[i]) for i, d in zip(meta["image_id"], in_db, strict=True) if d}
    keep = np.array([(i, old_sha[i]) in now for i in prior.rows["image_id"]], dtype=bool)
    had = {(i, old_sha[i]) for i in prior.rows["image_id"]}
    add = [n for n, i in enumerate(meta["image_id"]) if in_db[n] and (i, new_sha[i]) not in had]
    if keep.sum() + len(add) < 2:
        raise InputError(f"{feats}: too few database images", [Problem(
            str(feats), f"{int(keep.sum()) + len(add)} images would be left",
            fix="point at the updated site's features")])
    meta, raw = select(meta, raw, np.asarray(add, dtype=np.int64))
    change = prior.replace(keep, meta, raw)
    updated = doc.get("updated", []) + [{"features": str(feats), **change}]
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        prior.save(tmp)
        _write_prior_hashes(tmp, prior, {**old_sha, **new_sha})
        extra = {k: doc[k] for k in ("database", "compression", "appended") if k in doc}
        write_text_atomic(tmp / "report.json", _report(prior, {**extra, "updated": updated}))
        for name in ("build_config.yaml", "config.yaml"):  # the build's settings, through any chain of updates
            if (src / name).is_file():
                shutil.copyfile(src / name, tmp / "build_config.yaml")
                break
        write_effective_config(cfg, tmp, stage="prior-update", inputs=inputs)
    return out


def query_images(cfg: SitelocConfig, prior_dir: Path, images: list[Path], top: int = 3) -> list[dict]:
    """Each image's `top` most probable (room, area) classes."""
    from pipeline.detection.inference import load_image
    from pipeline.prior.model import AreaPrior
    from pipeline.prior.seeding import encoder_for

    prior = AreaPrior.load(prior_dir)
    enc = encoder_for(prior, cfg.prior.weights)
    missing = [im for im in images if not Path(im).is_file()]
    if missing:
        raise InputError(f"{len(missing)} images not found", [Problem(str(m), "no such file") for m in missing])
    out = []
    for im in images:
        probs = prior.probabilities(enc([load_image(Path(im))]))[0]
        order = np.argsort(-probs, kind="stable")[:top]
        out.append({"image": str(im), "areas": [{"room": prior.classes[k][0], "area": prior.classes[k][1],
                                                 "probability": round(float(probs[k]), 4)} for k in order]})
    return out
