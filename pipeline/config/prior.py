"""The `prior` section: seed 001's area prior (`prior features`, `prior build`, `prior evaluate`)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config.base import Strict


class PriorConfig(Strict):
    """`siteloc prior ...`: seed 001's area prior from pretrained multi-layer CNN features (no training)."""

    backbone: Literal["efficientnet_lite0", "alexnet", "vgg16"] = Field(
        "efficientnet_lite0", description="pretrained CNN (the paper: AlexNet; Lite0's ImageNet weights ship offline)")
    weights: str | None = Field("imagenet", description="imagenet, a local state-dict file, or null for random")
    input_size: int = Field(224, ge=32, description="images are resized to this square (the network's input)")
    batch: int = Field(16, ge=1, description="images per network pass")
    chunk: int = Field(256, ge=1, description="images per resumable chunk (a file under <out>.partial/; a Ray "
                       "task with --engine ray)")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    engine: Literal["auto", "torch", "onnx"] = Field(
        "auto", description="what runs the encoder in `prior features`: onnx (the graph the bundle carries, checked "
        "against torch on export.parity_images images of each size, one image per thread), torch, or auto (onnx on "
        "the CPU, torch on a GPU)")
    compression: Literal["ipca", "kpca", "srp", "grp", "none"] = Field(
        "srp", description="per-layer compression (the paper picked sparse random projection)")
    n_components: int = Field(128, ge=2, description="compressed dimension (the paper: 128)")
    k: int = Field(10, ge=1, description="neighbours returned by the ball tree per layer (the paper: 10)")
    leaf_size: int = Field(40, ge=1, description="ball tree leaf size")
    index: Literal["balltree", "brute"] = Field(
        "balltree", description="exact k-NN by scikit-learn's BallTree (the paper's) or brute-force numpy (the same "
        "neighbours; 2-3x faster at 128-d, benchmarks/prior_query.py)")
    # The defaults are the best of `prior evaluate` on the office site (docs/prior.md); the paper preset
    # keeps the paper's choice (Spearman, most weight on pool5).
    measure: Literal["spearman", "pearson", "euclidean", "gaussian"] = Field(
        "gaussian", description="how the neighbours' classes are scored: spearman or pearson correlation, "
        "euclidean (the tree's order), or gaussian (each class's Gaussian)")
    layer_weights: tuple[float, float, float] = Field(
        (1.0, 1.0, 1.0), description="relative weights of the three layers, low to high (normalised to sum 1)")
    shrinkage: float | None = Field(
        None, ge=0, le=1, description="covariance shrinkage of the per-(room, area) Gaussians; null: Ledoit-Wolf")
    temperature: float | None = Field(
        None, gt=0, description="Gaussian log-likelihoods are divided by this before the softmax; null: the dimension")
    area_radius_m: float = Field(2.0, gt=0, description="an area's free space: cells within this of its stops, "
                                 "nearer to them than to any other area's")
    max_areas: int = Field(3, ge=1, description="seeding spreads particles over at most this many top areas")
    seed: int = Field(0, description="seed of the compression (PCA / kernel PCA sample)")
