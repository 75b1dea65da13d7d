"""A rosbag2 writer for recording a live graph: messages go in already serialized, the bag splits by size
or duration into files of one bag (ros2 bag's `<name>_<k>.mcap` layout, one metadata.yaml), and
`flush()` puts everything so far on disk in a form `recover()` can read back after a crash.

The open split lives in `<bag>/.open/<name>_<k>/` (a plain rosbags bag); closing it moves its file into
`<bag>/` and merges its metadata into `<bag>/metadata.yaml`, so the bag directory is always a valid bag
of the closed splits. A recorder killed mid-split leaves `.open/`, which `recover()` finishes.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from rosbags.interfaces import Qos
from rosbags.rosbag2 import Reader, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

from .reader import BagError, typestore

STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
COMPRESSIONS = ("none", "zstd")
OPEN_DIR = ".open"
MCAP_MAGIC = b"\x89MCAP0\r\n"
VERSION = 9
ROS_DISTRO = "jazzy"  # what rosbag2 writes into metadata.yaml (rosbags writes its own name)


@dataclass
class TopicSpec:
    name: str
    msgtype: str
    qos: list[Qos] = field(default_factory=list)
    msgdef: str = ""
    digest: str = ""


def definition(msgtype: str) -> tuple[str, str]:
    """(message definition, RIHS01 hash) of a type: Jazzy's standard types, or the .msg files of the
    installed interface package (ament index) for the rest."""
    store = typestore()
    if msgtype not in store.types:
        _register_installed(msgtype)
    try:
        msgdef, _ = store.generate_msgdef(msgtype, ros_version=2)
        return msgdef, store.hash_rihs01(msgtype)
    except Exception as exc:  # noqa: BLE001 - e.g. a nested type that is not known either
        raise BagError(f"no complete message definition for {msgtype}: {exc}") from None


def _register_installed(msgtype: str) -> None:
    from rosbags.typesys import get_types_from_msg

    package, kind, name = msgtype.split("/")
    try:
        from ament_index_python.packages import get_package_share_directory

        text = (Path(get_package_share_directory(package)) / kind / f"{name}.msg").read_text()
    except Exception as exc:  # noqa: BLE001 - any failure means: no definition available
        raise BagError(f"no message definition for {msgtype} (not a Jazzy standard type, and {exc})") from None
    typestore().register(get_types_from_msg(text, msgtype))


class BagWriter:
    """Not thread-safe: call from one thread (the recorder's executor)."""

    def __init__(self, path: str | Path, storage: str = "mcap", compression: str | None = None,
                 max_bytes: int = 0, max_duration_s: float = 0.0) -> None:
        if storage not in STORAGES:
            raise BagError(f"storage must be one of {', '.join(STORAGES)}, not {storage!r}")
        if compression is None:  # zstd chunks by default (a tenth of the size); sqlite3 has no compression
            compression = "zstd" if storage == "mcap" else "none"
        if compression not in COMPRESSIONS:
            raise BagError(f"compression must be one of {', '.join(COMPRESSIONS)}, not {compression!r}")
        if compression != "none" and storage != "mcap":
            raise BagError("compression needs the mcap storage")
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path} exists already; a recording never overwrites one")
        self.path.mkdir(parents=True)
        self.storage, self.compression = storage, compression
        self.max_bytes, self.max_duration_ns = int(max_bytes), int(max_duration_s * 1e9)
        self.topics: dict[str, TopicSpec] = {}
        self.counts: dict[str, int] = {}
        self.splits_closed = 0
        self._writer: Writer | None = None
        self._connections: dict = {}
        self._split_bytes = 0
        self._split_start_ns: int | None = None

    # ------------------------------------------------------------------ writing
    def add_topic(self, name: str, msgtype: str, qos: list[Qos] | tuple = ()) -> None:
        """Register a topic; raises BagError if its type has no known definition."""
        if name in self.topics:
            return
        msgdef, digest = definition(msgtype)
        self.topics[name] = TopicSpec(name, msgtype, list(qos), msgdef, digest)
        self.counts[name] = 0

    def write(self, topic: str, timestamp_ns: int, data: bytes | memoryview) -> None:
        if self._writer is not None and self._split_due(timestamp_ns):
            self._close_split()
        if self._writer is None:
            self._open_split(timestamp_ns)
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._connections[topic] = self._connect(self._writer, self.topics[topic])
        self._writer.write(connection, timestamp_ns, data)
        self._split_bytes += len(data)
        self.counts[topic] += 1

    def flush(self) -> None:
        """Everything written so far reaches the disk (closes the MCAP chunk / commits the transaction)."""
        if self._writer is None:
            return
        storage = self._writer.storage
        if self.storage == "mcap":
            if storage.chunk.bio.tell():
                storage.close_chunk()
            storage.bio.flush()
            os.fsync(storage.bio.fileno())
        else:
            storage.conn.commit()

    def close(self) -> None:
        if self._writer is not None:
            self._close_split()
        if not (self.path / "metadata.yaml").exists():  # nothing recorded: still a valid, empty bag
            _write_metadata(self.path / "metadata.yaml", _empty_metadata(self.storage))
        recover(self.path)  # a split whose adoption was interrupted (Ctrl-C in the middle) is finished here

    # ------------------------------------------------------------------ splits
    def _split_due(self, timestamp_ns: int) -> bool:
        if self.max_bytes and self._split_bytes >= self.max_bytes:
            return True
        return bool(self.max_duration_ns and timestamp_ns - self._split_start_ns >= self.max_duration_ns)

    def _open_split(self, timestamp_ns: int) -> None:
        split_dir = self.path / OPEN_DIR / f"{self.path.name}_{self.splits_closed}"
        writer = Writer(split_dir, version=VERSION, storage_plugin=STORAGES[self.storage])
        if self.compression == "zstd":
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        writer.open()
        self._writer, self._connections = writer, {}
        self._split_bytes, self._split_start_ns = 0, timestamp_ns

    def _connect(self, writer: Writer, spec: TopicSpec):
        return writer.add_connection(spec.name, spec.msgtype, msgdef=spec.msgdef, rihs01=spec.digest,
                                     offered_qos_profiles=spec.qos)

    def _close_split(self) -> None:
        writer, self._writer = self._writer, None
        writer.close()
        _adopt_split(self.path, writer.path)
        self.splits_closed += 1


