"""Per-image outputs reused from an earlier run of a stage, keyed by the image's sha256 and the encoder.

After `siteloc update` most images of a site are the same files as before. A stage whose rows depend
only on an image's bytes and on its encoder (`extract`, `frame-features`, `prior features`) records each
image's sha256 (image_sha256.parquet) and an encoder key in its report.json; given the earlier output
with `--reuse`, it takes the rows of the images whose sha256 it has seen under the same key and encodes
only the others. The result is the output a full run would write.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from pipeline.errors import InputError, Problem
from pipeline.io import tables

HASHES_FILE = "image_sha256.parquet"


def encoder_key(*parts) -> str:
    """sha256 of what an image's rows depend on besides the image (JSON-able parts)."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def state_digest(model) -> str:
    """sha256 over a torch module's state (names and tensor bytes): what its outputs depend on."""
    import hashlib

    h = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def image_hashes(ingested: Path, image_ids: list[str]) -> dict[str, str]:
    """{image_id: sha256}: the stops' from images.parquet (ingest computed them), the run frames' from their files."""
    from pipeline.io.hashing import sha256_file

    t = tables.read_table(Path(ingested) / "images.parquet", "images").select(["image_id", "sha256"]).to_pydict()
    known = dict(zip(t["image_id"], t["sha256"], strict=True))
    return {i: known.get(i) or sha256_file(Path(ingested) / i) for i in dict.fromkeys(image_ids)}


def write_hashes(directory: Path, sha: dict[str, str], ids: list[str]) -> Path:
    return tables.write_table(Path(directory) / HASHES_FILE, tables.to_table("image_hashes", {
        "image_id": list(ids), "sha256": [sha[i] for i in ids]}), "image_hashes")


class EarlierImages:
    """The images of an earlier output by sha256, when it was made with the same encoder (`matches`).

    `report_field` names the report.json entry holding the earlier encoder key; `stage` the command that
    wrote it, for the error a directory that cannot be reused gets."""

    def __init__(self, directory: Path, key: str, *, report_field: str, stage: str):
        directory = Path(directory)
        report = directory / "report.json"
        if not report.is_file() or not (directory / HASHES_FILE).is_file():
            raise InputError(f"{directory}: not an output this siteloc can reuse", [Problem(
                str(directory), f"no report.json or {HASHES_FILE}",
                fix=f"pass the --out of an earlier `siteloc {stage}` (outputs from before image hashes were "
                    "recorded cannot be reused: run without --reuse)")])
        self.directory = directory
        self.matches = json.loads(report.read_text()).get(report_field) == key
        self._ids: dict[str, str] = {}
        if self.matches:
            t = tables.read_table(directory / HASHES_FILE, "image_hashes").to_pydict()
            self._ids = dict(zip(t["sha256"], t["image_id"], strict=True))

    def image_id(self, sha256: str) -> str | None:
        """The earlier image id with these bytes, or None."""
        return self._ids.get(sha256)

    def __len__(self) -> int:
        return len(self._ids)
