"""Place-recognition heads over a conv trunk's map, for `retrieval.backbone: checkpoint`.

Both take the trunk's (B, D, h, w) map and give one l2-normalised global descriptor per image, which is
then the image's IPA (RPA still pools the trunk's map over the detector's regions):

- `NetVLAD` (Arandjelovic et al. 2016), K clusters: each local feature x (l2-normalised over channels
  first, `normalize_input`) is softly assigned to the clusters, a = softmax_k(w_k . x + b_k); the
  residuals to the centres are summed, V_k = sum_x a_k(x) (x - c_k); each V_k is l2-normalised
  (intra-normalisation), the K x D matrix is flattened and l2-normalised: a K * D vector.
  Parameters: `assign.weight` (K, D, 1, 1), `assign.bias` (K,), `centroids` (K, D).
- `GeM` (Radenovic et al. 2018): (mean over positions of max(x, eps)^p)^(1 / p), l2-normalised: D values.
  `p` is learned (the parameter `p`, shape (1,), in the state dict) or given (not in the state dict).

Both export to ONNX (opset 17) as they are.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

HEADS = ("netvlad", "gem")


class NetVLAD(nn.Module):
    def __init__(self, clusters: int, dim: int, *, normalize_input: bool = True):
        super().__init__()
        if clusters < 1 or dim < 1:
            raise ValueError(f"NetVLAD needs at least one cluster and one channel, got {clusters} x {dim}")
        self.clusters, self.dim, self.normalize_input = int(clusters), int(dim), bool(normalize_input)
        self.assign = nn.Conv2d(dim, clusters, kernel_size=1, bias=True)
        self.centroids = nn.Parameter(torch.randn(clusters, dim) * 0.1)

    @property
    def out_dim(self) -> int:
        return self.clusters * self.dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.normalize_input:
            x = F.normalize(x, dim=1)
        a = F.softmax(self.assign(x).flatten(2), dim=1)  # (B, K, N)
        local = x.flatten(2).transpose(1, 2)  # (B, N, D)
        v = torch.bmm(a, local) - a.sum(dim=2, keepdim=True) * self.centroids[None]  # (B, K, D)
        v = F.normalize(v, dim=2)
        return F.normalize(v.flatten(1), dim=1)


class GeM(nn.Module):
    def __init__(self, dim: int, *, p: float = 3.0, learn_p: bool = True, eps: float = 1e-6):
        super().__init__()
        if p <= 0:
            raise ValueError(f"GeM needs p > 0, got {p}")
        self.dim, self.eps, self.learn_p = int(dim), float(eps), bool(learn_p)
        if learn_p:
            self.p = nn.Parameter(torch.full((1,), float(p)))
        else:
            self.register_buffer("p", torch.full((1,), float(p)), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.p.reshape(1, 1, 1, 1)
        y = x.clamp(min=self.eps).pow(p).mean(dim=(2, 3)).pow(1.0 / self.p.reshape(1, 1))
        return F.normalize(y, dim=1)
