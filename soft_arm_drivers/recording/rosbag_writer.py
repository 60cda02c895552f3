"""ROS-free rosbag2 writer: MCAP storage, bag metadata version 9 (ROS 2 Jazzy).

The core of the ``recorder`` node: the node subscribes with raw (serialized) callbacks and hands
this writer the CDR bytes of each message, stored as given. (``rclpy.serialization.
serialize_message`` encodes the same content, but with rmw_fastrtps pads it to Fast DDS's size
estimate with uninitialised bytes; raw subscriptions deliver the exact wire bytes.) Nothing here
imports ROS, so it runs and is tested anywhere.

Output
------
``<directory>/metadata.yaml`` and ``<directory>/<directory name>_0.mcap``, the names
``ros2 bag record -s mcap -o <directory>`` uses. All times are integer nanoseconds (since the Unix
epoch, or whatever clock the caller stamps with); sizes are bytes.

Where the layout comes from (rosbag2 sources read, nothing copied):

* ``metadata.yaml``: rosbag2 Jazzy (0.26.x) ``rosbag2_storage/include/rosbag2_storage/yaml.hpp``
  gives the keys and their order under ``rosbag2_bagfile_information``; times are
  ``{nanoseconds: n}`` and ``{nanoseconds_since_epoch: n}``. Version 9 (rosbag2 PR #1476, first
  released in Jazzy) stores ``offered_qos_profiles`` as a YAML *list*, no longer as a string.
  ``rosbag2_storage/src/rosbag2_storage/qos.cpp`` gives the version-9 QoS entries: policies as
  rmw strings (``reliable``, ``keep_last``, ...), durations as ``{sec, nsec}``, rmw's "infinite"
  being ``{sec: 9223372036, nsec: 854775807}``. The ``rosbags`` 0.11 version-9 writer agrees.
* MCAP records: ``rosbag2_storage_mcap/src/mcap_storage.cpp`` and the MCAP ``ros2`` profile
  (foxglove/mcap ``docs/specification/profiles/ros2.md``): profile ``ros2``; one schema per type,
  named ``pkg/msg/Type``, encoding ``ros2msg``; one channel per topic with message encoding
  ``cdr`` and metadata ``offered_qos_profiles`` (the same QoS list as a YAML block string) and
  ``topic_type_hash``; when the bag is closed, a metadata record ``rosbag2`` whose
  ``serialized_metadata`` holds the bag metadata as YAML.
* Message definitions: ``rosbag2_cpp/src/rosbag2_cpp/message_definitions/
  local_message_definition_source.cpp``: the type's ``.msg`` text as installed, then for every
  dependency (sorted by name, depth first, each once) a newline, 80 ``=``, ``MSG: pkg/Type`` and
  that type's text. The texts are the files rosbag2 itself reads:
  ``<prefix>/share/<pkg>/msg/<Type>.msg`` for each prefix in ``AMENT_PREFIX_PATH``, then
  ``sys.prefix`` (where the PyPI ``ros-jazzy-*`` wheels install them). The type hash (RIHS01) comes
  from the rosidl-generated ``<Type>.json`` beside the ``.msg``; it is written as an empty string
  when that file is missing. Types that only have an ``.idl`` (no ``.msg``) are not supported.

Crash safety
------------
Messages are buffered in memory, in the open chunk, until the chunk holds ``chunk_size`` bytes
of message records or :meth:`RosbagWriter.flush` is called. Only then is the chunk written and
the file object flushed, so the data is with the operating system: it survives SIGKILL of this
process, though not a power cut (there is no fsync). Each flush also leaves the MCAP file ending
in a provisional tail (a DataEnd record, then a Footer that announces no summary, then the magic
bytes) and replaces ``metadata.yaml`` atomically (temporary file, then ``os.replace``) so that it
describes exactly what is in the file. The next flush truncates the tail before it writes, so the
file on disk is always a prefix of the bytes meant to be written.

After SIGKILL, the open chunk is lost: at most ``chunk_size`` bytes of messages, or whatever came
since the last :meth:`RosbagWriter.flush`. Everything before it stays readable. There is no MCAP
summary; readers scan the data section instead. In detail:

* Killed between two flushes (nearly always: a flush takes microseconds to milliseconds): the
  MCAP file is complete but has no summary. ``rosbags.rosbag2.Reader`` and ``mcap``'s
  ``make_reader``/``NonSeekingReader`` read it without help (tested). rosbag2's MCAP plugin should
  too, as the C++ MCAP reader scans the data section when a file has no summary (read in its
  source, not tried: there is no ROS install here). ``metadata.yaml`` matches the file, or counts
  one chunk less if the kill fell between the file flush and the replacement of
  ``metadata.yaml``: ``ros2 bag info`` then shows too few messages, but readers still deliver
  every message in the file.
* Killed during a flush (or a flush failed, e.g. disk full): the file ends in a partly written
  record and has no footer. ``mcap``'s ``NonSeekingReader(f, validate_crcs=True)
  .iter_messages(log_time_order=False)`` yields every message of every complete chunk, then
  raises ``mcap.exceptions.EndOfFile`` (``struct.error`` if the cut is in the footer).
  ``rosbags`` refuses the file ("File end magic is invalid"), and so, presumably, does rosbag2's
  scan, which stops with an error at a cut record. :func:`recover` cuts the partial record off,
  appends the provisional tail and rewrites ``metadata.yaml`` from what the file holds; after
  that every reader reads it.

:func:`recover` is safe on any bag this module wrote (on a cleanly closed one it changes nothing),
but must not run while the writing process is still alive.

A :class:`RosbagWriter` is not thread-safe: call it from one thread (a single-threaded executor).
"""
from __future__ import annotations

