"""The `prior evaluate` report: report.md with seed 001's Table I, the layer-weight comparison and the
seeding comparison, and the PNGs a reader would rather look at than read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PAPER_TABLE_ONE = {"ipca": (27100, 0.026), "kpca": (218000, 0.031), "srp": (3700, 0.025), "grp": (53400, 0.026),
                   "none": (480000, None)}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _weights_label(ws) -> str:
    return "/".join(f"{w:.2g}" for w in ws)


def write_figures(out: Path, metrics: dict) -> list[str]:
    from pipeline.evaluation.plots import save_figure

    plt = _plt()
    names = []
    rows = metrics["table_one"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    comps = [r["compression"] for r in rows]
    for ax, key, title in zip(axes, ("memory_kb_mean_layer", "query_ms", "area_accuracy"),
                              ("memory per layer (KB)", "query time, 3 layers (ms)", "top-1 (room, area) accuracy"),
                              strict=True):
        ax.bar(comps, [r[key] for r in rows], color="#457b9d")
        ax.set_title(title, fontsize=10)
        if key != "area_accuracy":
            ax.set_yscale("log")
    fig.suptitle("Table I: compressions to 128-d (database: train stops; queries: held-out stops)", fontsize=10)
    save_figure(fig, out / "table_one.png")
    names.append("table_one.png")

    panels = [("same site", metrics["weights"])] + ([("after synth --change", metrics["changed"]["weights"])]
                                                    if "changed" in metrics else [])
    fig, axes = plt.subplots(len(panels), 1, figsize=(11, 3.4 * len(panels)), squeeze=False)
    layers = "/".join(metrics["layers"])
    for ax, (title, grid) in zip(axes[:, 0], panels, strict=True):
        measures = list(grid)
        n_w = len(grid[measures[0]])
        width = 0.8 / len(measures)
        for i, m in enumerate(measures):
            ax.bar(np.arange(n_w) + (i - (len(measures) - 1) / 2) * width, [g["area"] for g in grid[m]], width,
                   label=m)
        ax.set_xticks(np.arange(n_w), [_weights_label(g["weights"]) for g in grid[measures[0]]], fontsize=8)
        ax.set_ylabel("top-1 area accuracy")
        ax.set_title(f"{title}: layer weights ({layers}) x measure", fontsize=10)
        ax.legend(fontsize=8, ncol=4)
    save_figure(fig, out / "layer_weights.png")
    names.append("layer_weights.png")

    if "seeding" in metrics:
        fig, ax = plt.subplots(figsize=(6, 3.6))
        for s, reps in metrics["seeding"]["replays"].items():
            steps = np.sort([r["converged_step"] for r in reps if r["converged_step"] is not None])
            if len(steps):
                ax.step(steps, np.arange(1, len(steps) + 1) / len(reps), where="post", label=s)
        ax.set_xlabel("steps to converge")
        ax.set_ylabel("share of replays converged")
        ax.set_title("global localization by seeding", fontsize=10)
        ax.legend(fontsize=8)
        save_figure(fig, out / "seeding.png")
        names.append("seeding.png")
    return names


def write_examples(path: Path, prior, meta_q: dict, probs: np.ndarray, data: Path, n: int = 8, top: int = 5) -> bool:
    """Query images beside their `top` most probable classes (green: the query's own), like the paper's
    Figures 2-5; False when the images are not where the features were computed from."""
    from pipeline.evaluation.plots import save_figure
    from pipeline.io.images import image_rgb

    picks = np.linspace(0, len(meta_q["image_id"]) - 1, min(n, len(meta_q["image_id"]))).astype(int)
    if not all((Path(data) / meta_q["image_id"][i]).is_file() for i in picks):
        return False
    plt = _plt()
    cols = 2
    rows = (len(picks) + cols - 1) // cols
    fig, axes = plt.subplots(rows, 2 * cols, figsize=(13, 2.3 * rows), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 1.3] * cols})
    for ax in axes.ravel():
        ax.axis("off")
    for j, i in enumerate(picks):
        a_img, a_bar = axes[j // cols, 2 * (j % cols)], axes[j // cols, 2 * (j % cols) + 1]
        a_img.imshow(image_rgb(Path(data) / meta_q["image_id"][i]))
        truth = (meta_q["room"][i], meta_q["area"][i])
        a_img.set_title(f"{truth[0]}/{truth[1]}", fontsize=8)
        order = np.argsort(-probs[i], kind="stable")[:top][::-1]
        a_bar.axis("on")
        a_bar.barh(range(len(order)), probs[i][order],
                   color=["#2a9d8f" if prior.classes[k] == truth else "#e76f51" for k in order])
        a_bar.set_yticks(range(len(order)), ["/".join(prior.classes[k]) for k in order], fontsize=7)
        a_bar.set_xlim(0, 1)
        a_bar.tick_params(axis="x", labelsize=7)
    fig.subplots_adjust(wspace=0.7)
    fig.suptitle("held-out queries and their most probable (room, area) classes (green: right)", fontsize=10)
    save_figure(fig, path)
    return True


def _grid_table(grid: dict) -> list[str]:
    measures = list(grid)
    lines = ["| layer weights | " + " | ".join(f"{m} area / room" for m in measures) + " |",
             "|---|" + "---|" * len(measures)]
    for i, g in enumerate(grid[measures[0]]):
        cells = [f"{grid[m][i]['area']:.3f} / {grid[m][i]['room']:.3f}" for m in measures]
        lines.append(f"| {_weights_label(g['weights'])} | " + " | ".join(cells) + " |")
    return lines


def write_report(path: Path, metrics: dict, figures: list[str]) -> Path:
    from pipeline.io.atomic import write_text_atomic

    s, e, cfg = metrics["site"], metrics["encoder"], metrics["settings"]
    k = cfg["k"]
    lines = [
        "# Area prior from pretrained multi-layer features (seed 001)", "",
        f"Encoder: {e['backbone']} ({e['weights']}), layers {', '.join(e['layers'])}, input {e['input_size']} px. "
        f"Database: {s['database_images']} images of {s['classes']} (room, area) classes in {s['rooms']} rooms; "
        f"queries: {s['query_images']} images of held-out stops. Chance: {1 / s['classes']:.3f} (area).", "",
        f"## Table I (compression to {cfg['n_components']}-d; measure {cfg['measure']}, layer weights "
        f"{_weights_label(cfg['layer_weights'])})", "",
        f"| compression | dims | memory per layer (KB) | query (ms) | hit@{k} | area acc | room acc | "
        "changed site: area / room acc | paper memory (KB) | paper time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for r in metrics["table_one"]:
        pm, pt = PAPER_TABLE_ONE[r["compression"]]
        ch = (f"{r['changed_area_accuracy']:.3f} / {r['changed_room_accuracy']:.3f}"
              if "changed_area_accuracy" in r else "-")
        lines.append(f"| {r['compression']} | {'/'.join(str(v) for v in r['dims'].values())} | "
                     f"{r['memory_kb_mean_layer']:.0f} | {r['query_ms']:.2f} | {r[f'hit_at_{k}']:.3f} | "
                     f"{r['area_accuracy']:.3f} | {r['room_accuracy']:.3f} | {ch} | {pm} | "
                     f"{pt if pt is not None else 'NA'} |")
    lines += ["", f"Memory: the compression's arrays plus the database vectors, mean over the layers (the paper's "
              f"includes the transformation too). hit@{k}: a neighbour of the right (room, area) among the {k} "
              "(the paper's 'returns the correct index'), mean over the layers.", "", "![](table_one.png)", "",
              f"## Layer weights x measure ({cfg['compression']})", ""]
    lines += _grid_table(metrics["weights"])
    if "changed" in metrics:
        lines += ["", f"### After `synth --change` ({metrics['changed']['query_images']} queries: every image of "
                  "the changed site against the original database)", ""]
        lines += _grid_table(metrics["changed"]["weights"])
    lines += ["", "![](layer_weights.png)", ""]
    if "examples.png" in figures:
        lines += ["![](examples.png)", ""]
    if "append" in metrics:
        a = metrics["append"]
        lines += ["## Appending new areas", "",
                  f"A prior built without {a['rooms_appended']} of the rooms ({a['images_first']} images, "
                  f"{a['build_first_s']:.2f} s), then their {a['images_appended']} images appended "
                  f"({a['append_s']:.2f} s; building on everything at once: {a['build_all_s']:.2f} s):", "",
                  "| queries | area accuracy before | after appending | built at once |", "|---|---|---|---|",
                  f"| of the appended rooms ({a['late_queries']}) | {a['late_area_accuracy_before']} | "
                  f"{a['late_area_accuracy_after']} | {a['late_area_accuracy_built_at_once']} |",
                  f"| of the other rooms ({a['other_queries']}) | {a['other_area_accuracy_before']} | "
                  f"{a['other_area_accuracy_after']} | - |", "",
                  f"{a['other_unchanged_share']:.0%} of the other rooms' queries keep their answer (the others now "
                  "have an appended image among their neighbours).", ""]
    if "seeding" in metrics:
        sd = metrics["seeding"]
        lines += ["## Seeding the filter: area prior vs Top-4 candidates vs uniform", "",
                  f"{len(sd['starts'])} starts (each query run's first frame and every kidnapping: a robot woken "
                  f"up there, until the next kidnapping), {len(sd['replays']['uniform'])} replays per seeding, no "
                  f"injection afterwards. The prior spreads particles over its {sd['max_areas']} most probable "
                  f"areas; the true area is among them at {sd['prior_hit_rate']:.0%} of the starts and first at "
                  f"{sd['prior_top1_rate']:.0%} (the Top-1 retrieved pose lies in it at "
                  f"{sd['retrieval_top1_rate']:.0%}).", "",
                  "| seeding | converged | within 15 steps | median steps | mean steps | mean particles |",
                  "|---|---|---|---|---|---|"]
        for name, m in sd["summary"].items():
            lines.append(f"| {name} | {m['converged']}/{m['replays']} | {m['within_15']} | "
                         f"{m['converged_step_median']} | {m['converged_step_mean']} | {m['particles_mean']} |")
        lines += ["", "![](seeding.png)", ""]
    return write_text_atomic(path, "\n".join(lines) + "\n")
