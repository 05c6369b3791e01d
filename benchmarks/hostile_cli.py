"""A hostile try of the CLI: bad inputs a careless or hostile user gives, and how each command answers.

Every case builds its inputs from tiny generated fixtures, runs `siteloc ...` in a subprocess (the code of
--code, so an older checkout can be compared with this one) and classifies the outcome:

    clean      refused with exit 1, a short readable message naming the cause, inputs untouched, nothing
               written (or, for valid input, accepted)
    accepted   exit 0 on input that must be refused (silently wrong data)
    refused    valid input refused
    off-target refused, but not for the case's cause (another check happened to stop it)
    unexpected `error: unexpected ...`, a traceback, or another exit code
    data loss  an input changed or disappeared
    leftover   refused, but an output or a temporary was written
    noisy      refused, but the message is long (> 4000 characters) or carries terminal control bytes

    .venv/bin/python benchmarks/hostile_cli.py                      # this checkout
    .venv/bin/python benchmarks/hostile_cli.py --code /tmp/older    # another checkout, same cases
"""

from __future__ import annotations

import argparse
import gzip
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.machine import machine_summary  # noqa: E402
from tests.fixtures.capture_site import write_capture_site  # noqa: E402
from tests.fixtures.carmen_logs import flaser_line, room_log_lines, room_poses, write_log  # noqa: E402


@dataclass
class Case:
    name: str
    build: Callable[[Path], tuple[list[str], list[Path], list[Path]]]  # work dir -> (argv, inputs, outputs)
    refuse: bool = True
    words: tuple[str, ...] = ()  # a refusal is for the right reason when its message holds all of them


def snapshot(paths: list[Path]) -> dict[str, bytes]:
    out = {}
    for p in paths:
        if p.is_dir():
            out.update({str(f): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()})
        elif p.exists():
            out[str(p)] = p.read_bytes()
        else:
            out[str(p)] = b"<absent>"
    return out


# --- ingest ------------------------------------------------------------------------------------------------

def _site(work: Path) -> Path:
    return write_capture_site(work / "site")


def ingest_case(change: Callable[[Path], None] | None = None, out_rel: str = "out", force: bool = False):
    def build(work: Path):
        site = _site(work)
        if change is not None:
            change(site)
        argv = ["ingest", str(site), "--out", str(work / out_rel), "--config", "ci"] + (["--force"] if force else [])
        return argv, [site], ([] if out_rel.startswith("site") or out_rel == "." else [work / out_rel])
    return build


def _append(site: Path, raw: bytes) -> None:
    with (site / "captures.csv").open("ab") as fh:
        fh.write(raw)


def _extra_field(site: Path) -> None:  # an unquoted comma in a room name: room and area would shift
    csv = site / "captures.csv"
    csv.write_bytes(csv.read_bytes().replace(b",room_a,west", b",room_a, east wing,west", 1))


def _first_image(site: Path) -> Path:
    return site / (site / "captures.csv").read_text().splitlines()[1].split(",")[0]


def _image_16bit(site: Path) -> None:
    path = _first_image(site)
    w, h = Image.open(path).size
    Image.fromarray(np.full((h, w), 40000, np.uint16)).save(path)


def _image_truncated(site: Path) -> None:
    path = _first_image(site)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _image_empty(site: Path) -> None:
    _first_image(site).write_bytes(b"")


def _latin1(site: Path) -> None:
    csv = site / "captures.csv"
    lines = csv.read_bytes().splitlines(keepends=True)
    lines[1] = lines[1].rstrip(b"\r\n") + " K\xfcche".encode("latin-1") + b"\n"
    csv.write_bytes(b"".join(lines))


def _utf16(site: Path) -> None:
    (site / "captures.csv").write_bytes((site / "captures.csv").read_text().encode("utf-16"))


def _utf8_bom(site: Path) -> None:
    (site / "captures.csv").write_bytes(b"\xef\xbb\xbf" + (site / "captures.csv").read_bytes())


