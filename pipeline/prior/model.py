"""Seed 001's model database: per layer, compressed vectors in a ball tree, labelled (room, area).

A query image's three layer vectors are compressed with the layer's fitted compression; each layer's
ball tree (scikit-learn, Minkowski p=2) returns the k nearest database images. Their classes are scored
per layer by `measure`:

- `spearman` / `pearson`: a class's score is the best similarity (1 + r) / 2 among its neighbours;
- `euclidean`: the ball tree's own order, 1 / (1 + distance) (no re-scoring);
- `gaussian`: every class seen among any layer's neighbours is scored by its Gaussian's log-likelihood.

Each layer's scores become probabilities over the classes (correlations: normalised to sum 1; Gaussian:
a softmax of log-likelihoods divided by `temperature`, the dimension by default, so that 128 dimensions
do not make every decision certain); the layers are mixed by `layer_weights` (low to high). `append`
adds images with the fitted compressions: old rows, compressions and the Gaussians of classes that got
no new image stay bit for bit as they were. Saved as npz arrays, Parquet and JSON; the ball trees are
rebuilt from the vectors on load (sub-second for a building), so nothing is pickled.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem
from pipeline.prior.scoring import ClassGaussians, similarity_from_r, softmax, standardise

MEASURES = ("spearman", "pearson", "euclidean", "gaussian")
FORMAT = "siteloc-area-prior"
FORMAT_VERSION = "1.0"


@dataclass
class PriorSettings:
    k: int = 10
    leaf_size: int = 40
    measure: str = "spearman"
    layer_weights: tuple[float, ...] = (0.6, 0.3, 0.1)
    temperature: float | None = None
    index: str = "balltree"  # or "brute": the same exact neighbours by numpy (faster at 128-d)


def top_areas(probs: np.ndarray, max_areas: int) -> np.ndarray:
    """Particle shares per class: the `max_areas` most probable classes keep their probability, the rest 0."""
    probs = np.asarray(probs, dtype=np.float64)
    keep = np.argsort(-probs, kind="stable")[:max_areas]
    w = np.zeros_like(probs)
    w[keep] = probs[keep]
    return w


class AreaPrior:
    def __init__(self, layers: tuple[str, ...], compressors: dict, settings: PriorSettings, encoder: dict):
        self.layers, self.compressors, self.settings, self.encoder = tuple(layers), compressors, settings, encoder
        self.classes: list[tuple[str, str]] = []
        self.rows = {c: [] for c in ("image_id", "stop_id", "room", "area", "split")}
        self.xyt = np.zeros((0, 3))
        self.labels = np.zeros(0, dtype=np.int64)
        self.vectors: dict[str, np.ndarray] = {}
        self.gaussians: dict[str, ClassGaussians] = {}
        self._trees: dict = {}
        self._std: dict = {}

    # ---------------------------------------------------------------------------------- building

    @classmethod
    def build(cls, meta: dict, raw: dict[str, np.ndarray], *, compression: str, n_components: int, seed: int,
              settings: PriorSettings, encoder: dict, shrinkage: float | None = None) -> AreaPrior:
        """Fit each layer's compression on `raw` (the database images) and index them."""
        from pipeline.descriptors.compression import make_compressor

        layers = tuple(raw)
        comps = {name: make_compressor(compression, n_components, seed=seed).fit(raw[name]) for name in layers}
        prior = cls(layers, comps, settings, encoder)
        prior._add(meta, raw)
        prior.gaussians = {name: ClassGaussians(shrinkage).fit(prior.vectors[name], prior.labels, len(prior.classes))
                           for name in layers}
        return prior

    def append(self, meta: dict, raw: dict[str, np.ndarray]) -> list[int]:
        """Add images (new areas, or more of known ones) without refitting the compressions; returns the
        classes whose Gaussians were (re)fitted: the new ones and those that got images."""
        if set(raw) != set(self.layers):
            raise ValueError(f"append needs the layers {self.layers}, got {tuple(raw)}")
        touched = self._add(meta, raw)
        for name in self.layers:
            self.gaussians[name].update(self.vectors[name], self.labels, touched)
        return touched

    def replace(self, keep: np.ndarray, meta: dict, raw: dict[str, np.ndarray]) -> dict:
        """Drop the rows where `keep` is False and add new images, with the fitted compressions.

        Kept rows, and the Gaussians of classes that neither lost nor got a row, stay bit for bit; a class
        left without rows is removed. Returns the counts and the classes refitted, added and removed."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != self.labels.shape:
            raise ValueError(f"keep has {keep.size} entries for {self.labels.size} rows")
        incoming = set(zip(meta["room"], meta["area"], strict=True))
        alive = np.zeros(len(self.classes), dtype=bool)
        alive[np.unique(self.labels[keep])] = True
        alive |= np.array([c in incoming for c in self.classes], dtype=bool)
        renumber = np.cumsum(alive) - 1
        lost = {int(renumber[k]) for k in np.unique(self.labels[~keep]) if alive[k]}
        removed = [self.classes[k] for k in np.flatnonzero(~alive)]
        known = {c for c, a in zip(self.classes, alive, strict=True) if a}
        self.classes = [c for c, a in zip(self.classes, alive, strict=True) if a]
        self.rows = {c: [v for v, k in zip(vals, keep, strict=True) if k] for c, vals in self.rows.items()}
        self.xyt, self.labels = self.xyt[keep], renumber[self.labels[keep]]
        for name in self.layers:
            self.vectors[name] = self.vectors[name][keep]
            self.gaussians[name].keep(alive)
        self._trees, self._std = {}, {}
        touched = sorted(lost | set(self._add(meta, raw))) if len(meta["room"]) else sorted(lost)
        for name in self.layers:
            self.gaussians[name].update(self.vectors[name], self.labels, touched)
        return {"kept": int(keep.sum()), "dropped": int((~keep).sum()), "added": len(meta["room"]),
                "refitted_classes": [list(self.classes[k]) for k in touched if self.classes[k] in known],
                "new_classes": [list(self.classes[k]) for k in touched if self.classes[k] not in known],
                "removed_classes": [list(c) for c in removed]}

    def _add(self, meta: dict, raw: dict[str, np.ndarray]) -> list[int]:
        index = {c: i for i, c in enumerate(self.classes)}
        labels = []
        for room, area in zip(meta["room"], meta["area"], strict=True):
            if (room, area) not in index:
                index[(room, area)] = len(self.classes)
                self.classes.append((room, area))
            labels.append(index[(room, area)])
        for c in self.rows:
            self.rows[c].extend(meta[c])
        self.xyt = np.vstack([self.xyt, np.column_stack([meta["x"], meta["y"], meta["theta"]])])
        self.labels = np.r_[self.labels, np.asarray(labels, dtype=np.int64)]
        for name in self.layers:
            new = self.compressors[name].transform(raw[name]).astype(np.float32)
            old = self.vectors.get(name)
            self.vectors[name] = new if old is None else np.vstack([old, new])
        self._trees, self._std = {}, {}
        return sorted(set(labels))

    # ------------------------------------------------------------------------------------ querying

    def tree(self, layer: str):
        if layer not in self._trees:
            from sklearn.neighbors import BallTree

            self._trees[layer] = BallTree(self.vectors[layer], leaf_size=self.settings.leaf_size)
        return self._trees[layer]

    def _standardised(self, layer: str, ranks: bool) -> np.ndarray:
        key = (layer, ranks)
        if key not in self._std:
            self._std[key] = standardise(self.vectors[layer], ranks=ranks)
        return self._std[key]

    def compress(self, raw: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {name: self.compressors[name].transform(np.atleast_2d(raw[name])) for name in self.layers}

    def neighbours(self, compressed: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """{layer: (distances (Q, k), database rows (Q, k))} from each layer's ball tree."""
        k = min(self.settings.k, len(self.labels))
        if self.settings.index == "brute":
            return {name: self._brute(name, compressed[name], k) for name in self.layers}
        return {name: self.tree(name).query(compressed[name], k=k) for name in self.layers}

    def _brute(self, layer: str, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        db = self.vectors[layer].astype(np.float64)
        q = np.atleast_2d(q).astype(np.float64)
        d2 = np.maximum((q**2).sum(1)[:, None] - 2.0 * q @ db.T + (db**2).sum(1)[None], 0.0)
        idx = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < len(db) else np.tile(np.arange(len(db)), (len(q), 1))
        order = np.argsort(np.take_along_axis(d2, idx, 1), axis=1, kind="stable")
        idx = np.take_along_axis(idx, order, 1)
        return np.sqrt(np.take_along_axis(d2, idx, 1)), idx

    def layer_probabilities(self, compressed: dict[str, np.ndarray], measure: str | None = None,
                            found: dict | None = None) -> dict[str, np.ndarray]:
        """{layer: (Q, C) class probabilities} of compressed queries."""
        measure = measure or self.settings.measure
        if measure not in MEASURES:
            raise ValueError(f"measure must be one of {MEASURES}, got '{measure}'")
        found = found or self.neighbours(compressed)
        n_q, n_c = len(next(iter(compressed.values()))), len(self.classes)
        if measure == "gaussian":
            candidates = [np.unique(np.concatenate([self.labels[found[n][1][q]] for n in self.layers]))
                          for q in range(n_q)]
        out = {}
        for name in self.layers:
            dist, idx = found[name]
            p = np.zeros((n_q, n_c))
            if measure in ("spearman", "pearson"):
                ranks = measure == "spearman"
                qs = standardise(compressed[name], ranks=ranks)
                db = self._standardised(name, ranks)
                sim = similarity_from_r(np.einsum("qkd,qd->qk", db[idx], qs))
            elif measure == "euclidean":
                sim = 1.0 / (1.0 + dist)
            for q in range(n_q):
                if measure == "gaussian":
                    ks = candidates[q]
                    ll = self.gaussians[name].log_likelihood(compressed[name][q], ks)
                    p[q, ks] = softmax(ll / (self.settings.temperature or compressed[name].shape[1]))
                else:
                    np.maximum.at(p[q], self.labels[idx[q]], sim[q])
                    p[q] /= max(p[q].sum(), 1e-12)
            out[name] = p
        return out

    def combine(self, per_layer: dict[str, np.ndarray], weights=None) -> np.ndarray:
        w = np.asarray(self.settings.layer_weights if weights is None else weights, dtype=np.float64)
        if len(w) != len(self.layers) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError(f"layer weights {w.tolist()} do not fit the layers {self.layers}")
        return sum(wi * per_layer[n] for wi, n in zip(w / w.sum(), self.layers, strict=True))

    def probabilities(self, raw: dict[str, np.ndarray], measure: str | None = None, weights=None) -> np.ndarray:
        """(Q, C) probability of each (room, area) class for raw layer vectors of Q images."""
        return self.combine(self.layer_probabilities(self.compress(raw), measure), weights)

    # ------------------------------------------------------------------------------------ area space

    def area_cells(self, lmap, radius_m: float) -> np.ndarray:
        """(K,) class of each free cell of `lmap` (-1: none): the class of the nearest database stop, if
        that stop is within `radius_m` (an area's free space is where its images were taken from)."""
        from scipy.spatial import cKDTree

        row, col = np.divmod(lmap.free_cells, lmap.width)
        xy = np.column_stack([lmap.origin_x + (col + 0.5) * lmap.resolution,
                              lmap.origin_y + (row + 0.5) * lmap.resolution])
        stops, first = np.unique(self.xyt[:, :2], axis=0, return_index=True)
        dist, nearest = cKDTree(stops).query(xy, k=1)
        out = self.labels[first][nearest]
        out[dist > radius_m] = -1
        return out

    # ---------------------------------------------------------------------------------- persistence

    def nbytes(self) -> dict[str, int]:
        """Bytes of what a query needs, per layer: the compression's arrays plus the database vectors."""
        return {n: int(self.compressors[n].nbytes() + self.vectors[n].nbytes) for n in self.layers}

    def save(self, out: Path) -> Path:
        from pipeline.io import tables
        from pipeline.io.atomic import atomic_file, write_text_atomic

        out = Path(out)
        for name in self.layers:
            self.compressors[name].save(out / f"{name}_compression.npz")
            with atomic_file(out / f"{name}_gaussians.npz", "wb") as fh:
                np.savez(fh, **self.gaussians[name].arrays())
            cols = {**self.rows, "x": self.xyt[:, 0], "y": self.xyt[:, 1], "theta": self.xyt[:, 2],
                    "descriptor": tables.descriptor_array(self.vectors[name])}
            tables.write_table(out / f"db_{name}.parquet", tables.to_table("prior_db", cols), "prior_db",
                               metadata={"layer": name})
        s = self.settings
        doc = {"format": FORMAT, "version": FORMAT_VERSION, "layers": list(self.layers), "encoder": self.encoder,
               "classes": [list(c) for c in self.classes], "images": len(self.labels),
               "settings": {"k": s.k, "leaf_size": s.leaf_size, "measure": s.measure,
                            "layer_weights": list(s.layer_weights), "temperature": s.temperature,
                            "index": s.index}}
        write_text_atomic(out / "prior.json", json.dumps(doc, indent=2) + "\n")
        return out

    @classmethod
    def load(cls, path: Path) -> AreaPrior:
        from pipeline.descriptors.compression import load_compressor
        from pipeline.io import tables

        path = Path(path)
        doc_path = path / "prior.json"
        if not doc_path.is_file():
            raise InputError(f"{path}: not an area prior", [Problem(
                str(doc_path), "missing", fix="build one with `siteloc prior build FEATURES --out DIR`")])
        doc = json.loads(doc_path.read_text())
        if doc.get("format") != FORMAT or str(doc.get("version", "")).split(".")[0] != FORMAT_VERSION.split(".")[0]:
            raise InputError(f"{doc_path}: not readable", [Problem(
                str(doc_path), f"format {doc.get('format')!r} version {doc.get('version')!r}",
                fix=f"rebuild it with this siteloc ({FORMAT} {FORMAT_VERSION})")])
        s = doc["settings"]
        settings = PriorSettings(s["k"], s["leaf_size"], s["measure"], tuple(s["layer_weights"]), s["temperature"],
                                 s.get("index", "balltree"))
        layers = tuple(doc["layers"])
        prior = cls(layers, {n: load_compressor(path / f"{n}_compression.npz") for n in layers}, settings,
                    doc["encoder"])
        prior.classes = [tuple(c) for c in doc["classes"]]
        index = {c: i for i, c in enumerate(prior.classes)}
        for n, name in enumerate(layers):
            t = tables.read_table(path / f"db_{name}.parquet", "prior_db")
            prior.vectors[name] = tables.descriptor_matrix(t)
            with np.load(path / f"{name}_gaussians.npz", allow_pickle=False) as z:
                prior.gaussians[name] = ClassGaussians.from_arrays(z)
            if n == 0:
                prior.rows = {c: t.column(c).to_pylist() for c in prior.rows}
                prior.xyt = np.column_stack([t.column(c).to_numpy() for c in ("x", "y", "theta")])
                prior.labels = np.array([index[(r, a)] for r, a in zip(prior.rows["room"], prior.rows["area"],
                                                                       strict=True)], dtype=np.int64)
        return prior
