"""What a recording holds, the way `ros2 bag info` shows it, plus the role siteloc would give each topic."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.rosbag.bagfile import bag_name, messages, open_reader
from pipeline.rosbag.read import ROLE_TYPES, TF_TYPES


def inventory(path: Path) -> dict:
    """Topics with type, count, rate (Hz, from receive times) and role; the time span; the storage."""
    path = Path(path)
    with open_reader(path) as reader:
        stamps: dict[str, list[int]] = {c.topic: [] for c in reader.connections}
        for conn, t, _ in messages(reader, path):
            stamps[conn.topic].append(t)
        types = {c.topic: c.msgtype for c in reader.connections}
        start, end = reader.start_time, reader.end_time
    topics = {}
    for topic in sorted(types):
        t = np.asarray(stamps[topic], dtype=np.int64)
        span = (t.max() - t.min()) * 1e-9 if len(t) > 1 else 0.0
        role = next((r for r, tys in ROLE_TYPES.items() if types[topic] in tys), None)
        if topic in ("/tf", "/tf_static") and types[topic] in TF_TYPES:
            role = topic.strip("/")
        topics[topic] = {"type": types[topic], "count": int(len(t)),
                         "rate_hz": round((len(t) - 1) / span, 2) if span > 0 else None, "role": role}
    storage = "ros1 bag" if path.suffix == ".bag" else ("ros2 " + (path.suffix.lstrip(".") if path.is_file() else
                                                                    _dir_storage(path)))
    return {"name": bag_name(path), "path": str(path), "storage": storage,
            "start_s": start * 1e-9 if start else None, "duration_s": round((end - start) * 1e-9, 3) if end else 0.0,
            "messages": sum(v["count"] for v in topics.values()), "topics": topics}


def _dir_storage(path: Path) -> str:
    return "mcap" if any(path.glob("*.mcap")) else "sqlite3" if any(path.glob("*.db3")) else "?"
