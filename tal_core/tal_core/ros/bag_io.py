"""rosbag2-layout MCAP bags: write and read them without the ros2 command line.

A bag is a folder with ``metadata.yaml`` (rosbag2's bag information, version 9 as Jazzy writes it) and
one ``<folder name>_0.mcap`` file. Each topic has a channel with ``cdr`` message encoding and a schema
with ``ros2msg`` encoding whose data is the message definition followed by those of every nested type
(each after a line of 80 ``=`` and ``MSG: pkg/msg/Type``), the way rosbag2's MCAP storage writes them.
Messages are serialised with rclpy (the same CDR bytes rosbag2 stores); ``log_time`` is the receive
time [ns] and ``publish_time`` the header stamp when there is one.

Reading streams the file record by record, so memory stays flat in the length of the bag and a
truncated file (a recorder killed with SIGKILL) yields every message before the damage, then reports
how much it could read. rclpy and the interface packages are imported lazily (reading raw records
needs neither).
"""

from __future__ import annotations

import hashlib
import logging
import re
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.exceptions import McapError
from mcap.reader import StreamReader, breakup_chunk
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.writer import CompressionType, Writer

from tal_core.errors import InputError

LOG = logging.getLogger(__name__)
METADATA_FILE = "metadata.yaml"
ROSBAG2_VERSION = 9
SEPARATOR = "=" * 80
PRIMITIVE_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "string", "wstring"})


class BagError(InputError):
    """A bag that cannot be written or read as asked (the message says what and how much was read)."""


# -- message definitions ------------------------------------------------------------------------------------
def _msg_file(type_name: str) -> Path:
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    package, _, name = _split_type(type_name)
    try:
        share = Path(get_package_share_directory(package))
    except PackageNotFoundError as exc:
        raise BagError(f"message type {type_name}: package '{package}' is not installed") from exc
    path = share / "msg" / f"{name}.msg"
    if not path.is_file():
        raise BagError(f"message type {type_name}: no definition at {path}")
    return path


