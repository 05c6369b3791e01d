"""`siteloc extract --engine ray`: the chunks of an extraction described by Ray actors running the ONNX graph.

The driver exports and checks one graph per image size (torch stays there), then each actor opens the
graphs with onnxruntime (one intra-op thread, as the local pool's sessions on 2 cores) and writes its
chunk's tables into the extraction's `.partial/` folder; `run_extract` merges them as it does the local
chunks, so both engines write the same tables. See `pipeline.ray_engine` for retries and resuming.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.retrieval.extract import ImageRecord, chunk_done, write_chunk


class ChunkDescriber:
    """A Ray actor: describes one chunk per call through the exported graphs and writes its tables."""

    def __init__(self, partial: str, ingested: str, graphs: dict[str, tuple[str, dict]]):
        self.partial, self.ingested, self.graphs = Path(partial), Path(ingested), graphs
        self.sessions: dict[str, object] = {}

    def _session(self, key: str):
        if key not in self.sessions:
            import onnxruntime as ort

            options = ort.SessionOptions()
            options.intra_op_num_threads = 1
            options.inter_op_num_threads = 1
            self.sessions[key] = ort.InferenceSession(self.graphs[key][0], options,
                                                      providers=["CPUExecutionProvider"])
        return self.sessions[key]

    def __call__(self, batch: dict) -> dict:
        from pipeline.runtime.describer import describe_with, image_array

        k = int(batch["chunk"][0])
        ids = [str(i) for i in batch["image_ids"][0]]
        described = []
        for image_id in ids:
            image = image_array(self.ingested / image_id)
            key = f"{image.shape[2]}x{image.shape[1]}"
            if key not in self.graphs:
                from pipeline.errors import SitelocError

                raise SitelocError(f"{self.ingested / image_id}: an image of {key} pixels, for which no graph was "
                                   f"exported (sizes: {sorted(self.graphs)})")
            described.append(describe_with(self._session(key), image, self.graphs[key][1]))
        write_chunk(self.partial, k, ids, described)
        return {"chunk": np.array([k]), "items": np.array([len(ids)])}


def extract_on_ray(chunks: list[list[ImageRecord]], partial: Path, ingested: Path, pool, bar, *,
                   ray_address: str | None = None, actor: type = ChunkDescriber) -> list[str]:
    """Describe the chunks not yet in `partial` on Ray; `pool` (extract's `onnx_describer`) exports the graphs.
    Returns the image ids described."""
    from pipeline.chunked_encoding import export_graphs
    from pipeline.ray_engine import run_on_ray

    pending = [k for k in range(len(chunks)) if not chunk_done(partial, k)]
    todo = set(pending)
    bar.update(sum(len(c) for k, c in enumerate(chunks) if k not in todo))
    if not pending:
        return []
    graphs = export_graphs([ingested / rec.image_id for k in pending for rec in chunks[k]], pool)
    run_on_ray(ray_address, [{"chunk": k, "image_ids": [rec.image_id for rec in chunks[k]]} for k in pending], actor,
               {"partial": str(partial), "ingested": str(ingested), "graphs": graphs},
               on_done=lambda _k, n: bar.update(n))
    return [rec.image_id for k in pending for rec in chunks[k]]
