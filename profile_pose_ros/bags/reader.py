"""Reading rosbag2 bags (MCAP or sqlite3, one or several files) in time order, with what a player needs
per topic: its type and the QoS its publishers offered."""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from rosbags.interfaces import Qos


class BagError(Exception):
    """A bag that cannot be written, read or recovered, with the reason."""


@functools.lru_cache(maxsize=1)
def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int
    qos: tuple[Qos, ...]


@dataclass(frozen=True)
class BagInfo:
    path: Path
    storage: str
    files: tuple[str, ...]
    start_ns: int
    duration_ns: int
    message_count: int
    topics: dict[str, TopicInfo]

    def table(self) -> str:
        lines = [f"bag:       {self.path}", f"storage:   {self.storage} ({len(self.files)} file(s))",
                 f"duration:  {self.duration_ns * 1e-9:.3f} s", f"messages:  {self.message_count}", "topics:"]
        lines += [f"  {t.name:<32} {t.msgtype:<40} {t.count:>9}" for t in self.topics.values()]
        return "\n".join(lines)


def _open(path: Path):
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    if (path / ".open").is_dir():
        raise BagError(f"{path} was not closed (its recorder was killed?): run `profile_pose_bag recover {path}`")
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, FileNotFoundError) as exc:
        raise BagError(f"cannot read {path}: {exc}") from None
    return reader


def bag_info(path: str | Path) -> BagInfo:
    path = Path(path)
    reader = _open(path)
    try:
        topics: dict[str, TopicInfo] = {}
        for c in reader.connections:
            old = topics.get(c.topic)
            count = c.msgcount + (old.count if old else 0)
            topics[c.topic] = TopicInfo(c.topic, c.msgtype, count, tuple(c.ext.offered_qos_profiles))
        files = _files(path)
        storage = "mcap" if any(f.endswith(".mcap") for f in files) else "sqlite3"
        return BagInfo(path, storage, files, reader.start_time if reader.message_count
                       else 0, reader.duration, reader.message_count, topics)
    finally:
        reader.close()


def _files(path: Path) -> tuple[str, ...]:
    return tuple(sorted(f.name for f in path.iterdir() if f.suffix in (".mcap", ".db3")))



def read_messages(path: str | Path, topics: Iterable[str] | None = None, start_ns: int | None = None
                  ) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, receive time ns, serialized message) in receive-time order; `topics` filters."""
    path = Path(path)
    reader = _open(path)
    try:
        wanted = set(topics) if topics is not None else None
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not connections:
            return
        for connection, timestamp, data in reader.messages(connections=connections, start=start_ns):
            yield connection.topic, connection.msgtype, timestamp, bytes(data)
    finally:
        reader.close()