def _split_type(type_name: str) -> tuple[str, str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> (pkg, 'msg', Type)."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], "msg", parts[2]
    if len(parts) == 2:
        return parts[0], "msg", parts[1]
    raise BagError(f"message type '{type_name}' is not of the form pkg/msg/Type")


def _nested_types(text: str, package: str) -> list[str]:
    """The non-primitive field types of a .msg text, as full 'pkg/msg/Type' names, in order."""
    found = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 2 or "=" in tokens[1]:
            continue  # a constant (NAME=value)
        field_type = tokens[0]
        base = re.sub(r"\[.*\]$", "", field_type)
        base = re.sub(r"<=\d+$", "", base)
        if base in PRIMITIVE_TYPES or base.startswith("string<=") or base.startswith("wstring<="):
            continue
        if "/" not in base:
            base = "std_msgs/Header" if base == "Header" else f"{package}/{base}"
        pkg, _, name = _split_type(base)
        found.append(f"{pkg}/msg/{name}")
    return found


def message_definition(type_name: str) -> str:
    """The ros2msg schema text of ``type_name``: its .msg file, then every nested type's, depth first."""
    package, _, name = _split_type(type_name)
    root = f"{package}/msg/{name}"
    text = _msg_file(root).read_text()
    parts = [text.rstrip("\n")]
    seen = {root}
    queue = _nested_types(text, package)
    while queue:
        nested = queue.pop(0)
        if nested in seen:
            continue
        seen.add(nested)
        nested_text = _msg_file(nested).read_text()
        parts.append(f"{SEPARATOR}\nMSG: {nested}\n{nested_text.rstrip(chr(10))}")
        queue.extend(_nested_types(nested_text, nested.split("/")[0]))
    return "\n".join(parts) + "\n"


def message_class(type_name: str) -> Any:
    """The rclpy message class of 'pkg/msg/Type'; BagError if it is not installed."""
    import importlib

    package, _, name = _split_type(type_name)
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (AttributeError, ImportError) as exc:
        raise BagError(f"message type {type_name} is not installed: {exc}") from exc


def type_name_of(msg: Any) -> str:
    """'pkg/msg/Type' of an rclpy message instance."""
    module = type(msg).__module__.split(".")
    return f"{module[0]}/msg/{type(msg).__name__}"


def exact_cdr(message: Any) -> bytes:
    """The CDR bytes of an rclpy message, exactly as a publisher sends them.

    rclpy's serialize_message (with rmw_fastrtps) returns the *estimated* size, which for types with
    sequences can end in up to 8 bytes of stale memory. ROS 2 subscribers ignore them; strict readers
    (rosbags) reject the message. The true length is the shortest prefix that still deserialises.
    """
    from rclpy.serialization import deserialize_message, serialize_message

    data = serialize_message(message)
    cls = type(message)
    for length in range(max(4, len(data) - 8), len(data)):
        try:
            deserialize_message(data[:length], cls)
        except Exception:  # noqa: BLE001 (too short: FastCDR raises its "not enough memory" error)
            continue
        return data[:length]
    return data


def _stamp_ns(msg: Any) -> int | None:
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# -- writing ------------------------------------------------------------------------------------------------
@dataclass
class _TopicState:
    name: str
    type_name: str
    channel_id: int
    count: int = 0
    qos: str = ""


class BagWriter:
    """Writes a rosbag2 MCAP bag folder. Use as a context manager or call ``close()``.

    ``compression``: zstd (default), lz4 or none, per chunk; ``chunk_size`` [bytes]: a chunk is written
    once this much is buffered; ``flush()`` writes the chunk in progress (the recorder calls it every
    second so that a SIGKILL loses at most that much).
    """

    def __init__(self, path: str | Path, *, compression: str = "zstd", chunk_size: int = 1 << 20) -> None:
        self.path = Path(path)
        if self.path.exists() and any(self.path.iterdir()):
            raise BagError(f"bag folder {self.path} exists and is not empty")
        kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in kinds:
            raise BagError(f"compression must be one of {sorted(kinds)}, got {compression!r}")
        self.path.mkdir(parents=True, exist_ok=True)
        self.mcap_name = f"{self.path.name}_0.mcap"
        self._file = open(self.path / self.mcap_name, "wb")  # noqa: SIM115 (closed in close())
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=kinds[compression])
        self._writer.start(profile="ros2", library="tal_core.ros.bag_io")
        self.compression = compression
        self._topics: dict[str, _TopicState] = {}
        self._schemas: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._closed = False

    def add_topic(self, topic: str, type_name: str, qos: str = "", definition: str | None = None) -> None:
        """Declare ``topic`` with its type 'pkg/msg/Type' (idempotent for the same type). ``definition``:
        the ros2msg schema text when the type is not installed here (raw bytes only)."""
        package, _, name = _split_type(type_name)
        full = f"{package}/msg/{name}"
        known = self._topics.get(topic)
        if known is not None:
            if known.type_name != full:
                raise BagError(f"topic {topic} already has type {known.type_name}, not {full}")
            return
        if full not in self._schemas:
            text = definition if definition is not None else message_definition(full)
            self._schemas[full] = self._writer.register_schema(full, "ros2msg", text.encode())
        channel = self._writer.register_channel(topic, "cdr", self._schemas[full])
        self._topics[topic] = _TopicState(topic, full, channel, qos=qos)

    def write(self, topic: str, message: Any, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one message (an rclpy message, or its CDR bytes for a declared topic)."""
        if self._closed:
            raise BagError(f"bag {self.path} is closed")
        if isinstance(message, (bytes, bytearray, memoryview)):
            if topic not in self._topics:
                raise BagError(f"raw bytes for undeclared topic {topic}: call add_topic first")
            data = bytes(message)
        else:
            self.add_topic(topic, type_name_of(message))
            data = exact_cdr(message)
            if publish_time_ns is None:
                publish_time_ns = _stamp_ns(message)
        state = self._topics[topic]
        log_time_ns = int(log_time_ns)
        self._writer.add_message(state.channel_id, log_time_ns, data,
                                 int(log_time_ns if publish_time_ns is None else publish_time_ns), state.count)
        state.count += 1
        self._first_ns = log_time_ns if self._first_ns is None else min(self._first_ns, log_time_ns)
        self._last_ns = log_time_ns if self._last_ns is None else max(self._last_ns, log_time_ns)

    def flush(self) -> None:
        """Write the chunk in progress and flush the file (everything so far survives a SIGKILL)."""
        if not self._closed:
            self._writer.flush()

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    @property
    def message_counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return {t.name: t.count for t in self._topics.values()}

    def close(self) -> None:
        """Finish the MCAP file (summary and index) and write metadata.yaml."""
        if self._closed:
            return
        self._writer.finish()
        self._file.close()
        self._closed = True
        write_metadata(self.path, [(t.name, t.type_name, t.count, t.qos) for t in self._topics.values()],
                       self._first_ns, self._last_ns, [self.mcap_name], self.compression)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_metadata(path: Path, topics: list[tuple[str, str, int, str]], first_ns: int | None,
                   last_ns: int | None, files: list[str], compression: str = "zstd") -> None:
    """rosbag2's metadata.yaml (version 9) for the bag folder ``path``."""
    start = int(first_ns or 0)
    duration = int((last_ns or start) - start)
    count = sum(t[2] for t in topics)
    info = {
        "version": ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": name, "type": type_name, "serialization_format": "cdr",
                                "offered_qos_profiles": qos, "type_description_hash": ""},
             "message_count": n} for name, type_name, n, qos in topics],
        # Compression is MCAP's own (per chunk), so rosbag2 sees an uncompressed storage.
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": files,
        "files": [{"path": f, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": count} for f in files],
        "custom_data": {"writer": "tal_core.ros.bag_io", "mcap_chunk_compression": compression},
        "ros_distro": "jazzy",
    }
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
    (path / METADATA_FILE).write_text(text)


# -- reading ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BagMessage:
    """One message: topic, type 'pkg/msg/Type', log_time [ns] (receive), publish_time [ns], CDR data, and
    the decoded rclpy message (None when reading raw)."""

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    message: Any = None


@dataclass
class ReadReport:
    """What a read got: messages per topic, whether the file ended cleanly, and why not."""

    counts: dict[str, int] = field(default_factory=dict)
    complete: bool = False
    error: str = ""
    skipped_types: set[str] = field(default_factory=set)

    @property
    def total(self) -> int:
        return sum(self.counts.values())


class BagReader:
    """Reads a bag folder (or a bare .mcap file) record by record.

    ``messages()`` yields BagMessage in file order; with ``decode=True`` each is deserialised with rclpy
    (unknown types are skipped with one warning per type). A truncated or corrupt file yields everything
    before the damage; ``report`` then says how much was read and ``strict=True`` raises BagError at the
    end instead.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            self.metadata = self._read_metadata()
            files = self.metadata.get("relative_file_paths") if self.metadata else None
            mcaps = [self.path / f for f in files] if files else sorted(self.path.glob("*.mcap"))
        elif self.path.is_file():
            self.metadata = None
            mcaps = [self.path]
        else:
            raise BagError(f"no bag at {self.path}")
        if not mcaps or not all(p.is_file() for p in mcaps):
            raise BagError(f"bag {self.path}: no MCAP file found ({[str(p) for p in mcaps]})")
        self.files = mcaps
        self.report = ReadReport()
        self._classes: dict[str, Any] = {}   # decode(): message classes by type name

    def _read_metadata(self) -> dict | None:
        meta = self.path / METADATA_FILE
        if not meta.is_file():
            return None  # a recorder killed before closing: read the MCAP file alone
        try:
            return yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        except (yaml.YAMLError, KeyError, TypeError) as exc:
            raise BagError(f"{meta}: not a rosbag2 metadata file ({exc})") from exc

    def topics(self) -> dict[str, str]:
        """Topic -> type from the file's channels and schemas (reads the records, not the metadata)."""
        types: dict[str, str] = {}
        for msg in self.messages(decode=False):
            types.setdefault(msg.topic, msg.type_name)
        return types

    def messages(self, topics: Iterable[str] | None = None, *, decode: bool = True, strict: bool = False,
                 start_ns: int | None = None, end_ns: int | None = None) -> Iterator[BagMessage]:
        wanted = set(topics) if topics is not None else None
        self.report = ReadReport()
        classes: dict[str, Any] = {}
        for path in self.files:
            for schema, channel, record in self._records(path):
                if wanted is not None and channel.topic not in wanted:
                    continue
                if start_ns is not None and record.log_time < start_ns:
                    continue
                if end_ns is not None and record.log_time > end_ns:
                    continue
                type_name = schema.name if schema is not None else ""
                decoded = None
                if decode:
                    decoded = self._decode(type_name, record.data, classes)
                    if decoded is None:
                        continue
                self.report.counts[channel.topic] = self.report.counts.get(channel.topic, 0) + 1
                yield BagMessage(channel.topic, type_name, record.log_time, record.publish_time, record.data, decoded)
        if strict and not self.report.complete:
            raise BagError(self.report.error)

    def decode(self, type_name: str, data: bytes) -> Any:
        """One record's bytes (``messages(decode=False)``) as its rclpy message; None for a type rclpy does not
        know (warned once, in ``report.skipped_types``)."""
        return self._decode(type_name, data, self._classes)

    def _decode(self, type_name: str, data: bytes, classes: dict[str, Any]) -> Any:
        from rclpy.serialization import deserialize_message

        if type_name not in classes:
            try:
                classes[type_name] = message_class(type_name)
            except BagError as exc:
                classes[type_name] = None
                self.report.skipped_types.add(type_name)
                LOG.warning("skipping messages of unknown type %s: %s", type_name, exc)
        cls = classes[type_name]
        return None if cls is None else deserialize_message(data, cls)

    def _records(self, path: Path) -> Iterator[tuple[Schema | None, Channel, Message]]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        count = 0
        with open(path, "rb") as stream:
            reader = StreamReader(stream, skip_magic=False)
            try:
                for record in reader.records:
                    inner = breakup_chunk(record) if isinstance(record, Chunk) else [record]
                    for r in inner:
                        if isinstance(r, Schema):
                            schemas[r.id] = r
                        elif isinstance(r, Channel):
                            channels[r.id] = r
                        elif isinstance(r, Message):
                            channel = channels.get(r.channel_id)
                            if channel is None:
                                raise McapError(f"message on unknown channel {r.channel_id}")
                            count += 1
                            yield schemas.get(channel.schema_id), channel, r
                    if isinstance(record, Footer):
                        self.report.complete = True
            except Exception as exc:  # noqa: BLE001 (mcap raises many types on damaged data)
                # Truncated or corrupt: everything before this point was yielded.
                self.report.complete = False
                self.report.error = (f"{path.name}: truncated or corrupt after {count} messages "
                                     f"({type(exc).__name__}: {exc}); the messages before it were read")
                LOG.warning("%s", self.report.error)
                return
        if not self.report.complete:
            self.report.error = f"{path.name}: ends without an MCAP footer after {count} messages"


def _digest_value(digest: Any, value: Any) -> None:
    """Feed a decoded message value into ``digest`` field by field (padding bytes never enter)."""
    if isinstance(value, np.generic):
        value = value.item()
    if hasattr(value, "get_fields_and_field_types"):
        for name in value.get_fields_and_field_types():
            digest.update(name.encode())
            _digest_value(digest, getattr(value, name))
    elif isinstance(value, str):
        digest.update(value.encode() + b"\0")
    elif isinstance(value, (bytes, bytearray)):
        digest.update(bytes(value))
    elif isinstance(value, (bool, int, float)):
        digest.update(struct.pack("<d", float(value)) if isinstance(value, float) else str(int(value)).encode())
    else:  # sequences and arrays: numpy, array.array, list
        items = list(value)
        digest.update(f"[{len(items)}]".encode())
        for item in items:
            _digest_value(digest, item)


def content_digest(path: str | Path, topics: Iterable[str] | None = None) -> str:
    """SHA-256 over the decoded content of a bag (topic, log time, every field of every message).

    The CDR bytes of two identical messages can differ: FastCDR leaves alignment padding uninitialised. This
    digest is equal for bags with equal content, so it is what tells two dataset runs apart.
    """
    digest = hashlib.sha256()
    for message in BagReader(path).messages(topics, strict=True):
        digest.update(f"{message.topic}@{message.log_time_ns}".encode())
        _digest_value(digest, message.message)
    return digest.hexdigest()
