"""`siteloc demo`: the main job on the shipped data."""

from __future__ import annotations

from typing import Annotated

import typer

from stages.common import VerboseOpt, cli_errors, load, print_tables

HELP = """Run the main job end to end: the DVC pipeline of dvc.yaml, stage by stage, with a summary.

This renders the reference site of the config (`synth.site`: office for the demo preset, a micro
site for ci; see `siteloc synth`) and ingests it, fine-tunes the detector on it and scores it on the
held-out stops (`siteloc train-detector`, `evaluate-detector`), extracts IPA / RPA descriptors
(`siteloc extract`), builds and measures the retrieval database (`build-index`, `evaluate-retrieval`),
encodes the run frames and trains the image-sequence LSTM on the mapping runs (`siteloc frame-features`,
`train-sequence`), builds seed 001's area prior (`siteloc prior features`, `prior build`), exports the
deployable bundle with all of them (`siteloc export`), localizes the site's query runs from the bundle
alone, camera frames included, beside the paper's baselines (`siteloc evaluate`, `prior evaluate`), and
ingests every real CARMEN laser log of ../shared/data/carmen (`siteloc ingest-log`) and the example
capture directory of docs/example-site. docs/results.md says how long it takes.

Every stage runs through DVC (`dvc repro STAGE`), so a stage whose inputs, code and parameters are
unchanged is reused, an interrupted demo resumes, and dvc.lock matches the outputs afterwards: `make
repro` then finds nothing to do. The config is configs/params.yaml; --config / --set first rewrite it
(fully defaulted), and DVC reruns exactly the stages whose parameters changed. --force reruns every stage.
Outputs: data/reference/{site,ingested,descriptors,index,frames,multilayer}/, models/{detector,
detector-eval,sequence,prior}/, bundles/<site>-<version>/ (+ .tar.gz), reports/{retrieval,<site>,
<site>-prior}/, data/carmen/<log>/, data/example/ingested/, data/demo-summary.json.
"""


def demo(
    config: Annotated[str | None, typer.Option(
        "--config", "-c", help="Preset name in configs/ (demo, ci, paper) or a YAML path: written, fully "
        "defaulted, to configs/params.yaml before the run \\[default: configs/params.yaml as it is].",
        rich_help_panel="Configuration")] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", "-s", help="Override one config key in configs/params.yaml first, e.g. --set "
        "detector.iterations=3000 (repeatable).", rich_help_panel="Configuration")] = None,
    force: Annotated[bool, typer.Option("--force", "-f", help="Rerun every stage (dvc repro --force).")] = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from rich.table import Table

        from pipeline.demo import PARAMS, project_root, run_demo, write_params

        if config is not None or set_:
            root = project_root()
            cfg = load(config or str(root / PARAMS), set_)
            if write_params(cfg, root):
                typer.echo(f"{PARAMS}: now preset '{cfg.preset}'" + (f" with {' '.join(set_)}" if set_ else ""))

        def skipped(stage: str, missing: list[str]) -> None:
            typer.secho(f"warning: {stage} skipped, its input is missing: {', '.join(missing)}", fg="yellow",
                        err=True)

        steps = run_demo(force=force, on_skip=skipped)

        table = Table(title="siteloc demo", caption="outputs under data/, models/, bundles/, reports/ (summary: "
                                                   "data/demo-summary.json; dvc.lock records them)")
        for col in ("stage", "input", "result", "status", "time"):
            table.add_column(col)
        for s in steps:
            table.add_row(s.name.removesuffix("-corrected"), *_describe(s.report), "reused" if s.reused else "done",
                          _duration(s.seconds))
        print_tables(table)
        typer.echo(f"total: {_duration(sum(s.seconds for s in steps))}")
        typer.echo("endpoints on walls: share of scan endpoints on occupied map cells, exact / within one cell")


def _map_size(m: dict) -> str:
    return f"map {m['width_cells'] * m['resolution']:.1f} x {m['height_cells'] * m['resolution']:.1f} m"


def _describe(r: dict) -> tuple[str, str]:
    """(input, result) of one step's report, for the summary table."""
    import numpy as np

    if "table_one" in r:  # prior evaluate
        best = max(r["table_one"], key=lambda row: row.get("area_accuracy") or 0)
        return (f"{len(r['table_one'])} compressions", f"area accuracy {best['area_accuracy']:.3f} "
                f"({best['compression']}), room {best['room_accuracy']:.3f}")
    if r.get("updated"):  # prior update
        u = r["updated"][-1]
        return (f"{u['kept'] + u['added']} images", f"kept {u['kept']}, dropped {u['dropped']}, added "
                f"{u['added']}; {len(u['refitted_classes']) + len(u['new_classes'])} classes refitted")
    if "compression" in r and "classes" in r:  # prior build
        return f"{r['images']} images", f"{r['classes']} (room, area) classes, {r['compression'].get('method', '')}"
    if "encoder" in r and "dims" in r:  # prior features
        return f"{r['images']} images", "layers " + ", ".join(f"{k} {v}-d" for k, v in r["dims"].items())
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
    if "recommendation" in r:  # check
        rec = r["recommendation"]
        return (f"{(r.get('images') or {}).get('images', 0)} new images, {r['map']['scans']} scans",
                f"re-capture {', '.join(rec['recapture']) or 'none'}; "
                f"map update {', '.join(rec['update_map']) or 'none'}")
    if "map" in r:
        return f"{r['images']} images", _map_size(r["map"])
    return "", ""


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 60 else f"{int(seconds // 60)} min {seconds % 60:02.0f} s"
