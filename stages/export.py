"""`siteloc export`: the deployable bundle a robot loads."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Write the deployable bundle: bundles/<site>-<version>/ and its .tar.gz.

MODEL is the output of `siteloc train-detector`, INDEX of `siteloc build-index`, DATA the ingested
site (map, laser geometry, camera). The bundle holds the map (ROS map_server YAML + PGM), the whitened
database descriptors and poses (Parquet) with the whitening arrays (npz), the detector as ONNX (image ->
stride-16 map, proposals, detections; checked against torch on export.parity_images of the site's
images, tolerances in models/describer.json), filter.yaml (filter, retrieval and laser settings) and
manifest.json, written last: schema and bundle versions, site, creation time, code version, effective
config, the dvc.lock hash and every file's sha256 and size. The runtime (`Localizer.from_bundle`)
refuses a bundle whose files do not match it.

With --sequence (the output of `siteloc train-sequence`), the bundle also carries the frame encoder
(EfficientNet-Lite0 logits) and the sequence LSTM as ONNX, each checked against torch, and the sequence
database: the Localizer can then re-localize from its last frames after a kidnapping
(filter.relocalise_with: sequence or both).

With --prior (the output of `siteloc prior build`), the bundle also carries seed 001's multi-layer
encoder as ONNX (checked against torch) and the area prior: with filter.seed_with=area_prior the
Localizer starts the filter over the free space of the first image's most probable (room, area) classes
instead of around its Top-4 retrieved poses.

With --parent (the previous bundle of the site), the bundle is its next version: by default the
parent's version with its last number raised by one; the manifest names the parent (name, version,
manifest sha256) and changelog.json / changelog.md say what changed against it: stops kept, added,
removed and re-captured per room/area, map cells changed per area, and which inputs (detector,
database, ingest, sequence model, area prior) were retrained or kept. `siteloc diff` prints the same
comparison for any two bundles.

Example: siteloc export models/office/detector data/office/index data/office/ingested --out bundles
"""


def export(
    model: Annotated[Path, typer.Argument(help="A trained detector.", show_default=False)],
    index: Annotated[Path, typer.Argument(help="The retrieval database (build-index).", show_default=False)],
    data: Annotated[Path, typer.Argument(help="The ingested site.", show_default=False)],
    sequence: Annotated[Path | None, typer.Option(
        "--sequence", help="A trained sequence LSTM (train-sequence): adds image-sequence re-localization.",
        show_default=False)] = None,
    prior: Annotated[Path | None, typer.Option(
        "--prior", help="An area prior (prior build): adds seeding the filter over (room, area) classes.",
        show_default=False)] = None,
    parent: Annotated[Path | None, typer.Option(
        "--parent", help="The previous bundle of this site: this one is its next version, with a changelog.",
        show_default=False)] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Directory the bundle goes into.")] = Path("bundles"),
    version: Annotated[str | None,
                       typer.Option("--version", help="Bundle version \\[default: export.version].")] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("export.parity_images=8") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.bundle.export import run_export

        if parent and not version:
            from pipeline.bundle.diff import next_version
            from pipeline.runtime.bundle import read_manifest

            version = next_version(str(read_manifest(parent).get("bundle_version")))
        cfg = load(config, (set_ or []) + ([f"export.version={json.dumps(version)}"] if version else []))  # a string
        inputs = {**({"parent": parent} if parent else {}),
                  "model": model, "index": index, "data": data, **({"sequence": sequence} if sequence else {}),
                  **({"prior": prior} if prior else {})}
        bundle = run_export(cfg, inputs=inputs, outputs={"out": out}, force=force,
                            on_note=lambda note: typer.echo(f"note: {note}", err=True))
        manifest = json.loads((bundle / "manifest.json").read_text())
        parity = json.loads((bundle / "models" / "describer.json").read_text())["parity"]["max_differences"]
        size = sum(e["size"] for e in manifest["files"].values())
        typer.echo(f"{len(manifest['files'])} files, {size / 2**20:.1f} MiB; ONNX vs torch: map "
                   f"{parity['feature_map_abs']:.1e}, IPA {parity['ipa_abs']:.1e}, RPA {parity['rpa_abs']:.1e}, "
                   f"detection scores {parity['score_abs']:.1e}")
        if sequence:
            seq = json.loads((bundle / "models" / "sequence.json").read_text())
            typer.echo(f"sequence re-localization: {seq['length']} frames; ONNX vs torch: frame logits "
                       f"{seq['frames']['parity']['max_abs']:.1e}, LSTM "
                       f"{max(seq['lstm_parity']['max_abs_by_length'].values()):.1e}")
        if prior:
            pm = json.loads((bundle / "models" / "prior.json").read_text())
            typer.echo(f"area prior: {pm['encoder']['backbone']} {', '.join(pm['encoder']['layers'])}; ONNX vs torch "
                       f"{max(pm['parity']['max_abs_by_layer'].values()):.1e} (filter.seed_with=area_prior uses it)")
        if parent:
            log = manifest["changelog"]
            typer.echo(f"against {manifest['parent']['name']}: areas changed {log['areas_changed'] or 'none'}; stops "
                       f"{log['stops']['stops_added']} added, {log['stops']['stops_removed']} removed, "
                       f"{log['stops']['stops_kept']} kept; map cells changed {log['map_cells_changed']}; inputs "
                       + ", ".join(f"{k} {v}" for k, v in log["components"].items()))
            echo_path("changelog", bundle / "changelog.md")
        echo_path("bundle", bundle)
        if cfg.export.archive:
            echo_path("archive", bundle.with_name(bundle.name + ".tar.gz"))
