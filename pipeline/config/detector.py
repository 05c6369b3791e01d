"""The `detector` section: `train-detector` and `evaluate-detector`."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config.base import Strict


class DetectorConfig(Strict):
    """`siteloc train-detector`: the 9-class Faster R-CNN (seed 000 sections 3.1.1 and 4.1)."""

    backbone: Literal["vgg16", "efficientnet_lite0"] = Field("efficientnet_lite0", description="the trunk: the "
                                                             "paper's VGG16 or EfficientNet-Lite0 (fast on a CPU)")
    weights: str | None = Field("imagenet", description="imagenet, a local state-dict file, or null for random")
    max_side: int | None = Field(384, ge=32, description="images are scaled so their longest side is at most this")
    min_size: int = Field(288, ge=32, description="Faster R-CNN's internal resize (paper: 600)")
    max_size: int = Field(384, ge=32, description="Faster R-CNN's internal resize cap (paper: 1000)")
    anchor_sizes: tuple[int, ...] = Field((16, 32, 64, 128, 256), min_length=1, description="paper: (128, 256, 512)")
    rpn_post_nms_top_n_test: int = Field(300, ge=1, description="RPN proposals kept at test time (paper: 300)")
    box_nms_thresh: float = Field(0.3, gt=0, le=1, description="per-class NMS IoU of the detections at test time "
                                  "(py-faster-rcnn: 0.3; torchvision: 0.5)")
    iterations: int = Field(1350, ge=1, description="the default fits 15 minutes on 2 CPU cores (office site)")
    batch_size: int = Field(2, ge=1, description="images per training iteration")
    lr: float = Field(5e-3, gt=0, description="SGD learning rate (paper: 1e-3 then 1e-4)")
    warmup_iterations: int = Field(100, ge=0, description="linear learning-rate warm-up from lr/100")
    lr_drop_at: float = Field(0.75, gt=0, le=1, description="share of the iterations after which lr drops 10x")
    momentum: float = Field(0.9, ge=0, lt=1, description="SGD momentum")
    weight_decay: float = Field(5e-4, ge=0, description="SGD weight decay")
    bias_lr_factor: float = Field(1.0, gt=0, description="biases learn this much faster (py-faster-rcnn: 2)")
    bias_decay: bool = Field(True, description="weight decay on biases too (py-faster-rcnn: false)")
    repeat_factor_threshold: float = Field(
        0.0, ge=0, le=1, description="repeat-factor sampling (LVIS): images of classes in fewer than this share of "
        "images are drawn more often; 0 draws uniformly")
    val_fraction: float = Field(0.15, ge=0, lt=1, description="share of the training stops held for validation")
    checkpoint_every: int = Field(200, ge=1, description="iterations between resumable checkpoints")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    amp: bool = Field(True, description="mixed precision (float16 autocast + grad scaling) on a GPU; CPU: off")
    eval_split: str = Field("test", description="the ingest split `evaluate-detector` scores (held-out stops)")
    eval_batch: int = Field(4, ge=1, description="images per forward pass when evaluating")
    plot_score: float = Field(0.5, ge=0, le=1, description="detections drawn in predictions.png score at least this")
    plot_images: int = Field(8, ge=1, description="held-out views in predictions.png")
    seed: int = Field(0, description="seed of the weights' initialisation, the sampling and the augmentation")
