"""The mocap bridge's reading of a NatNet frame of data: one compiled walk over the bytes, the rigid
bodies and labelled markers as arrays, nothing else decoded.

:func:`~.natnet.parse_frame_of_data` builds an object per item of every data set, which costs what
the frame's sender chooses: a 64 KiB frame of thousands of tiny items took 300 times a normal
frame's time. The bridge needs only the frame number, the two data sets it selects markers from and
the time stamps, so :func:`scan_frame_of_data` walks the layout in compiled code (every count,
byte size and cap checked exactly as :func:`~.natnet.parse_frame_of_data` checks them, so that both
accept and refuse the same frames) and views the rigid bodies and labelled markers in place as
numpy records. Its cost is one pass over the bytes, whatever they hold.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numba import njit

from .natnet import (ITEM_LIMITS, FrameOfData, MessageId, NatNetParseError, Version, _check_version, _expect,
                     build_frame_of_data)

__all__ = ["FrameScan", "LABELED_MARKER", "RIGID_BODY", "scan_frame_of_data", "warm_up"]

#: One rigid body as on the wire (38 bytes, packed, little-endian).
RIGID_BODY = np.dtype([("id", "<i4"), ("position", "<f4", (3,)), ("orientation", "<f4", (4,)),
                       ("mean_error", "<f4"), ("params", "<u2")])
#: One labelled marker as on the wire (26 bytes).
LABELED_MARKER = np.dtype([("id", "<i4"), ("position", "<f4", (3,)), ("size", "<f4"), ("params", "<u2"),
                           ("residual", "<f4")])
_SUFFIX = struct.Struct("<IIdQQQ")
_PRECISION = 8
_PARAMS = struct.Struct("<H")
_END_TAG = 4
_MIN_ASSET = 12

# data sets in the order they come; what the walk reports about each
_SECTIONS = ("marker set", "unlabelled marker", "rigid body", "skeleton", "labelled marker",
             "force plate", "device")
_NESTED = ("marker set marker", "skeleton rigid body", "analog channel", "analog sample")
_CAPS = np.array([ITEM_LIMITS[name] for name in _SECTIONS + _NESTED], dtype=np.int64)
_OK, _TRUNCATED, _IMPLAUSIBLE, _CAP, _SIZE, _SIZE_LEFT, _NO_NUL, _ASSETS, _TRAILING = range(9)


@dataclass(frozen=True)
class FrameScan:
    """What the bridge reads of a frame: its number, the rigid bodies and labelled markers as
    records (:data:`RIGID_BODY`, :data:`LABELED_MARKER`; views of the datagram), and the suffix:
    Motive's software time [s] and the server-clock ticks of mid-exposure, data received and
    transmit."""
    frame_number: int
    rigid_bodies: np.ndarray
    labeled_markers: np.ndarray
    timestamp: float
    camera_mid_exposure: int
    camera_data_received: int
    transmit_timestamp: int


@njit(cache=True, nogil=True)
def _i32(buf, o):
    v = np.int64(buf[o]) | (np.int64(buf[o + 1]) << 8) | (np.int64(buf[o + 2]) << 16) \
        | (np.int64(buf[o + 3]) << 24)
    return v - (np.int64(1) << 32) if v >= (np.int64(1) << 31) else v


@njit(cache=True, nogil=True)
def _walk(buf, sized, caps, out):
    """Walk the payload ``buf`` (uint8) of a frame; ``out`` (int64, 10): status, what, two values,
    rigid bodies' offset and count, labelled markers' offset and count, the suffix's offset.
    Status 0: a well-formed frame; otherwise the kind of fault with its details."""
    n = buf.shape[0]
    o = 4
    if n < 4:
        out[0], out[1], out[2], out[3] = _TRUNCATED, -1, 0, n
        return
    for section in range(7):
        if section == 4 and sized:                          # the 4.1 asset data set, skipped by size
            if o + 8 > n:
                out[0], out[1], out[2], out[3] = _TRUNCATED, -2, o, n - o
                return
            count, size = _i32(buf, o), _i32(buf, o + 4)
            o += 8
            if size < 0 or size > n - o or count < 0 or count * _MIN_ASSET > size:
                out[0], out[1], out[2], out[3] = _ASSETS, count, size, n - o
                return
            o += size
        if o + 4 > n:
            out[0], out[1], out[2], out[3] = _TRUNCATED, section, o, n - o
            return
        count = _i32(buf, o)
        o += 4
        available = n - o
        if sized:
            if o + 4 > n:
                out[0], out[1], out[2], out[3] = _TRUNCATED, section, o, n - o
                return
            size = _i32(buf, o)
            o += 4
            if size < 0 or size > n - o:
                out[0], out[1], out[2], out[3] = _SIZE_LEFT, section, size, n - o
                return
            available = size
        least = (5, 12, 38, 8, 26, 8, 8)[section]
        if count < 0 or count * least > available:
            out[0], out[1], out[2], out[3] = _IMPLAUSIBLE, section, count, available
            return
        if count > caps[section]:
            out[0], out[1], out[2], out[3] = _CAP, section, count, caps[section]
            return
        start = o
        if section == 2:
            out[4], out[5] = o, count
        elif section == 4:
            out[6], out[7] = o, count
        if section == 1 or section == 2 or section == 4:
            o += count * least
        else:
            for _ in range(count):
                if section == 0:                            # name, int32 m, m x float32[3]
                    end = o
                    while end < n and buf[end] != 0:
                        end += 1
                    if end >= n:
                        out[0], out[1], out[2], out[3] = _NO_NUL, section, o, 0
                        return
                    o = end + 1
                    inner, item, cap = 7, 12, caps[7]
                elif section == 3:                          # int32 id, int32 m, m x rigid body
                    if o + 4 > n:
                        out[0], out[1], out[2], out[3] = _TRUNCATED, section, o, n - o
                        return
                    o += 4
                    inner, item, cap = 8, 38, caps[8]
                else:                                       # int32 id, int32 c, c x (int32 f, f x float32)
                    if o + 4 > n:
                        out[0], out[1], out[2], out[3] = _TRUNCATED, section, o, n - o
                        return
                    o += 4
                    inner, item, cap = 9, 4, caps[9]
                if o + 4 > n:
                    out[0], out[1], out[2], out[3] = _TRUNCATED, section, o, n - o
                    return
                m = _i32(buf, o)
                o += 4
                if m < 0 or m * item > n - o:
                    out[0], out[1], out[2], out[3] = _IMPLAUSIBLE, inner, m, n - o
                    return
                if m > cap:
                    out[0], out[1], out[2], out[3] = _CAP, inner, m, cap
                    return
                if inner != 9:
                    o += m * item
                    continue
                for _ in range(m):
                    if o + 4 > n:
                        out[0], out[1], out[2], out[3] = _TRUNCATED, 10, o, n - o
                        return
                    f = _i32(buf, o)
                    o += 4
                    if f < 0 or f * 4 > n - o:
                        out[0], out[1], out[2], out[3] = _IMPLAUSIBLE, 10, f, n - o
                        return
                    if f > caps[10]:
                        out[0], out[1], out[2], out[3] = _CAP, 10, f, caps[10]
                        return
                    o += 4 * f
        if o > n:
            out[0], out[1], out[2], out[3] = _TRUNCATED, section, start, n - start
            return
        if sized and o - start != available:
            out[0], out[1], out[2], out[3] = _SIZE, section, available, o - start
            return
    tail = 40 + (8 if sized else 0) + 2
    if o + tail > n:
        out[0], out[1], out[2], out[3] = _TRUNCATED, 11, o, n - o
        return
    if n - (o + tail) != 0 and n - (o + tail) != 4:
        out[0], out[1], out[2], out[3] = _TRAILING, 11, n - (o + tail), 0
        return
    out[0], out[8] = _OK, o


def _what(index: int) -> str:
    names = _SECTIONS + _NESTED
    return {-1: "frame number", -2: "asset data set", 11: "frame suffix"}.get(
        index, names[index] if 0 <= index < len(names) else "?")


def _fault(out) -> NatNetParseError:
    status, what, a, b = (int(v) for v in out[:4])
    name = _what(what)
    return NatNetParseError({
        _TRUNCATED: f"truncated frame: {name} at offset {a}, {b} bytes left",
        _IMPLAUSIBLE: f"implausible {name} count {a} with {b} bytes left",
        _CAP: f"{name} count {a} is above the {b} a NatNet server sends (NatNetTypes.h)",
        _SIZE: f"{name} byte size says {a} but its items take {b}",
        _SIZE_LEFT: f"{name} byte size {a} exceeds the {b} bytes left",
        _NO_NUL: f"truncated frame: {name} name at offset {a} has no NUL",
        _ASSETS: f"implausible asset data set: {what} assets in {a} bytes with {b} bytes left",
        _TRAILING: f"{a} unexpected bytes after the frame params (only a 4-byte end-of-data tag "
                   f"may follow)",
    }[status])


def _records(payload: bytes, dtype: np.dtype, offset: int, count: int) -> np.ndarray:
    """``count`` records of ``dtype`` at ``offset`` of ``payload``, viewed in place."""
    if count == 0:
        return np.empty(0, dtype=dtype)
    return np.frombuffer(payload, dtype=dtype, count=count, offset=offset)


def scan_frame_of_data(data: bytes, version: Sequence[int]) -> FrameScan:
    """The bridge's reading of a NAT_FRAMEOFDATA datagram of stream ``version``; NatNetParseError,
    and nothing else, for every frame :func:`~.natnet.parse_frame_of_data` refuses."""
    sized = _check_version(version)
    payload = _expect(data, MessageId.NAT_FRAMEOFDATA)
    buf = np.frombuffer(payload, dtype=np.uint8)
    out = np.zeros(10, dtype=np.int64)
    _walk(buf, sized, _CAPS, out)
    if out[0] != _OK:
        raise _fault(out)
    frame_number = struct.unpack_from("<i", payload)[0]
    bodies = _records(payload, RIGID_BODY, int(out[4]), int(out[5]))
    labelled = _records(payload, LABELED_MARKER, int(out[6]), int(out[7]))
    _, _, timestamp, mid, received, transmit = _SUFFIX.unpack_from(payload, int(out[8]))
    return FrameScan(frame_number, bodies, labelled, timestamp, mid, received, transmit)


def warm_up():
    """Compile the walk (a cold numba cache: a fresh install), so that the first frame does not."""
    scan_frame_of_data(build_frame_of_data(Version(4, 1), FrameOfData(frame_number=1)), Version(4, 1))
