"""The sequence network of seed 000 section 3.3 and the windows it reads.

Frames (1000 logits each) go through one LSTM layer; the outputs are mean-pooled over time into the
sequence descriptor. It is trained as place classification: each window of `length` consecutive
mapping-run frames is labelled with the place of its last frame (a `place_cell_m` grid cell and one of
`heading_bins` headings). Classification and not a metric loss because the mapping runs label every
window with a place for free, a softmax over places needs no mining of hard negatives (which small CPU
batches make unreliable), and the pooled layer before the classifier is what is kept: PCA-whitened, it
is compared with the database's sequence descriptors like the paper's.
"""

from __future__ import annotations

import math

import numpy as np


def windows(steps: np.ndarray, breaks: np.ndarray, length: int) -> np.ndarray:
    """(N, length) row indices of every window of `length` consecutive rows of one run that crosses no
    break (a kidnapping starts a new segment) and no gap in the step numbers."""
    steps = np.asarray(steps)
    cut = np.r_[True, (np.diff(steps) != 1) | np.asarray(breaks, bool)[1:]]
    seg = np.cumsum(cut)
    out = [np.arange(i - length + 1, i + 1) for i in range(length - 1, len(steps)) if seg[i - length + 1] == seg[i]]
    return np.array(out, dtype=np.int64).reshape(-1, length)


def place_labels(xy: np.ndarray, theta: np.ndarray, cell_m: float, heading_bins: int) -> tuple[np.ndarray, list]:
    """Dense class ids of (grid cell, heading bin) places, and the place keys in id order."""
    b = np.floor((np.mod(theta, 2 * math.pi)) / (2 * math.pi / heading_bins)).astype(np.int64) % heading_bins
    keys = [(int(i), int(j), int(k)) for i, j, k in zip(np.floor(xy[:, 0] / cell_m).astype(np.int64),
                                                        np.floor(xy[:, 1] / cell_m).astype(np.int64), b,
                                                        strict=True)]
    order = sorted(set(keys))
    index = {k: n for n, k in enumerate(order)}
    return np.array([index[k] for k in keys], dtype=np.int64), order


def build_sequence_model(in_dim: int, hidden: int, num_places: int):
    import torch
    from torch import nn

    class SequenceLSTM(nn.Module):
        """(B, T, in_dim) frame features -> (B, hidden) descriptor (mean over time) -> place logits."""

        def __init__(self):
            super().__init__()
            # Logit scales differ between frames; normalising each frame keeps the LSTM's gates in range.
            self.norm = nn.LayerNorm(in_dim)
            self.lstm = nn.LSTM(in_dim, hidden, batch_first=True)
            self.head = nn.Linear(hidden, num_places)

        def describe(self, x: torch.Tensor) -> torch.Tensor:
            y, _ = self.lstm(self.norm(x))
            return y.mean(dim=1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.head(self.describe(x))

    return SequenceLSTM()
