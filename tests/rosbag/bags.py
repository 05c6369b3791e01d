"""Bag fixtures: the tiny capture site exported, and a rewriter that breaks or edits one thing of a bag."""

from __future__ import annotations

from pathlib import Path

from pipeline.config import load_config
from pipeline.rosbag.bagfile import BagWriter, open_reader
from tests.fixtures.capture_site import write_capture_site


def exported(root: Path, fmt: str = "mcap") -> tuple[Path, Path]:
    """(capture directory, folder of bags) of the tiny generated site."""
    from pipeline.rosbag.export import run_export_bag

    site = write_capture_site(root / "site")
    bags = run_export_bag(load_config("demo"), inputs={"site": site}, outputs={"out": root / f"bags_{fmt}"},
                          fmt=fmt, progress=False)
    return site, bags


def rewrite(src: Path, dst: Path, edit, fmt: str = "mcap", extra_topics: dict | None = None) -> Path:
    """Copy bag `src` to `dst`, passing every message through edit(topic, msg, bag_time, writer): it returns
    a list of (topic, msg, bag_time) to write instead (empty drops the message)."""
    with open_reader(src) as reader:
        items = [(c.topic, c.msgtype, t * 1e-9, reader.deserialize(raw, c.msgtype))
                 for c, t, raw in reader.messages()]
        types = {c.topic: c.msgtype for c in reader.connections}
    types.update(extra_topics or {})
    with BagWriter(dst, fmt) as w:
        for topic, typename in types.items():
            w.topic(topic, typename, latched=topic in ("/tf_static", "/map"))
        for topic, _, t, msg in items:
            for topic2, msg2, t2 in edit(topic, msg, t, w):
                w.write(topic2, t2, msg2)
    return dst


def keep(topic, msg, t, w):
    return [(topic, msg, t)]
