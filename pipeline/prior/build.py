"""Stages `prior build`, `prior append` and `prior query`: seed 001's model database as a product.

- `build`: fit each layer's compression on the database images (`train` split, or every image), index
  them, fit the per-(room, area) Gaussians; writes the prior directory (`AreaPrior.save`), report.json
  and config.yaml.
- `append`: a new area's (or a changed area's) images into a copy of a prior, with its fitted
  compressions; nothing else is refitted (the paper's scalability argument).
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
    from pipeline.errors import OutputExistsError
    from pipeline.io.atomic import atomic_dir, write_text_atomic
    from pipeline.prior.evaluate import build_prior
    from pipeline.prior.features import read_layers, select

    out = Path(outputs["out"])
    if out.exists() and not force:
        raise OutputExistsError(out)
    meta, raw, rep = read_layers(Path(inputs["features"]))
    keep = np.ones(len(meta["image_id"]), bool) if all_images else np.asarray(meta["split"]) == "train"
    if keep.sum() < 2:
        raise InputError(f"{inputs['features']}: too few database images", [Problem(
            str(inputs["features"]), f"{int(keep.sum())} images in the database", fix="use --all, or more captures")])
    meta, raw = select(meta, raw, keep)
    prior = build_prior(cfg, meta, raw, rep["encoder"])
    comps = {n: {"kind": prior.compressors[n].KIND, "dims": int(prior.compressors[n].n_components_),
                 "cap": prior.compressors[n].cap_reason_} for n in prior.layers}
    with atomic_dir(out, force=force) as tmp:
        prior.save(tmp)
        write_text_atomic(tmp / "report.json", _report(prior, {"compression": comps, "appended": []}))
        write_effective_config(cfg, tmp, stage="prior-build", inputs=inputs)
    return out


def run_prior_append(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                     rooms: list[str] | None = None, force: bool = False) -> Path:
    """A copy of `inputs['prior']` with the images of `inputs['features']` (those of `rooms` if given) added."""
    from pipeline.errors import OutputExistsError
    from pipeline.io.atomic import atomic_dir, write_text_atomic
    from pipeline.prior.features import read_layers, select
    from pipeline.prior.model import AreaPrior

    out = Path(outputs["out"])
    if out.exists() and not force:
        raise OutputExistsError(out)
    src = Path(inputs["prior"])
    prior = AreaPrior.load(src)
    meta, raw, rep = read_layers(Path(inputs["features"]))
    feats = Path(inputs["features"])
    if rep["encoder"] != prior.encoder:
        raise InputError(f"{feats}: encoded otherwise than the prior", [Problem(
            str(feats / "report.json"), f"encoder {rep['encoder']}, the prior's {prior.encoder}",
            fix="run `siteloc prior features` with the config the prior was built with")])
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
    with atomic_dir(out, force=force) as tmp:
        prior.save(tmp)
        extra = {"compression": doc.get("compression"), "appended": appended}
        write_text_atomic(tmp / "report.json", _report(prior, extra))
        if (src / "config.yaml").is_file():
            shutil.copyfile(src / "config.yaml", tmp / "build_config.yaml")
        write_effective_config(cfg, tmp, stage="prior-append", inputs=inputs)
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