import operator
import os
import struct
import sys
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import BinaryIO, Iterable, Mapping

import yaml
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, DataEnd, Footer, Header, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from .message_definitions import message_definition, type_description_hash

ROS_DISTRO = "jazzy"
METADATA_VERSION = 9
STORAGE_IDENTIFIER = "mcap"
SERIALIZATION_FORMAT = "cdr"
SCHEMA_ENCODING = "ros2msg"
MCAP_PROFILE = "ros2"
METADATA_FILE = "metadata.yaml"
DEFAULT_CHUNK_SIZE = 768 * 1024  # bytes; the chunk size of rosbag2's MCAP plugin
LIBRARY = f"soft_arm rosbag_writer ({LIBRARY_IDENTIFIER})"

_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4}
_RMW_INFINITE = (9223372036, 854775807)  # RMW_DURATION_INFINITE as (sec, nsec)
_NO_MESSAGES_START = 2**63 - 1  # rosbag2's starting_time of a bag without messages
_MAGIC = b"\x89MCAP0\r\n"
_RECORD_PREFIX = struct.Struct("<BQ")  # opcode, record length
_FOOTER_RECORD = _RECORD_PREFIX.size + 20  # opcode, length, summary start, offset start, crc
_MESSAGE_RECORD_OVERHEAD = _RECORD_PREFIX.size + 2 + 4 + 8 + 8  # channel, sequence, two times
_SEQUENCE_MODULUS = 2**32  # MCAP message sequence numbers are uint32


class UnknownTopicError(LookupError):
    """A message was written to a topic the writer was not opened with."""


class Reliability(str, Enum):
    """QoS reliability policy, by its rmw name."""

    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"
    SYSTEM_DEFAULT = "system_default"
    BEST_AVAILABLE = "best_available"


class Durability(str, Enum):
    """QoS durability policy, by its rmw name."""

    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"
    SYSTEM_DEFAULT = "system_default"
    BEST_AVAILABLE = "best_available"


class History(str, Enum):
    """QoS history policy, by its rmw name."""

    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"
    SYSTEM_DEFAULT = "system_default"


