"""Time the offline stages' CPU inference: eager torch against onnxruntime, in one or several threads.

    .venv/bin/python benchmarks/offline_inference.py --model models/detector --data data/reference/ingested
                                                     [--images 48] [--repeat 2]

On the first `--images` images of the ingested site (stops first, then query frames, as `extract` orders
them), times per image:

- the detector's IPA + RPA description (`extract`): torch in batches of `retrieval.batch` (4), the exported
  ONNX graph in one session using every core, and one single-threaded session per core
  (`pipeline.onnx_threads`, what `extract` does on a CPU);
- EfficientNet-Lite0's frame logits (`frame-features`): torch in batches of 16, and the same two onnxruntime
  layouts.

Decoding the JPEGs is included in every figure (each stage pays it). Each variant runs `--repeat` times after
a warm-up, interleaved, and the best is kept. Prints the machine, a table, and each variant's speed as a
ratio to torch in the same run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, required=True, help="a train-detector output")
    ap.add_argument("--data", type=Path, required=True, help="an ingested site")
    ap.add_argument("--images", type=int, default=48)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()

    import torch

    from pipeline.detection.inference import load_detector, load_image
    from pipeline.machine import machine_info
    from pipeline.onnx_threads import SizedGraphPool, thread_layout
    from pipeline.retrieval.extract import describe, onnx_describer, site_images
    from pipeline.sequence.frames import FrameEncoder
    from pipeline.sequence.onnx_export import export_frame_encoder

    for line in machine_info():
        print(line)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}")
    paths = [args.data / r.image_id for r in site_images(args.data, include_runs=True)[: args.images]]
    det = load_detector(args.model, device="cpu")
    enc = FrameEncoder("imagenet", 224)
    cores = thread_layout()[0] * thread_layout()[1]
    with tempfile.TemporaryDirectory() as tmp:
        layouts = {"onnx, 1 session x all cores": 1, f"onnx, {cores} sessions x 1 thread": cores}

        def frames_build(hw, images, path):
            return export_frame_encoder(enc, hw, path, [torch.from_numpy(im) for im in images])["parity"]

        def frames_run(session, image, _):
            return session.run(None, {"image": image})[0]

        pools = {}
        for label, n in layouts.items():
            layout = (1, cores) if n == 1 else (cores, 1)
            pools[("extract", label)] = onnx_describer(det, Path(tmp), rpa_proposals=100, rpa_min_score=0.3, samples=1,
                                                       layout=layout)
            pools[("frames", label)] = SizedGraphPool("frames", Path(tmp), frames_build, frames_run, samples=1,
                                                      layout=layout)
        variants = {
            ("extract", "torch, batches of 4"): lambda: [describe(det, [load_image(p) for p in paths[i:i + 4]], 100,
                                                                  0.3) for i in range(0, len(paths), 4)],
            ("frames", "torch, batches of 16"): lambda: [enc([load_image(p) for p in paths[i:i + 16]])
                                                         for i in range(0, len(paths), 16)],
            **{key: (lambda pool=pool: pool(paths)) for key, pool in pools.items()},
        }
        times = {key: float("inf") for key in variants}
        for fn in variants.values():  # one warm-up each, then interleaved repeats
            fn()
        for _ in range(args.repeat):
            for key, fn in variants.items():
                t0 = time.perf_counter()
                fn()
                times[key] = min(times[key], time.perf_counter() - t0)
        for pool in pools.values():
            pool.close()
    print(f"\n{len(paths)} images of {args.data}, best of {args.repeat}\n")
    print(f"{'stage':<9} {'variant':<32} {'ms/image':>9} {'vs torch':>9}")
    for stage in ("extract", "frames"):
        base = next(t for (s, label), t in times.items() if s == stage and label.startswith("torch"))
        for (s, label), t in times.items():
            if s == stage:
                print(f"{stage:<9} {label:<32} {t / len(paths) * 1000:>9.1f} {base / t:>8.2f}x")


if __name__ == "__main__":
    main()