def _garbage_line(site: Path) -> None:
    _append(site, b"\x1b[2J\x1b[31m" + b"A" * 10_000_000 + b"\n")


# --- ingest-log --------------------------------------------------------------------------------------------

def log_case(lines_of: Callable[[], list[str]], refuse: bool = True):
    def build(work: Path):
        log = write_log(work / "room.log", lines_of())
        return ["ingest-log", str(log), "--out", str(work / "out"), "--config", "ci"], [log], [work / "out"]
    return build


def _nan_lines() -> list[str]:
    poses = room_poses(40)
    return [flaser_line(np.full(181, np.nan), p, 0.1 * i) for i, p in enumerate(poses)]


def _far_pose_lines() -> list[str]:
    lines = room_log_lines(40)
    poses = room_poses(40)
    far = poses[20].copy()
    far[0] = 1e7
    lines[20] = flaser_line(np.full(181, 3.0), far, 2.0)
    return lines


def _escape_line() -> list[str]:
    return room_log_lines(40)[:10] + ["FLASER 3 \x1b[2J\x1b]0;owned\x07 garbage"] + room_log_lines(40)[10:]


# --- bundles -----------------------------------------------------------------------------------------------

def _bundle(work: Path) -> Path:
    from pipeline.bundle.export import write_manifest

    root = work / "site-1.0"
    (root / "db").mkdir(parents=True)
    (root / "map").mkdir()
    (root / "db" / "a.bin").write_bytes(bytes(range(256)) * 4)
    (root / "map" / "map.yaml").write_text("image: map.pgm\n")
    (root / "filter.yaml").write_text(
        "filter: {}\nretrieval: {top_n: 4, rerank: true, query_regions: 10, candidate_weights: [4, 3, 2, 1]}\n"
        "laser: {angle_min: -1.5, angle_increment: 0.01, range_max: 10.0, base_from_laser: [0.0, 0.0, 0.0]}\n")
    write_manifest(root, {"bundle_version": "1.0", "site": "site"})
    return root


def bundle_case(change: Callable[[Path, Path], Path]):
    """`siteloc localize --bundle B LOG` on a bundle altered by `change(bundle, work) -> what to pass`."""
    def build(work: Path):
        log = write_log(work / "room.log", room_log_lines(20))
        given = change(_bundle(work), work)
        argv = ["localize", str(log), "--bundle", str(given), "--out", str(work / "out"), "--config", "ci"]
        return argv, [given, log], [work / "out"]
    return build


def _manifest_link(bundle: Path, work: Path) -> Path:
    outside = work / "elsewhere.json"
    shutil.move(bundle / "manifest.json", outside)
    os.symlink(outside, bundle / "manifest.json")
    return bundle


def _manifest_wrong_type(bundle: Path, work: Path) -> Path:
    import json

    m = json.loads((bundle / "manifest.json").read_text())
    m["files"]["db/a.bin"] = 3
    (bundle / "manifest.json").write_text(json.dumps(m))
    return bundle