# ---------------------------------------------------------------------- metadata
def _info(path: Path) -> dict:
    return yaml.safe_load(path.read_text())["rosbag2_bagfile_information"]


def _write_metadata(path: Path, info: dict) -> None:
    tmp = path.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
    os.replace(tmp, path)


def _empty_metadata(storage: str) -> dict:
    return {"version": VERSION, "storage_identifier": storage, "relative_file_paths": [],
            "duration": {"nanoseconds": 0}, "starting_time": {"nanoseconds_since_epoch": 0},
            "message_count": 0, "topics_with_message_count": [], "compression_format": "",
            "compression_mode": "", "files": [], "custom_data": None, "ros_distro": ROS_DISTRO}


def merge_infos(infos: list[dict]) -> dict:
    """One bag's metadata from that of its parts (closed splits, or bags of closed splits)."""
    merged = _empty_metadata(infos[0]["storage_identifier"]) if infos else _empty_metadata("mcap")
    topics: dict[tuple[str, str], dict] = {}
    starts, ends = [], []
    for info in infos:
        if not info["message_count"]:
            continue
        start = info["starting_time"]["nanoseconds_since_epoch"]
        starts.append(start)
        ends.append(start + info["duration"]["nanoseconds"])
        merged["message_count"] += info["message_count"]
        merged["relative_file_paths"] += info["relative_file_paths"]
        merged["files"] += info["files"]
        for topic in info["topics_with_message_count"]:
            key = (topic["topic_metadata"]["name"], topic["topic_metadata"]["type"])
            if key in topics:
                topics[key]["message_count"] += topic["message_count"]
            else:
                topics[key] = {"topic_metadata": dict(topic["topic_metadata"]), "message_count": topic["message_count"]}
    if starts:
        merged["starting_time"] = {"nanoseconds_since_epoch": min(starts)}
        merged["duration"] = {"nanoseconds": max(ends) - min(starts)}
    merged["topics_with_message_count"] = list(topics.values())
    return merged


def _adopt_split(bag: Path, split_dir: Path) -> None:
    """Move a closed split's file into the bag and merge its metadata into the bag's. Safe to repeat
    after an interruption: the move is skipped once done, and a file already listed is not added twice."""
    split = _info(split_dir / "metadata.yaml")
    (file_name,) = split["relative_file_paths"]
    if (split_dir / file_name).exists():
        os.replace(split_dir / file_name, bag / file_name)
    target = bag / "metadata.yaml"
    current = [_info(target)] if target.exists() else []
    if not any(file_name in info["relative_file_paths"] for info in current):
        _write_metadata(target, merge_infos(current + [split]))
    shutil.rmtree(split_dir)


