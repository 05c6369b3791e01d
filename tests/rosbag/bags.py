"""Bag fixtures: the tiny capture site exported, and a rewriter that breaks or edits one thing of a bag."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from pipeline.config import load_config
from pipeline.rosbag.bagfile import BagWriter, open_reader
from pipeline.rosbag.messages import stamp_of
from tests.fixtures.capture_site import write_capture_site


def exported(root: Path, fmt: str = "mcap") -> tuple[Path, Path]:
    """(capture directory, folder of bags) of the tiny generated site."""
    from pipeline.rosbag.export import run_export_bag

    site = write_capture_site(root / "site")
    bags = run_export_bag(load_config("demo"), inputs={"site": site}, outputs={"out": root / f"bags_{fmt}"},
                          fmt=fmt, progress=False)
    return site, bags


def rewrite(src: Path, dst: Path, edit, fmt: str = "mcap", extra_topics: dict | None = None,
            drop_topics: tuple[str, ...] = ()) -> Path:
    """Copy bag `src` to `dst`, passing every message through edit(topic, msg, bag_time, writer): it returns
    a list of (topic, msg, bag_time) to write instead (empty drops the message). `extra_topics` (name -> type)
    are added; `drop_topics` are left out altogether (no connection; what edit returns for them is not written)."""
    with open_reader(src) as reader:
        items = [(c.topic, c.msgtype, t * 1e-9, reader.deserialize(raw, c.msgtype))
                 for c, t, raw in reader.messages()]
        types = {c.topic: c.msgtype for c in reader.connections}
    types.update(extra_topics or {})
    for topic in drop_topics:
        types.pop(topic, None)
    Path(dst).parent.mkdir(parents=True, exist_ok=True)
    with BagWriter(dst, fmt) as w:
        for topic, typename in types.items():
            w.topic(topic, typename, latched=topic in ("/tf_static", "/map"))
        for topic, _, t, msg in items:
            for topic2, msg2, t2 in edit(topic, msg, t, w):
                if topic2 not in drop_topics:
                    w.write(topic2, t2, msg2)
    return dst


def keep(topic, msg, t, w):
    return [(topic, msg, t)]


def header_stamps(path: Path, topic: str) -> list[float]:
    """header.stamp (s) of every message of `topic`, in bag order."""
    with open_reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [stamp_of(reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages(connections=conns)]


def restamped(msg, w, dt: float):
    """`msg` with its header stamp moved by dt seconds."""
    h = msg.header
    return dataclasses.replace(msg, header=dataclasses.replace(h, stamp=w.msgs.time(stamp_of(msg) + dt)))


def truncated(src: Path, dst: Path, fraction: float = 0.5) -> Path:
    """A copy of bag `src` (a file, or a ROS 2 folder whose storage file is cut) cut at `fraction` of its bytes."""
    src, dst = Path(src), Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        shutil.copytree(src, dst)
        files = [p for p in dst.iterdir() if p.suffix in (".mcap", ".db3")]
        assert len(files) == 1, files
        target = files[0]
    else:
        shutil.copyfile(src, dst)
        target = dst
    data = target.read_bytes()
    target.write_bytes(data[: int(len(data) * fraction)])
    return dst
