"""Topics of a bag whose messages all share one byte layout, decoded as arrays in one vectorised
pass: what the identification reads (hundreds of thousands of tendon states and marker frames).

A recorded ``sensor_msgs/JointState`` or ``geometry_msgs/PoseArray`` topic usually repeats one
layout: the same frame id, the same names, the same counts; only stamps and values change. The
first message is walked field by field (CDR, little-endian, alignment counted from the end of the
4-byte encapsulation header) to find where its stamp and values lie; every other message must be
as long and equal it byte for byte outside those places, or the topic is not decoded here
(``None``: the caller decodes it message by message with ``rosbags``). Stamps are the headers'
[s]; nothing is taken from the bag's own receive times.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from soft_arm_drivers.recording.rosbag_writer import open_bag

_HEADER = 4                 # bytes of the CDR encapsulation header
_LITTLE_ENDIAN = (b"\x00\x01", b"\x00\x03")      # CDR_LE, PL_CDR_LE
_TYPES = get_typestore(Stores.ROS2_JAZZY)


def read_raw(bag_dir: str, topics) -> dict:
    """Per topic (without leading slash) of ``topics``: (message type, serialised messages in bag
    order). The bag is recovered first if its writer was cut off (:func:`open_bag`)."""
    open_bag(bag_dir)
    out = {}
    with AnyReader([Path(bag_dir)], default_typestore=_TYPES) as reader:
        connections = [c for c in reader.connections if c.topic.lstrip("/") in topics]
        for conn, _, raw in reader.messages(connections=connections):
            entry = out.setdefault(conn.topic.lstrip("/"), (conn.msgtype, []))
            entry[1].append(bytes(raw))
    return out


class _Walk:
    """Offsets in one CDR message (``pos`` counts from the end of the encapsulation header)."""

    def __init__(self, raw: bytes):
        self.raw, self.pos = raw, 0

    def _align(self, size: int):
        self.pos += -self.pos % size

    def u32(self) -> tuple[int, int]:
        self._align(4)
        at = self.pos
        self.pos += 4
        return at, int.from_bytes(self.raw[_HEADER + at:_HEADER + at + 4], "little")

    def string(self):
        _, length = self.u32()
        self.pos += length

    def doubles(self, count: int) -> int:
        if count:               # an empty sequence has no element to align
            self._align(8)
        at = self.pos
        self.pos += 8 * count
        return at

    def header(self) -> int:
        """Walks a std_msgs/Header; returns the stamp's offset (int32 sec, uint32 nanosec)."""
        at, _ = self.u32()
        self.u32()
        self.string()
        return at

    def double_sequence(self) -> tuple[int, int]:
        _, count = self.u32()
        return self.doubles(count), count


def _stacked(raws: list) -> np.ndarray | None:
    """The messages as rows of one (N, length) byte array; None unless all are as long and
    little-endian."""
    length = len(raws[0])
    if any(len(r) != length for r in raws) or raws[0][:2] not in _LITTLE_ENDIAN:
        return None
    return np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), length)


def _uniform(rows: np.ndarray, variable: list) -> bool:
    """Every row equals the first outside the ``variable`` (offset, size) byte ranges."""
    fixed = np.ones(rows.shape[1], dtype=bool)
    for at, size in variable:
        fixed[_HEADER + at:_HEADER + at + size] = False
    return bool(np.all(rows[:, fixed] == rows[0, fixed]))


def _field(rows: np.ndarray, at: int, dtype: str, count: int) -> np.ndarray:
    size = np.dtype(dtype).itemsize
    return np.ascontiguousarray(rows[:, _HEADER + at:_HEADER + at + size * count]).view(dtype)


def _stamps(rows: np.ndarray, at: int) -> np.ndarray:
    return _field(rows, at, "<i4", 1)[:, 0] + 1e-9 * _field(rows, at + 4, "<u4", 1)[:, 0]


def _start(raws: list):
    """(rows, the walk past the header and the message's first sequence count, the stamp's offset,
    that count) of messages with one header layout; None if there are none or their lengths or
    byte orders differ."""
    rows = _stacked(raws) if raws else None
    if rows is None:
        return None
    walk = _Walk(raws[0])
    stamp = walk.header()
    _, count = walk.u32()
    return rows, walk, stamp, count


def joint_state_arrays(raws: list, names, fields=("position", "effort")):
    """``sensor_msgs/JointState`` messages of one layout as (header stamps (N,) [s], per field of
    ``fields`` an (N, len(names)) array, columns in the order of ``names``); None when the
    messages do not share one layout or the first lacks one of ``names`` or a field's values."""
    start = _start(raws)
    if start is None:
        return None
    rows, walk, stamp, count = start
    found = []
    for _ in range(count):
        at, length = walk.u32()
        walk.pos += length
        found.append(raws[0][_HEADER + at + 4:_HEADER + at + 4 + length].rstrip(b"\x00").decode())
    places = {f: walk.double_sequence() for f in ("position", "velocity", "effort")}
    if walk.pos > rows.shape[1] - _HEADER or any(n not in found for n in names) \
            or any(places[f][1] != count for f in fields):
        return None
    if not _uniform(rows, [(stamp, 8)] + [(at, 8 * c) for at, c in places.values()]):
        return None
    columns = [found.index(n) for n in names]
    t = _stamps(rows, stamp)
    values = {f: _field(rows, places[f][0], "<f8", count)[:, columns] for f in fields}
    first = _TYPES.deserialize_cdr(raws[0], "sensor_msgs/msg/JointState")     # the walk checked
    same = [np.array_equal(values[f][0], np.asarray(getattr(first, f))[columns], equal_nan=True)
            for f in fields]
    if list(first.name) != found or t[0] != _seconds(first.header) or not all(same):
        return None
    return t, values


def pose_array_positions(raws: list):
    """``geometry_msgs/PoseArray`` messages of one layout as (header stamps (N,) [s], positions
    (N, poses, 3) [m]); None when they do not share one layout."""
    start = _start(raws)
    if start is None:
        return None
    rows, walk, stamp, count = start
    at = walk.doubles(7 * count)        # each pose: position (3), orientation (4), all float64
    if walk.pos > rows.shape[1] - _HEADER or not _uniform(rows, [(stamp, 8), (at, 56 * count)]):
        return None
    poses = _field(rows, at, "<f8", 7 * count).reshape(len(raws), count, 7)
    t, positions = _stamps(rows, stamp), np.ascontiguousarray(poses[:, :, :3])
    first = _TYPES.deserialize_cdr(raws[0], "geometry_msgs/msg/PoseArray")    # the walk checked
    want = np.array([[p.position.x, p.position.y, p.position.z] for p in first.poses]).reshape(count, 3)
    if t[0] != _seconds(first.header) or not np.array_equal(positions[0], want, equal_nan=True):
        return None
    return t, positions


def _seconds(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec
