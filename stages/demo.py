"""`siteloc demo`: the main job on the shipped data."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, SetOpt, VerboseOpt, cli_errors, load

HELP = """Run the main job end to end on data that ships with the project.

This renders the reference site of the config (`synth.site`: office for the demo preset, a micro
site for ci; see `siteloc synth`; about 5.5 minutes on 2 cores for the office site) and ingests it,
fine-tunes the detector on it and scores it on the held-out stops (`siteloc train-detector`,
`evaluate-detector`; about 7.5 minutes), extracts IPA / RPA descriptors (`siteloc extract`; about 2
minutes), builds and measures the retrieval database (`build-index`, `evaluate-retrieval`), encodes the
run frames and trains the image-sequence LSTM on the mapping runs (`siteloc frame-features`,
`train-sequence`; about 1 minute), exports the deployable bundle with it (`siteloc export
--sequence`), localizes the site's query runs from the bundle alone, camera frames included, beside
the paper's baselines, and writes the report (`siteloc evaluate`; about 2-2.5 minutes). 15-20 minutes in
all on 2 Intel cores (2026-12-02; the machine's speed varied that much; 45 minutes on an AMD EPYC). Then it
ingests every real CARMEN laser log in ../shared/data/carmen (`siteloc ingest-log`) and the example
capture directory of docs/example-site, and prints a summary.

Finished steps are reused, so an interrupted demo resumes; --force redoes everything.
Outputs: DATA/reference/{site,ingested,descriptors,index,retrieval-eval,frames}/, MODELS/detector/,
MODELS/detector-eval/, MODELS/sequence/, BUNDLES/<site>-<version>/ (+ .tar.gz), REPORTS/<site>/report.md,
DATA/carmen/<log>/, DATA/example/ingested/, DATA/demo-summary.json.
"""


def demo(
    data: Annotated[Path, typer.Option("--data", "-d", help="Where the outputs go.")] = Path("data"),
    carmen_dir: Annotated[
        Path | None,
        typer.Option(
            "--carmen-dir", help="Folder of CARMEN logs \\[default: ../shared/data/carmen or $SITELOC_CARMEN_DIR]."
        ),
    ] = None,
    models: Annotated[Path, typer.Option("--models", "-m", help="Where trained models go.")] = Path("models"),
    bundles: Annotated[Path, typer.Option("--bundles", help="Where the deployable bundle goes.")] = Path("bundles"),
    reports: Annotated[Path, typer.Option("--reports", help="Where the localization report goes.")] = Path("reports"),
    config: ConfigOpt = "demo",
    set_: SetOpt = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from rich.console import Console
        from rich.table import Table

        from pipeline.demo import DEFAULT_CARMEN_DIR, run_demo

        cfg = load(config, set_)
        carmen = carmen_dir or DEFAULT_CARMEN_DIR
        if not carmen.is_dir():
            typer.secho(
                f"warning: no CARMEN logs at {carmen}; only the example site is ingested", fg="yellow", err=True
            )
        steps = run_demo(cfg, inputs={"carmen_dir": carmen},
                         outputs={"data": data, "models": models, "bundles": bundles, "reports": reports}, force=force)

        table = Table(title="siteloc demo", caption=f"outputs under {data}/ and {models}/ (summary: "
                                                   "data/demo-summary.json)")
        for col in ("step", "input", "result", "status", "time"):
            table.add_column(col)
        for s in steps:
            table.add_row(s.name.removesuffix("-corrected"), *_describe(s.report), "reused" if s.reused else "done",
                          _duration(s.seconds))
        Console().print(table)
        typer.echo(f"total: {_duration(sum(s.seconds for s in steps))}")
        typer.echo("endpoints on walls: share of scan endpoints on occupied map cells, exact / within one cell")


def _map_size(m: dict) -> str:
    return f"map {m['width_cells'] * m['resolution']:.1f} x {m['height_cells'] * m['resolution']:.1f} m"


def _describe(r: dict) -> tuple[str, str]:
    """(input, result) of one step's report, for the summary table."""
    import numpy as np

    if "objects_per_class" in r:
        return f"{r['capture_images']} views, {len(r['runs'])} runs", _map_size(r["map"])
    if "scans" in r:
        w, h = r["map_size_m"]
        return (f"{r['scans']} x {r['beams']} scans", f"map {w:.1f} x {h:.1f} m, endpoints on walls "
                f"{r['endpoint_on_occupied_share_tol0']:.2f} / {r['endpoint_on_occupied_share_tol1']:.2f}")
    if "train_windows" in r:
        six = r["recall"].get("length_6") or next(iter(r["recall"].values()), {})
        return (f"{r['train_windows']} windows, {r['places']} places",
                f"6 frames R@1 {six.get('recall_at_1_2m', float('nan')):.3f} (2 m), single frame "
                f"{r['recall'].get('single_frame', {}).get('recall_at_1_2m', float('nan')):.3f}")
    if "frames" in r and "dim" in r:
        return f"{r['frames']} frames, {len(r['runs'])} runs", f"{r['dim']}-d logits"
    if "loss_history" in r:
        return (f"{r['train_images']} train images",
                f"loss {r['loss_first']:.3f} -> {r['loss_last_50_mean']:.3f}, {r['iterations_per_s']} it/s")
    if "ipa_dim" in r and "regions" in r and "whitening" not in r:
        return f"{r['images']} images", f"IPA {r['ipa_dim']}-d, {r['regions']} RPA regions"
    if "whitening" in r:
        return f"{r['images']} database images", f"whitening {r['whitening']}: IPA {r['ipa_dim']}-d"
    if "variants" in r:
        best = r["variants"].get("ipa+rpa / pca") or next(iter(r["variants"].values()))
        m = best["2m_30deg"]
        return (f"{r['query_images']} queries", f"IPA+RPA/PCA mAP@4 {m['map_at_4']:.3f}, R@1 {m['recall_at_1']:.3f} "
                f"(2 m, 30 deg)")
    if "parity" in r:
        return f"{r['files']} files, {r['bytes'] / 2**20:.1f} MiB", (
            f"ONNX vs torch: IPA {r['parity']['ipa_abs']:.1e}, RPA {r['parity']['rpa_abs']:.1e}")
    if "table1" in r:
        s, w = r["summary"]["proposed"], r["summary"]["amcl"]
        return (f"{len(r['runs'])} query runs x {r['trials']}", f"global p90 error {s['error_p90_global_m']:.2f} m "
                f"(no camera {w['error_p90_global_m']:.2f} m), kidnappings {s['recovered']}/{s['kidnaps']} recovered, "
                f"{s['recovered_within_15']} within 15 steps")
    if "summary" in r:
        s = list(r["summary"].values())
        if not any("converged" in v for v in s):
            return f"{len(s)} query runs", "no ground truth"
        med = [v["error_median_m"] for v in s if v.get("error_median_m") is not None]
        return (f"{len(s)} query runs", f"converged {sum(v['converged'] for v in s)}/{sum(v['trials'] for v in s)}"
                + (f", median error {np.median(med):.2f} m" if med else ""))
    if "map_50" in r:
        fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
        return (f"{r['images']} held-out images", f"mAP@0.5 {fmt(r['map_50'])}, mAP@[.5:.95] {fmt(r['map_50_95'])}")
    return f"{r['images']} images", _map_size(r["map"])


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 60 else f"{int(seconds // 60)} min {seconds % 60:02.0f} s"