@dataclass(frozen=True)
class QosProfile:
    """The QoS a topic's publisher offered; ``ros2 bag play`` offers it again.

    Policies take the enums or their rmw names (``"best_effort"``); ``depth`` is the history depth
    in messages. Deadline, lifespan and liveliness lease are recorded as infinite and liveliness as
    ``automatic``, what a Jazzy publisher with default QoS offers.
    """

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10

    def __post_init__(self):
        object.__setattr__(self, "reliability", Reliability(self.reliability))
        object.__setattr__(self, "durability", Durability(self.durability))
        object.__setattr__(self, "history", History(self.history))
        if operator.index(self.depth) < 0:
            raise ValueError(f"QoS depth must be >= 0, got {self.depth}")

    def to_metadata(self) -> dict:
        """This profile as one entry of a version-9 ``offered_qos_profiles`` list."""
        infinite = {"sec": _RMW_INFINITE[0], "nsec": _RMW_INFINITE[1]}
        return {"history": self.history.value, "depth": self.depth,
                "reliability": self.reliability.value, "durability": self.durability.value,
                "deadline": dict(infinite), "lifespan": dict(infinite),
                "liveliness": "automatic", "liveliness_lease_duration": dict(infinite),
                "avoid_ros_namespace_conventions": False}


@dataclass(frozen=True)
class TopicSpec:
    """A topic to record: fully qualified ``name`` (``/arm/joint_states``), message ``type``
    (``sensor_msgs/msg/JointState``) and the ``qos`` its publisher offers."""

    name: str
    type: str
    qos: QosProfile = field(default_factory=QosProfile)

    def __post_init__(self):
        if not self.name.startswith("/"):
            raise ValueError(f"topic name must be fully qualified (start with '/'): {self.name!r}")


@dataclass
class _Counts:
    """Message counts per topic and the time span (ns) of a set of messages."""

    per_topic: dict[str, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None

    @property
    def total(self) -> int:
        return sum(self.per_topic.values())

    def add(self, topic: str, time_ns: int):
        self.per_topic[topic] = self.per_topic.get(topic, 0) + 1
        self._cover(time_ns, time_ns)

    def merge(self, other: _Counts):
        for topic, count in other.per_topic.items():
            self.per_topic[topic] = self.per_topic.get(topic, 0) + count
        if other.start_ns is not None:
            self._cover(other.start_ns, other.end_ns)

    def _cover(self, start_ns: int, end_ns: int):
        self.start_ns = start_ns if self.start_ns is None else min(self.start_ns, start_ns)
        self.end_ns = end_ns if self.end_ns is None else max(self.end_ns, end_ns)


# libyaml's parser and emitter where PyYAML has them (its wheels do): same documents, a tenth of the
# pure-Python time on the many small metadata files a campaign reads and rewrites.
_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _NoAliasDumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):
    """Writes an object met twice out twice, as rosbag2 does, not as a YAML anchor and alias."""

    def ignore_aliases(self, data):
        return True


def _dump_yaml(data) -> str:
    return yaml.dump(data, Dumper=_NoAliasDumper, sort_keys=False, default_flow_style=False)


