"""`siteloc extract --engine ray`: the chunks of an extraction described by Ray actors running the ONNX graph.

The driver exports and checks one graph per image size (torch stays there), then each actor opens the
graphs with onnxruntime (one intra-op thread, as the local pool's sessions on 2 cores) and writes its
chunk's tables into the extraction's `.partial/` folder; `run_extract` merges them as it does the local
chunks, so both engines write the same tables. See `pipeline.ray_engine` for retries and resuming.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.retrieval.extract_chunks import ImageRecord, chunk_done, write_chunk


class ChunkDescriber:
    """A Ray actor: describes one chunk per call through the exported graphs and writes its tables."""

    def __init__(self, partial: str, ingested: str, graphs: dict[str, tuple[str, dict]]):
        from pipeline.chunked_encoding import SizedSessions

        self.partial, self.ingested, self.sessions = Path(partial), Path(ingested), SizedSessions(graphs)

    def __call__(self, batch: dict) -> dict:
        from pipeline.runtime.describer import describe_with

        k = int(batch["chunk"][0])
        ids = [str(i) for i in batch["image_ids"][0]]
        write_chunk(self.partial, k, ids, [describe_with(*self.sessions(self.ingested / i)) for i in ids])
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