# ---------------------------------------------------------------------- recovery
def recover(bag: str | Path) -> list[str]:
    """Finish a bag whose recorder died: every split left open is cut after its last complete record
    (what the last flush() wrote), rewritten as a closed split and merged into the bag. Returns what
    was recovered, one line per split; an already closed bag is left as it is."""
    bag = Path(bag)
    open_dir = bag / OPEN_DIR
    if not bag.is_dir():
        raise BagError(f"{bag} is not a bag directory")
    done = []
    recovered_dir = open_dir / ".recovered"
    leftovers = [d for d in (recovered_dir, open_dir) if d.is_dir()]
    for split_dir in [s for d in leftovers for s in sorted(d.iterdir()) if s != recovered_dir]:
        if (split_dir / "metadata.yaml").exists():  # closed but its adoption was interrupted
            _adopt_split(bag, split_dir)
            done.append(f"{split_dir.name}: closed split adopted")
            continue
        files = [f for f in split_dir.iterdir() if f.suffix in (".mcap", ".db3")]
        if files:
            compression = "none"
            if files[0].suffix == ".mcap":
                compression = _mcap_compression(files[0])
                _terminate_mcap(files[0])
            count = _rewrite(files[0], recovered_dir / split_dir.name, compression)
            done.append(f"{split_dir.name}: {count} messages recovered")
        shutil.rmtree(split_dir)
        if files:
            _adopt_split(bag, recovered_dir / split_dir.name)
    shutil.rmtree(open_dir, ignore_errors=True)
    if not (bag / "metadata.yaml").exists():
        raise BagError(f"{bag} has neither metadata.yaml nor an open split: not a bag")
    return done


def _terminate_mcap(path: Path) -> None:
    """Cut an unfinished MCAP file after its last complete record and end it with a footer without a
    summary (readers then scan it), as a closed file would be."""
    size = path.stat().st_size
    with path.open("r+b") as f:
        if f.read(8) != MCAP_MAGIC:
            raise BagError(f"{path} is not an MCAP file")
        good = 8
        while good + 9 <= size:
            f.seek(good)
            op, length = f.read(1)[0], int.from_bytes(f.read(8), "little")
            if op in (0x0F, 0x02) or good + 9 + length > size:  # data end / footer, or a cut record
                break
            good += 9 + length
        f.truncate(good)
        f.seek(good)
        f.write(b"\x0f" + (4).to_bytes(8, "little") + (0).to_bytes(4, "little"))  # DataEnd, no CRC
        f.write(b"\x02" + (20).to_bytes(8, "little") + bytes(20))  # Footer: no summary
        f.write(MCAP_MAGIC)


def _mcap_compression(path: Path) -> str:
    """The compression of an MCAP file's first chunk ("zstd", or "none" when it has no compressed chunk):
    what the recovered split is written with, so recovering a zstd bag does not make it ten times larger."""
    with path.open("rb") as f:
        data = f.read(1 << 20)
    at = len(MCAP_MAGIC)
    while at + 9 <= len(data):
        op, length = data[at], int.from_bytes(data[at + 1:at + 9], "little")
        if op == 0x06 and at + 9 + 32 <= len(data):  # Chunk: start, end, size (u64 each), crc (u32), compression
            size = int.from_bytes(data[at + 37:at + 41], "little")
            name = data[at + 41:at + 41 + size].decode(errors="replace")
            return name if name in COMPRESSIONS else "none"
        at += 9 + length
    return "none"


def _rewrite(raw: Path, target: Path, compression: str = "none") -> int:
    """Copy every message of a storage file into a new closed split at `target`."""
    count = 0
    storage = "mcap" if raw.suffix == ".mcap" else "sqlite3"
    with Reader(raw) as reader:
        writer = Writer(target, version=VERSION, storage_plugin=STORAGES[storage])
        if compression == "zstd":
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        writer.open()
        connections = {}
        for c in reader.connections:
            msgdef, digest = c.msgdef.data, c.digest
            if not msgdef or not digest:
                msgdef, digest = definition(c.msgtype)
            connections[c.id] = writer.add_connection(c.topic, c.msgtype, msgdef=msgdef, rihs01=digest,
                                                      offered_qos_profiles=c.ext.offered_qos_profiles)
        for connection, timestamp, data in reader.messages():
            writer.write(connections[connection.id], timestamp, data)
            count += 1
        writer.close()
    return count