def _bag_info(topics: list[dict], counts: _Counts, file_name: str,
              custom_data: Mapping[str, str]) -> dict:
    """The version-9 ``rosbag2_bagfile_information`` mapping for one MCAP file."""
    start = _NO_MESSAGES_START if counts.start_ns is None else counts.start_ns
    duration = {"nanoseconds": 0 if counts.start_ns is None else counts.end_ns - counts.start_ns}
    return {
        "version": METADATA_VERSION,
        "storage_identifier": STORAGE_IDENTIFIER,
        "duration": duration,
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": counts.total,
        "topics_with_message_count": [
            {"topic_metadata": topic, "message_count": counts.per_topic.get(topic["name"], 0)}
            for topic in topics],
        "compression_format": "",  # MCAP chunk compression is internal to the storage file
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [{"path": file_name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": duration, "message_count": counts.total}],
        "custom_data": dict(custom_data) or None,
        "ros_distro": ROS_DISTRO,
    }


def _write_metadata_file(directory: Path, info: dict):
    """Replace ``metadata.yaml`` atomically: a reader sees the old or the new file, never half."""
    tmp = directory / f".{METADATA_FILE}.tmp"
    tmp.write_text(_dump_yaml({"rosbag2_bagfile_information": info}), encoding="utf-8")
    os.replace(tmp, directory / METADATA_FILE)


def _provisional_tail() -> bytes:
    """DataEnd, a Footer announcing no summary, and the magic: a file ending so is complete."""
    builder = RecordBuilder()
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return builder.end() + _MAGIC


class RosbagWriter:
    """Writes one rosbag2 bag (``metadata.yaml`` + one MCAP file) into a new ``directory``.

    ``topics``: the :class:`TopicSpec` of every topic that may be written; their message
    definitions and type hashes are looked up here, before anything is created.
    ``chunk_size``: bytes of message records after which the open chunk is written to disk (also
    the most a SIGKILL can lose). ``compression``: ``"none"``, ``"zstd"`` or ``"lz4"`` per chunk.
    ``custom_data``: string pairs stored under ``custom_data`` in ``metadata.yaml``.

    Raises :class:`FileExistsError` if ``directory`` exists,
    :class:`~.message_definitions.UnknownMessageTypeError` for a type without definition,
    :class:`ValueError` for duplicate topics or bad options.
    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, directory: str | os.PathLike, topics: Iterable[TopicSpec], *,
                 chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = "none",
                 custom_data: Mapping[str, str] | None = None):
        self._directory = Path(directory)
        self._topics = _unique_topics(topics)
        if operator.index(chunk_size) <= 0:
            raise ValueError(f"chunk_size must be > 0 bytes, got {chunk_size}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, "
                             f"got {compression!r}")
        self._custom_data = _string_pairs(custom_data or {})
        if self._directory.exists():
            raise FileExistsError(f"bag directory already exists: {self._directory}")
        definitions = {spec.type: message_definition(spec.type) for spec in self._topics}
        self._topic_metadata = [
            {"name": spec.name, "type": spec.type, "serialization_format": SERIALIZATION_FORMAT,
             "offered_qos_profiles": [spec.qos.to_metadata()],
             "type_description_hash": type_description_hash(spec.type)}
            for spec in self._topics]
        self._chunk_size = chunk_size
        self._flushed = _Counts()
        self._pending = _Counts()
        self._pending_bytes = 0
        self._sequence: dict[str, int] = {}
        self._closed = False
        self._directory.mkdir(parents=True)
        self._mcap_path = self._directory / f"{self._directory.name}_0.mcap"
        self._file: BinaryIO = open(self._mcap_path, "wb")
        # The writer alone decides when a chunk ends (flush), so it knows when data is on disk.
        self._mcap = Writer(self._file, chunk_size=sys.maxsize,
                            compression=_COMPRESSION[compression])
        self._mcap.start(profile=MCAP_PROFILE, library=LIBRARY)
        self._channels = self._register(definitions)
        self._file.flush()
        self._append_tail()
        self._write_metadata()

    @property
    def mcap_path(self) -> Path:
        """The MCAP file of the bag."""
        return self._mcap_path

    @property
    def message_count(self) -> int:
        """Messages written so far, including those still in the open chunk."""
        return self._flushed.total + self._pending.total

    @property
    def flushed_message_count(self) -> int:
        """Messages in completed chunks on disk: what survives a SIGKILL now."""
        return self._flushed.total

    def write(self, topic: str, timestamp_ns: int, data: bytes | bytearray | memoryview,
              publish_time_ns: int | None = None):
        """Record one message: CDR ``data`` received on ``topic`` at ``timestamp_ns`` (ns; the
        MCAP log time and rosbag2 receive time). ``publish_time_ns`` (ns) defaults to it."""
        if self._closed:
            raise ValueError(f"bag {self._directory} is closed")
        channel_id = self._channels.get(topic)
        if channel_id is None:
            raise UnknownTopicError(f"topic {topic!r} is not in this bag; "
                                    f"its topics are {sorted(self._channels)}")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"data must be serialized CDR bytes, got {type(data).__name__}")
        payload = bytes(data)
        log_time = _check_time(timestamp_ns, "timestamp_ns")
        publish_time = (log_time if publish_time_ns is None
                        else _check_time(publish_time_ns, "publish_time_ns"))
        sequence = self._sequence[topic] = (self._sequence[topic] + 1) % _SEQUENCE_MODULUS
        self._mcap.add_message(channel_id=channel_id, log_time=log_time, data=payload,
                               publish_time=publish_time, sequence=sequence)
        self._pending.add(topic, log_time)
        self._pending_bytes += _MESSAGE_RECORD_OVERHEAD + len(payload)
        if self._pending_bytes >= self._chunk_size:
            self.flush()

    def set_custom_data(self, key: str, value: str):
        """Set one string pair of ``custom_data`` in ``metadata.yaml`` (from the next flush on)."""
        self._custom_data.update(_string_pairs({key: value}))

    def flush(self):
        """Write the open chunk to disk now and refresh ``metadata.yaml``; no-op when the open
        chunk is empty. Call it from a timer to bound what a crash loses in time, not only in
        bytes. If writing fails (disk full), the writer is closed and the error raised: the bag
        then holds what earlier flushes wrote, and needs :func:`recover`."""
        if self._closed:
            raise ValueError(f"bag {self._directory} is closed")
        if not self._pending.total:
            return
        with self._replacing_tail():
            self._mcap.flush()
            self._append_tail()
        self._flushed.merge(self._pending)
        self._pending, self._pending_bytes = _Counts(), 0
        self._write_metadata()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` ran (or a failed write closed the writer)."""
        return self._closed

    def close(self):
        """Write the open chunk, the MCAP summary and footer and the final ``metadata.yaml``.

        Idempotent; also what leaving a ``with`` block does, whether or not the block raised, so
        everything written is kept. A failure while writing closes the writer as :meth:`flush`
        describes."""
        if self._closed:
            return
        self.flush()
        with self._replacing_tail():
            self._mcap.add_metadata("rosbag2", {
                "serialized_metadata": _dump_yaml(self._info()).rstrip("\n")})
            self._mcap.finish()
            self._file.close()
        self._closed = True
        self._write_metadata()

    def __enter__(self) -> RosbagWriter:
        return self

    def __exit__(self, *exc_info):
        self.close()

    def _register(self, definitions: dict[str, str]) -> dict[str, int]:
        schema_ids = {type_name: self._mcap.register_schema(type_name, SCHEMA_ENCODING,
                                                            text.encode("utf-8"))
                      for type_name, text in definitions.items()}
        channels = {}
        for spec, topic in zip(self._topics, self._topic_metadata):
            channels[spec.name] = self._mcap.register_channel(
                spec.name, SERIALIZATION_FORMAT, schema_ids[spec.type],
                {"offered_qos_profiles": _dump_yaml(topic["offered_qos_profiles"]).rstrip("\n"),
                 "topic_type_hash": topic["type_description_hash"]})
            self._sequence[spec.name] = 0
        return channels

    def _append_tail(self):
        """End the file with the provisional tail, keeping the write position before it."""
        self._tail_offset = self._file.tell()
        self._file.write(_provisional_tail())
        self._file.flush()
        self._file.seek(self._tail_offset)

    @contextmanager
    def _replacing_tail(self):
        """Drop the provisional tail before writing over it, so that a write cut short leaves a
        clean prefix of the file. If writing fails, abandon the writer, keeping that prefix."""
        try:
            self._file.truncate(self._tail_offset)
            yield
        except BaseException:
            self._closed = True
            with suppress(OSError):  # closing flushes what is buffered; the disk may refuse it
                self._file.close()
            raise

    def _info(self) -> dict:
        return _bag_info(self._topic_metadata, self._flushed, self._mcap_path.name,
                         self._custom_data)

    def _write_metadata(self):
        _write_metadata_file(self._directory, self._info())


def _unique_topics(topics: Iterable[TopicSpec]) -> list[TopicSpec]:
    topics = list(topics)
    names = [spec.name for spec in topics]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise ValueError(f"topics given more than once: {duplicates}")
    return topics


def _string_pairs(custom_data: Mapping[str, str]) -> dict[str, str]:
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in custom_data.items()):
        raise ValueError(f"custom_data keys and values must be strings: {dict(custom_data)!r}")
    return dict(custom_data)


def _check_time(value: int, name: str) -> int:
    value = operator.index(value)
    if not 0 <= value < 2**64:
        raise ValueError(f"{name} must be an unsigned 64-bit count of nanoseconds, got {value}")
    return value


class BagError(ValueError):
    """A directory that is not a rosbag2 bag (nor what is left of one)."""


def open_bag(directory: str | os.PathLike) -> int:
    """Make sure the bag in ``directory`` opens with every reader and that its ``metadata.yaml``
    counts what it holds, recovering it (:func:`recover`) unless its writer closed it and
    ``metadata.yaml`` counts what its summary does: an MCAP file without its footer, one ending in
    the provisional tail (killed between flushes: metadata.yaml may count one chunk less), or no
    ``metadata.yaml`` beside it (killed while it was created).
    What every tool of the project does before it reads a bag; must not run while the bag's writer
    is alive. Returns the number of messages; BagError for a directory that holds no bag."""
    directory = Path(directory)
    if not directory.is_dir():
        raise BagError(f"{directory} is not a bag directory")
    mcap = _mcap_file(directory)
    if mcap is None:
        raise BagError(f"{directory} holds no rosbag2 bag (no {METADATA_FILE}, no .mcap file)")
    with open(mcap, "rb") as file:
        counted = _summary_count(file) if _closed(file) else None
    info = _read_metadata(directory)
    if counted is not None and info is not None and int(info["message_count"]) == counted:
        return counted
    return recover(directory)


def recover(directory: str | os.PathLike) -> int:
    """Make a bag whose writer died (SIGKILL, power loss) readable by every reader.

    Cuts off a partly written last record (and a partly written summary), ends the MCAP file with
    the provisional tail if it has no footer, and rewrites ``metadata.yaml`` from the messages
    the file holds (its topics from the file's channels when the writer died before writing
    ``metadata.yaml``; a file cut inside its header is rewritten as a bag without topics). A
    cleanly closed bag comes out unchanged. Returns the number of messages in the bag. Never run
    it while the writing process is alive.
    """
    directory = Path(directory)
    info = _read_metadata(directory)
    path = directory / info["relative_file_paths"][0] if info else _mcap_file(directory)
    if path is None:
        raise BagError(f"{directory} holds no rosbag2 bag (no {METADATA_FILE}, no .mcap file)")
    with open(path, "r+b") as file:
        if not _has_header(file):
            file.truncate(0)
            file.seek(0)
            file.write(_MAGIC + _header_record() + _provisional_tail())
        complete_end, has_footer = _scan_records(file)
        if not has_footer:
            file.truncate(complete_end)
            file.seek(complete_end)
            file.write(_provisional_tail())
        file.seek(0)
        counts, channels = _count_messages(file)
    if info:
        topics = [entry["topic_metadata"] for entry in info["topics_with_message_count"]]
        custom_data = info["custom_data"] or {}
    else:
        topics, custom_data = [_topic_of(schema, channel) for schema, channel in channels], {}
    _write_metadata_file(directory, _bag_info(topics, counts, path.name, custom_data))
    return counts.total


def _mcap_file(directory: Path) -> Path | None:
    """The bag's MCAP file: the one ``metadata.yaml`` names, else the only ``*.mcap`` file."""
    info = _read_metadata(directory)
    if info:
        return directory / info["relative_file_paths"][0]
    files = sorted(directory.glob("*.mcap"))
    return files[0] if len(files) == 1 else None


def _read_metadata(directory: Path) -> dict | None:
    """The ``rosbag2_bagfile_information`` of ``metadata.yaml``, None if there is none (or it is
    not one: the file is replaced atomically, so that means it was never written)."""
    try:
        text = (directory / METADATA_FILE).read_text(encoding="utf-8")
        info = yaml.load(text, Loader=_SafeLoader)  # noqa: S506 - a safe loader
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    info = info.get("rosbag2_bagfile_information") if isinstance(info, dict) else None
    return info if isinstance(info, dict) and info.get("relative_file_paths") else None


def _closed(file: BinaryIO) -> bool:
    """The file is an MCAP its writer closed: it starts with the magic and ends with a Footer
    pointing to a summary, then the magic (the provisional tail's Footer points to none). Leaves
    the file at its start."""
    size = file.seek(0, os.SEEK_END)
    if size < 2 * len(_MAGIC) + _FOOTER_RECORD:
        return False
    file.seek(size - len(_MAGIC) - _FOOTER_RECORD)
    tail = file.read()
    file.seek(0)
    if tail[0] != Opcode.FOOTER or not tail.endswith(_MAGIC) or file.read(len(_MAGIC)) != _MAGIC:
        return False
    (summary_start,) = struct.unpack_from("<Q", tail, _RECORD_PREFIX.size)
    file.seek(0)
    return summary_start != 0


def _summary_count(file: BinaryIO) -> int | None:
    """The message count of a closed MCAP file's summary statistics (None without them)."""
    try:
        summary = make_reader(file).get_summary()
    except (McapError, struct.error, ValueError):
        return None
    finally:
        file.seek(0)
    return None if summary is None or summary.statistics is None else summary.statistics.message_count


def _has_header(file: BinaryIO) -> bool:
    """The file starts with the magic and a complete Header record."""
    size = file.seek(0, os.SEEK_END)
    file.seek(0)
    if file.read(len(_MAGIC)) != _MAGIC or size < len(_MAGIC) + _RECORD_PREFIX.size:
        return False
    opcode, length = _RECORD_PREFIX.unpack(file.read(_RECORD_PREFIX.size))
    return opcode == Opcode.HEADER and len(_MAGIC) + _RECORD_PREFIX.size + length <= size


def _header_record() -> bytes:
    builder = RecordBuilder()
    Header(profile=MCAP_PROFILE, library=LIBRARY).write(builder)
    return builder.end()


def _topic_of(schema, channel) -> dict:
    """A topic's ``metadata.yaml`` entry from its MCAP channel (as this module writes them)."""
    qos = yaml.load(channel.metadata.get("offered_qos_profiles", ""),  # noqa: S506 - a safe loader
                    Loader=_SafeLoader) or []
    return {"name": channel.topic, "type": schema.name if schema is not None else "",
            "serialization_format": channel.message_encoding, "offered_qos_profiles": qos,
            "type_description_hash": channel.metadata.get("topic_type_hash", "")}


def _scan_records(file: BinaryIO) -> tuple[int, bool]:
    """Walk the top-level MCAP records by their lengths alone.

    Returns where the complete data records end (at DataEnd if there is one, else before the
    first record cut short) and whether the file is complete: a Footer and the magic end it.
    """
    size = file.seek(0, os.SEEK_END)
    file.seek(0)
    if file.read(len(_MAGIC)) != _MAGIC:
        raise ValueError(f"{file.name} is not an MCAP file")
    offset, data_end = len(_MAGIC), None
    while offset + _RECORD_PREFIX.size <= size:
        opcode, length = _RECORD_PREFIX.unpack(file.read(_RECORD_PREFIX.size))
        end = offset + _RECORD_PREFIX.size + length
        if end > size:
            break
        if opcode == Opcode.DATA_END and data_end is None:
            data_end = offset
        elif opcode == Opcode.FOOTER:
            file.seek(end)
            return (offset if data_end is None else data_end), file.read() == _MAGIC
        offset = file.seek(end)
    return (offset if data_end is None else data_end), False


def _count_messages(file: BinaryIO) -> tuple[_Counts, list]:
    """The messages per topic of a complete MCAP file, and its (schema, channel) pairs in order."""
    counts, schemas, channels = _Counts(), {}, {}
    for record in StreamReader(file, validate_crcs=True).records:
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
    file.seek(0)
    reader = NonSeekingReader(file, validate_crcs=True)
    for _, channel, message in reader.iter_messages(log_time_order=False):
        counts.add(channel.topic, message.log_time)
    return counts, [(schemas.get(c.schema_id), c) for c in channels.values()]
