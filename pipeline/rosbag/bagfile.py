"""Opening recordings for reading and writing, whatever their format, with clear errors.

Reading goes through `rosbags.highlevel.AnyReader`: a ROS 1 `.bag` file, a ROS 2 bag directory
(metadata.yaml + sqlite3 or mcap storage) or a bare `.db3` / `.mcap` file. Writing makes a ROS 2 bag
directory (`mcap` or `db3` storage, as `ros2 bag record -s mcap` does) or a ROS 1 `.bag` file.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from pipeline.errors import InputError, Problem
from pipeline.rosbag.messages import FORMATS, Messages

BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def is_bag(path: Path) -> bool:
    path = Path(path)
    return (path.is_file() and path.suffix in BAG_SUFFIXES) or (path.is_dir() and (path / "metadata.yaml").is_file())


def find_bags(paths: list[Path]) -> list[Path]:
    """The recordings named: bags themselves, or folders holding bags (one level down), sorted by name."""
    out: list[Path] = []
    for p in map(Path, paths):
        if is_bag(p):
            out.append(p)
        elif p.is_dir():
            inside = sorted(q for q in p.iterdir() if is_bag(q))
            if not inside:
                raise InputError(f"{p}: no recordings", [Problem(
                    str(p), "holds no .bag, .mcap, .db3 or ROS 2 bag folder", fix="pass a bag or a folder of bags")])
            out.extend(inside)
        else:
            fix = "pass a ROS 1 .bag, a ROS 2 bag folder (with metadata.yaml), or a .mcap / .db3 file"
            what = "does not exist" if not p.exists() else "is not a recording"
            raise InputError(f"{p}: not a recording", [Problem(str(p), what, fix=fix)])
    names = [bag_name(p) for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError("recordings share a name", [Problem(str(p), f"two recordings are named '{bag_name(p)}'",
                                                             fix="rename one; the name becomes the run's name")
                                                     for p in out if bag_name(p) in dup])
    return out


def bag_name(path: Path) -> str:
    """The recording's name: its file or folder name without the suffix."""
    path = Path(path)
    return path.stem if path.is_file() else path.name


@contextlib.contextmanager
def open_reader(path: Path) -> Iterator:
    """An open AnyReader; unreadable or truncated recordings raise InputError naming the file."""
    from rosbags.highlevel import AnyReader

    from pipeline.rosbag.messages import typestore

    path = Path(path)
    store = typestore("ros1" if path.suffix == ".bag" else "ros2")
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated types for damaged files
        raise InputError(f"{path}: cannot read the recording", [
            Problem(str(path), f"unreadable or truncated: {type(exc).__name__}: {exc}",
                    fix="check the file is complete (re-copy it; `ros2 bag reindex` / `rosbag reindex` repair "
                        "an unclosed bag)")]) from None
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def messages(reader, path: Path, connections=None) -> Iterator:
    """reader.messages(connections), with storage that breaks off while reading (a truncated or damaged
    file that still opened) raised as an InputError naming the file, not the storage library's error."""
    it = iter(reader.messages() if connections is None else reader.messages(connections=connections))
    n = 0
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as exc:  # apsw / sqlite3 / mcap / lz4 errors: all mean the same to the user
            raise InputError(f"{path}: cannot read the recording", [
                Problem(str(path), f"unreadable or truncated after {n} messages: {type(exc).__name__}: {exc}",
                        fix="check the file is complete (re-copy it; `ros2 bag reindex` / `rosbag reindex` "
                            "repair an unclosed bag)")]) from None
        n += 1
        yield item


class BagWriter:
    """Writes one recording; topics are added once, messages in any order: they are written sorted by time.

    With `ordered=True` the caller writes in time order (each message at a bag time no earlier than the last)
    and every message goes to the file at once: memory stays bounded however long the recording.
    """

    def __init__(self, path: Path, fmt: str, *, ordered: bool = False):
        if fmt not in FORMATS:
            raise ValueError(f"format must be one of {FORMATS}")
        self.path, self.fmt = Path(path), fmt
        self.ordered = ordered
        self._last_ns = -1
        self.msgs = Messages.for_format(fmt)
        self.conns: dict[str, object] = {}
        self.counts: dict[str, int] = {}
        self._pending: list[tuple[int, int, str, bytes]] = []

    def __enter__(self) -> BagWriter:
        if self.fmt == "bag":
            from rosbags.rosbag1 import Writer

            self.writer = Writer(self.path)
            self.writer.set_compression(Writer.CompressionFormat.LZ4)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(self.path, version=9, storage_plugin=plugin)
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        try:
            if exc[0] is None:
                # In receive-time order, as a recorder writes: a reader going through the recording in time then
                # meets each (compressed) chunk once.
                for t, _, topic, data in sorted(self._pending, key=lambda m: (m[0], m[1])):
                    self.writer.write(self.conns[topic], t, data)
        finally:
            self._pending = []
            self.writer.close()

    def topic(self, name: str, typename: str, *, latched: bool = False) -> None:
        if self.fmt == "bag":
            conn = self.writer.add_connection(name, typename, typestore=self.msgs.store, latching=int(latched))
        else:
            from rosbags.convert.converter import LATCH  # transient-local QoS, as ros2 bag records /tf_static

            qos = LATCH if latched else ()
            conn = self.writer.add_connection(name, typename, typestore=self.msgs.store, offered_qos_profiles=qos)
        self.conns[name] = conn
        self.counts[name] = 0

    def write(self, topic: str, bag_time: float, msg) -> None:
        from pipeline.rosbag.messages import ns

        t = ns(bag_time)
        if self.ordered:
            if t < self._last_ns:
                raise ValueError(f"{topic}: bag time {bag_time:.6f} s is before the last message's "
                                 f"({self._last_ns * 1e-9:.6f} s); an ordered BagWriter takes messages in time order")
            self.writer.write(self.conns[topic], t, self.msgs.serialize(msg))
            self._last_ns = t
        else:
            self._pending.append((t, len(self._pending), topic, self.msgs.serialize(msg)))
        self.counts[topic] += 1