def _truncated_archive(bundle: Path, work: Path) -> Path:
    archive = work / "site-1.0.tar.gz"
    with tarfile.open(archive, "w:gz") as tf:
        tf.add(bundle, arcname=bundle.name)
    data = archive.read_bytes()
    archive.write_bytes(data[: len(data) // 2])
    shutil.rmtree(bundle)
    return archive


def _empty_archive(bundle: Path, work: Path) -> Path:
    archive = work / "site-1.0.tar.gz"
    archive.write_bytes(gzip.compress(b""))
    shutil.rmtree(bundle)
    return archive


CASES = [
    Case("ingest: --out is the site, --force", ingest_case(out_rel="site", force=True), words=("input",)),
    Case("ingest: --out inside the site, --force", ingest_case(out_rel="site/images", force=True), words=("input",)),
    Case("ingest: --out contains the site, --force", ingest_case(out_rel=".", force=True), words=("input",)),
    Case("ingest: row with an extra field", ingest_case(_extra_field), words=("line 2", "fields")),
    Case("ingest: Latin-1 byte in captures.csv", ingest_case(_latin1), words=("line 2", "UTF-8")),
    Case("ingest: captures.csv in UTF-16", ingest_case(_utf16), words=("UTF-16",)),
    Case("ingest: 10 MB line with escape bytes", ingest_case(_garbage_line), words=("captures.csv",)),
    Case("ingest: 16-bit PNG", ingest_case(_image_16bit), words=("16-bit",)),
    Case("ingest: truncated image", ingest_case(_image_truncated), words=("truncated",)),
    Case("ingest: empty image", ingest_case(_image_empty), words=("empty",)),
    Case("ingest: UTF-8 with byte-order mark (valid)", ingest_case(_utf8_bom), refuse=False),
    Case("ingest: a valid site (valid)", ingest_case(), refuse=False),
    Case("ingest-log: every range NaN", log_case(_nan_lines), words=("valid range",)),
    Case("ingest-log: one pose at x = 1e7", log_case(_far_pose_lines), words=("line",)),
    Case("ingest-log: escape bytes in a line", log_case(_escape_line), words=("room.log",)),
    Case("ingest-log: a valid log (valid)", log_case(lambda: room_log_lines(40), refuse=False), refuse=False),
    Case("localize: manifest.json is a link out", bundle_case(_manifest_link), words=("manifest.json", "link")),
    Case("localize: manifest entry of the wrong type", bundle_case(_manifest_wrong_type), words=("db/a.bin",)),
    Case("localize: truncated bundle archive", bundle_case(_truncated_archive), words=("site-1.0.tar.gz",)),
    Case("localize: empty bundle archive", bundle_case(_empty_archive), words=("site-1.0.tar.gz",)),
]


def classify(case: Case, code: Path, work: Path) -> tuple[str, str]:
    argv, inputs, outputs = case.build(work)
    before = snapshot(inputs)
    env = {**os.environ, "PYTHONPATH": str(code), "COLUMNS": "200"}
    proc = subprocess.run([sys.executable, "-c", "from stages.app import app; app()", *argv], cwd=code, env=env,
                          capture_output=True, timeout=600)
    text = (proc.stdout + proc.stderr).decode("utf-8", "replace")
    last = next((line for line in reversed(text.splitlines()) if line.startswith("error")), text[-200:])
    if snapshot(inputs) != before:
        return "data loss", last
    if "unexpected" in text or "Traceback" in text or proc.returncode not in (0, 1):
        return "unexpected", last
    if not case.refuse:
        return ("clean" if proc.returncode == 0 else "refused"), last
    if proc.returncode == 0:
        return "accepted", last
    if not all(w.lower() in text.lower() for w in case.words):
        return "off-target", last
    if any(p.exists() for p in outputs) or any(".tmp-" in p.name for p in work.rglob("*")):
        return "leftover", last
    if len(text) > 4000 or "\x1b" in text or "\x07" in text:
        return "noisy", last
    return "clean", last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--code", type=Path, default=ROOT, help="the checkout whose CLI is tried (default: this one)")
    args = parser.parse_args()
    print(machine_summary())
    print(f"code: {args.code.resolve()}")
    counts: Counter[str] = Counter()
    t0 = time.perf_counter()
    for case in CASES:
        with tempfile.TemporaryDirectory(prefix="hostile-") as tmp:
            outcome, last = classify(case, args.code.resolve(), Path(tmp))
        counts[outcome] += 1
        print(f"{outcome:10s}  {case.name:48s}  {last[-150:].encode('unicode_escape').decode()}")
    kinds = ("clean", "accepted", "refused", "off-target", "unexpected", "data loss", "leftover", "noisy")
    print(f"{len(CASES)} cases in {time.perf_counter() - t0:.0f} s: " + ", ".join(f"{k} {counts[k]}" for k in kinds))


if __name__ == "__main__":
    main()
