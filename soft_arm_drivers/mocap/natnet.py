"""NatNet (OptiTrack Motive) packet codec and client-side parser, without ROS.

Parses what a NatNet server sends (server info, frames of data) and builds what a client sends
(connect request, commands), plus the reverse of both so that a server emulator and the tests can
speak the real protocol over UDP. Everything is little-endian.

Packet (one UDP datagram)::

    uint16 message id (``MessageId``)   uint16 payload size N   N bytes of payload

Server info payload (``sSender_Server`` in the SDK's NatNetTypes.h, packed, 279 bytes)::

    char[256] application name (NUL-terminated)   uint8[4] application version
    uint8[4] NatNet stream version   uint64 high-resolution clock frequency [ticks/s]
    uint16 data port   uint8 multicast flag   uint8[4] multicast group address

Servers older than NatNet 3.0 send only the first 264 bytes (``sSender``).

Connect request payload: an ``sSender`` block (client name, zero versions) followed by
``sConnectionOptions`` (uint8 subscribed-data-only flag, uint8[4] requested bitstream version;
0.0.0.0 lets the server choose), padded with four zero bytes as the SDK's PacketClient.cpp does.

Frame of data payload, supported for stream versions 3.0, 3.1, 4.0 and 4.1 (3.x and 4.0 frames
are identical; 4.1 inserts an int32 byte size after every data-set count, covering the bytes after
that size field, adds the asset data set and a precision timestamp)::

    int32 frame number
    marker sets:        int32 n [int32 size]  n x (NUL-terminated name, int32 m, m x float32[3])
    unlabelled markers: int32 n [int32 size]  n x float32[3]               (legacy "other markers")
    rigid bodies:       int32 n [int32 size]  n x rigid body
    skeletons:          int32 n [int32 size]  n x (int32 id, int32 m, m x rigid body)
    assets (4.1 only):  int32 n  int32 size   skipped by its byte size
    labelled markers:   int32 n [int32 size]  n x labelled marker
    force plates:       int32 n [int32 size]  n x analog data
    devices:            int32 n [int32 size]  n x analog data
    uint32 timecode, uint32 timecode subframe, float64 timestamp [s],
    uint64 camera mid-exposure, uint64 camera data received, uint64 transmit [clock ticks],
    (4.1 only) uint32 precision timestamp seconds, uint32 precision timestamp fraction,
    uint16 frame params (bit 0 recording, bit 1 tracked models changed),
    optional int32 end-of-data tag (sent by Motive, read by the SDK's C++ client)

    rigid body (38 bytes):       int32 id, float32[3] position [m], float32[4] quaternion x, y, z, w,
                                 float32 mean marker error [m], uint16 params (bit 0 tracking valid)
    labelled marker (26 bytes):  int32 id (model id << 16 | marker id), float32[3] position [m],
                                 float32 size [m], uint16 params (bit 0 occluded, bit 1 point-cloud
                                 solved, bit 2 model solved), float32 residual [m]
    analog data:                 int32 id, int32 c, c x (int32 f, f x float32)

Positions are in Motive's streaming units (metres by default). The SDK declares the uint16 params
fields as int16; the bytes are the same.

Sources: NatNet SDK 4.1 ``NatNetClient.py`` (as mirrored in lunarring/optitrack_python) and
``PacketClient.cpp`` (4.x, as mirrored in several public repositories), NatNetTypes.h
(``sSender``, ``sSender_Server``, ``sConnectionOptions``, message ids). The two SDK samples disagree
on the precision timestamp: PacketClient.cpp reads it from 4.1 on, NatNetClient.py for every 4.x
stream; this module follows PacketClient.cpp (no precision timestamp in 4.0), which is unverified
against a live Motive 3.0 server.

Robustness: every parser raises ``NatNetParseError`` (a ValueError) for malformed, truncated,
mis-sized or unexpected packets and never anything else; counts are checked against the bytes left
before anything is allocated, and against what a NatNet server sends (:data:`ITEM_LIMITS`): a frame
beyond those is malformed, so that what a frame costs to read is bounded by what Motive can send, not
by what fits in 64 KiB. Builders raise ValueError for values that do not fit the wire format.
"""
import ipaddress
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Callable, NamedTuple, Optional, Sequence, Tuple, TypeVar

__all__ = [
    "ITEM_LIMITS", "AnalogData", "ConnectRequest", "FrameFilter", "FrameOfData", "LabeledMarker", "MarkerSet",
    "MessageId", "NatNetParseError", "RigidBody", "SUPPORTED_VERSIONS", "ServerInfo", "Skeleton",
    "Version", "build_connect_request", "build_frame_of_data", "build_packet", "build_request",
    "build_server_info", "parse_connect_request", "parse_frame_of_data", "parse_packet",
    "parse_server_info",
]


class NatNetParseError(ValueError):
    """A received packet is malformed, truncated, of the wrong type or of an unsupported version."""


class MessageId(IntEnum):
    """NatNet message ids (NatNetTypes.h)."""

    NAT_CONNECT = 0
    NAT_SERVERINFO = 1
    NAT_REQUEST = 2
    NAT_RESPONSE = 3
    NAT_REQUEST_MODELDEF = 4
    NAT_MODELDEF = 5
    NAT_REQUEST_FRAMEOFDATA = 6
    NAT_FRAMEOFDATA = 7
    NAT_MESSAGESTRING = 8
    NAT_DISCONNECT = 9
    NAT_KEEPALIVE = 10
    NAT_DISCONNECTBYTIMEOUT = 11
    NAT_ECHOREQUEST = 12
    NAT_ECHORESPONSE = 13
    NAT_DISCOVERY = 14
    NAT_UNRECOGNIZED_REQUEST = 100


class Version(NamedTuple):
    """A four-part NatNet or application version; compares like a tuple."""

    major: int
    minor: int
    build: int = 0
    revision: int = 0

    def __str__(self):
        return ".".join(str(part) for part in self)


SUPPORTED_VERSIONS = (Version(3, 0), Version(3, 1), Version(4, 0), Version(4, 1))

#: The most items of each data set one frame holds: the model limits of the NatNet SDK's
#: ``NatNetTypes.h`` (3.x and 4.x: MAX_MARKERSETS 1000, MAX_MARKERS 200 per marker set,
#: MAX_UNLABELED_MARKERS 1000, MAX_RIGIDBODIES 1000, MAX_SKELETONS 100, MAX_SKELRIGIDBODIES 200,
#: MAX_LABELED_MARKERS 1000, MAX_FORCEPLATES 8, MAX_DEVICES 32, MAX_ANALOG_CHANNELS 32 per device
#: or force plate, MAX_ANALOG_SUBFRAMES 30 samples per channel and frame), the sizes of the SDK's
#: own frame structure: a server does not send more.
ITEM_LIMITS = {"marker set": 1000, "marker set marker": 200, "unlabelled marker": 1000,
               "rigid body": 1000, "skeleton": 100, "skeleton rigid body": 200, "labelled marker": 1000,
               "force plate": 8, "device": 32, "analog channel": 32, "analog sample": 30}

Vector3 = Tuple[float, float, float]
Quaternion = Tuple[float, float, float, float]
T = TypeVar("T")

_HEADER = struct.Struct("<HH")
_MAX_PAYLOAD = 0xFFFF
_NAME_LENGTH = 256
_I32 = struct.Struct("<i")
_VECTOR3 = struct.Struct("<3f")
_FLOAT = struct.Struct("<f")
_PARAMS = struct.Struct("<H")
_RIGID_BODY = struct.Struct("<i3f4ffH")
_LABELED_MARKER = struct.Struct("<i3ffHf")
_SUFFIX = struct.Struct("<IIdQQQ")
_PRECISION_TIMESTAMP = struct.Struct("<II")
_END_OF_DATA = _I32
_SENDER = struct.Struct(f"<{_NAME_LENGTH}s4B4B")
_SERVER_CONNECTION = struct.Struct("<QHB4s")
_CONNECTION_OPTIONS = struct.Struct("<B4B")
_CONNECT_PADDING = bytes(4)
_MIN_ASSET_SIZE = 12  # int32 id, int32 rigid body count, int32 marker count
_EMPTY_ASSETS = _I32.pack(0) + _I32.pack(0)  # 4.1 asset data set: count 0, byte size 0
_SUPPORTED_KEYS = frozenset((v.major, v.minor) for v in SUPPORTED_VERSIONS)


# --- data ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MarkerSet:
    """A named marker set and its marker positions [m]."""

    name: str
    markers: Tuple[Vector3, ...] = ()


@dataclass(frozen=True)
class RigidBody:
    """One rigid body: position [m], orientation quaternion (x, y, z, w), mean marker error [m]."""

    id: int
    position: Vector3
    orientation: Quaternion
    mean_error: float = 0.0
    params: int = 0x01

    @property
    def tracking_valid(self) -> bool:
        """Motive tracked the body in this frame (params bit 0)."""
        return bool(self.params & 0x01)


@dataclass(frozen=True)
class Skeleton:
    """A skeleton: its id and its bones as rigid bodies."""

    id: int
    rigid_bodies: Tuple[RigidBody, ...] = ()


@dataclass(frozen=True)
class LabeledMarker:
    """One labelled marker: position [m], size [m], params bit field, residual [m]."""

    id: int
    position: Vector3
    size: float = 0.0
    params: int = 0
    residual: float = 0.0

    @property
    def occluded(self) -> bool:
        """The marker was not seen in this frame (params bit 0)."""
        return bool(self.params & 0x01)

    @property
    def model_id(self) -> int:
        """The asset the marker belongs to (high 16 bits of the id)."""
        return (self.id >> 16) & 0xFFFF

    @property
    def marker_id(self) -> int:
        """The marker's index within its asset, or its point-cloud id (low 16 bits of the id)."""
        return self.id & 0xFFFF


@dataclass(frozen=True)
class AnalogData:
    """A force plate or device: its id and, per channel, the samples of this frame."""

    id: int
    channels: Tuple[Tuple[float, ...], ...] = ()


@dataclass(frozen=True)
class FrameOfData:
    """One NAT_FRAMEOFDATA message.

    ``timestamp`` is Motive's software time [s]; ``camera_mid_exposure``, ``camera_data_received``
    and ``transmit_timestamp`` are ticks of the server's high-resolution clock
    (``ServerInfo.clock_frequency`` ticks per second). The precision timestamp (typically PTP) is
    only carried by 4.1 streams and is zero when absent.
    """

    frame_number: int
    rigid_bodies: Tuple[RigidBody, ...] = ()
    labeled_markers: Tuple[LabeledMarker, ...] = ()
    marker_sets: Tuple[MarkerSet, ...] = ()
    unlabeled_markers: Tuple[Vector3, ...] = ()
    skeletons: Tuple[Skeleton, ...] = ()
    force_plates: Tuple[AnalogData, ...] = ()
    devices: Tuple[AnalogData, ...] = ()
    timecode: int = 0
    timecode_subframe: int = 0
    timestamp: float = 0.0
    camera_mid_exposure: int = 0
    camera_data_received: int = 0
    transmit_timestamp: int = 0
    precision_timestamp_secs: int = 0
    precision_timestamp_frac_secs: int = 0
    params: int = 0

    @property
    def is_recording(self) -> bool:
        """Motive is recording (frame params bit 0)."""
        return bool(self.params & 0x01)

    @property
    def tracked_models_changed(self) -> bool:
        """The list of tracked assets changed; model definitions should be re-requested (bit 1)."""
        return bool(self.params & 0x02)


@dataclass(frozen=True)
class ServerInfo:
    """NAT_SERVERINFO: who the server is and which stream version it sends.

    The connection fields (clock frequency [ticks/s], data port, multicast flag and group) exist
    from NatNet 3.0 on and are None for older servers.
    """

    app_name: str
    app_version: Version
    natnet_version: Version
    clock_frequency: Optional[int] = None
    data_port: Optional[int] = None
    multicast: Optional[bool] = None
    multicast_group: Optional[str] = None


@dataclass(frozen=True)
class ConnectRequest:
    """NAT_CONNECT as a server sees it; ``bitstream_version`` None lets the server choose."""

    client_name: str
    bitstream_version: Optional[Version] = None
    subscribed_data_only: bool = False


# --- packets -------------------------------------------------------------------------------------

def build_packet(message_id: MessageId, payload: bytes = b"") -> bytes:
    """Header plus payload; ValueError if the payload exceeds the 65535 bytes of the size field."""
    if len(payload) > _MAX_PAYLOAD:
        raise ValueError(f"NatNet payload of {len(payload)} bytes exceeds {_MAX_PAYLOAD}")
    return _HEADER.pack(MessageId(message_id), len(payload)) + bytes(payload)


def parse_packet(data: bytes) -> Tuple[MessageId, bytes]:
    """Split a datagram into message id and payload.

    Bytes after the declared payload are ignored (the SDK's Python client appends a NUL to
    keep-alives that declare an empty payload); a declared size beyond the datagram, a datagram
    shorter than the header or an unknown message id raises NatNetParseError.
    """
    data = bytes(data)
    if len(data) < _HEADER.size:
        raise NatNetParseError(f"datagram of {len(data)} bytes is shorter than the 4-byte header")
    raw_id, size = _HEADER.unpack_from(data)
    try:
        message_id = MessageId(raw_id)
    except ValueError:
        raise NatNetParseError(f"unknown NatNet message id {raw_id}") from None
    if _HEADER.size + size > len(data):
        raise NatNetParseError(f"{message_id.name} declares {size} payload bytes but the datagram "
                               f"carries {len(data) - _HEADER.size}")
    return message_id, data[_HEADER.size:_HEADER.size + size]


def _expect(data: bytes, expected: MessageId) -> bytes:
    """The payload of ``data``; NatNetParseError if it is not an ``expected`` message."""
    message_id, payload = parse_packet(data)
    if message_id != expected:
        raise NatNetParseError(f"expected {expected.name} ({int(expected)}), "
                               f"got {message_id.name} ({int(message_id)})")
    return payload


def build_request(command: str) -> bytes:
    """NAT_REQUEST carrying a NUL-terminated command string, e.g. ``"Bitstream,4.1"``."""
    return build_packet(MessageId.NAT_REQUEST, _encode_cstring(command, "command"))


# --- handshake -----------------------------------------------------------------------------------

def _encode_cstring(text: str, what: str, length: Optional[int] = None) -> bytes:
    """UTF-8 plus NUL, NUL-padded to ``length`` if given; ValueError if it contains NUL or is long."""
    raw = text.encode("utf-8")
    if b"\0" in raw:
        raise ValueError(f"{what} must not contain NUL characters: {text!r}")
    if length is not None and len(raw) >= length:
        raise ValueError(f"{what} is {len(raw)} bytes long; at most {length - 1} fit")
    return raw.ljust(length, b"\0") if length is not None else raw + b"\0"


def _decode_name(raw: bytes) -> str:
    """Text up to the first NUL of a fixed-size name field (invalid UTF-8 replaced)."""
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def _version_bytes(version: Sequence[int], what: str) -> Version:
    """``version`` padded to four parts, each 0..255; ValueError otherwise."""
    parts = tuple(version) + (0,) * (4 - len(version))
    if len(parts) != 4 or not all(isinstance(p, int) and 0 <= p <= 0xFF for p in parts):
        raise ValueError(f"{what} must be up to four integers in 0..255, got {version!r}")
    return Version(*parts)


def build_connect_request(client_name: str = "soft_arm",
                          bitstream_version: Optional[Sequence[int]] = None,
                          subscribed_data_only: bool = False) -> bytes:
    """NAT_CONNECT packet; ``bitstream_version`` (e.g. ``(4, 1)``) asks for a stream version."""
    requested = _version_bytes(bitstream_version or (), "bitstream_version")
    zero_versions = bytes(8)  # the SDK's clients leave their app and NatNet versions zero
    payload = (_SENDER.pack(_encode_cstring(client_name, "client_name", _NAME_LENGTH),
                            *zero_versions)
               + _CONNECTION_OPTIONS.pack(bool(subscribed_data_only), *requested)
               + _CONNECT_PADDING)
    return build_packet(MessageId.NAT_CONNECT, payload)


def parse_connect_request(data: bytes) -> ConnectRequest:
    """Decode a NAT_CONNECT packet (for a server emulator).

    Accepts the SDK 4.x layouts (sender block plus connection options, with any padding), a bare
    sender block, and the legacy form whose payload is just a NUL-terminated name or empty.
    """
    payload = _expect(data, MessageId.NAT_CONNECT)
    if len(payload) < _SENDER.size:
        return ConnectRequest(client_name=_decode_name(payload))
    name = _decode_name(_SENDER.unpack_from(payload)[0])
    if len(payload) < _SENDER.size + _CONNECTION_OPTIONS.size:
        return ConnectRequest(client_name=name)
    subscribed, *requested = _CONNECTION_OPTIONS.unpack_from(payload, _SENDER.size)
    bitstream_version = Version(*requested) if any(requested) else None
    return ConnectRequest(name, bitstream_version, subscribed_data_only=bool(subscribed))


def build_server_info(info: ServerInfo) -> bytes:
    """NAT_SERVERINFO packet: 279 payload bytes from NatNet 3.0 on, 264 before.

    The connection fields must all be given for 3.0 and later servers and all be None before;
    ValueError otherwise.
    """
    natnet = _version_bytes(info.natnet_version, "natnet_version")
    sender = _SENDER.pack(_encode_cstring(info.app_name, "app_name", _NAME_LENGTH),
                          *_version_bytes(info.app_version, "app_version"), *natnet)
    connection = (info.clock_frequency, info.data_port, info.multicast, info.multicast_group)
    if natnet.major < 3:
        if any(field is not None for field in connection):
            raise ValueError("servers older than NatNet 3.0 send no connection fields")
        return build_packet(MessageId.NAT_SERVERINFO, sender)
    if any(field is None for field in connection):
        raise ValueError("NatNet 3.0+ server info needs clock_frequency, data_port, multicast and "
                         "multicast_group")
    try:
        extra = _SERVER_CONNECTION.pack(info.clock_frequency, info.data_port, bool(info.multicast),
                                        ipaddress.IPv4Address(info.multicast_group).packed)
    except (struct.error, ipaddress.AddressValueError) as error:
        raise ValueError(f"server connection fields do not fit the wire format: {error}") from None
    return build_packet(MessageId.NAT_SERVERINFO, sender + extra)


def parse_server_info(data: bytes) -> ServerInfo:
    """Decode a NAT_SERVERINFO packet; ``natnet_version`` selects the frame layout."""
    payload = _expect(data, MessageId.NAT_SERVERINFO)
    full = _SENDER.size + _SERVER_CONNECTION.size
    if len(payload) not in (_SENDER.size, full):
        raise NatNetParseError(f"server info payload must be {_SENDER.size} or {full} bytes, "
                               f"got {len(payload)}")
    name, *versions = _SENDER.unpack_from(payload)
    app_version, natnet_version = Version(*versions[:4]), Version(*versions[4:])
    if len(payload) == _SENDER.size:
        if natnet_version.major >= 3:
            raise NatNetParseError(f"NatNet {natnet_version} server info lacks the connection "
                                   f"fields ({len(payload)} of {full} bytes)")
        return ServerInfo(_decode_name(name), app_version, natnet_version)
    frequency, port, multicast, group = _SERVER_CONNECTION.unpack_from(payload, _SENDER.size)
    return ServerInfo(_decode_name(name), app_version, natnet_version, clock_frequency=frequency,
                      data_port=port, multicast=bool(multicast),
                      multicast_group=str(ipaddress.IPv4Address(group)))


# --- frame of data: parsing ----------------------------------------------------------------------

class _Reader:
    """Sequential reads from a payload; every shortfall raises NatNetParseError."""

    def __init__(self, data: bytes):
        self.data = data
        self.offset = 0

    @property
    def remaining(self) -> int:
        return len(self.data) - self.offset

    def unpack(self, layout: struct.Struct, what: str) -> tuple:
        if layout.size > self.remaining:
            raise NatNetParseError(f"truncated frame: {what} needs {layout.size} bytes at offset "
                                   f"{self.offset}, {self.remaining} left")
        values = layout.unpack_from(self.data, self.offset)
        self.offset += layout.size
        return values

    def count(self, what: str, min_item_size: int) -> int:
        """A non-negative int32 count whose items can fit in the bytes left, within
        :data:`ITEM_LIMITS`."""
        (count,) = self.unpack(_I32, f"{what} count")
        if count < 0 or count * min_item_size > self.remaining:
            raise NatNetParseError(f"implausible {what} count {count} with {self.remaining} bytes "
                                   f"left")
        _check_limit(what, count)
        return count

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise NatNetParseError(f"truncated frame: {what} at offset {self.offset} has no NUL")
        text = self.data[self.offset:end].decode("utf-8", errors="replace")
        self.offset = end + 1
        return text

    def skip(self, size: int):
        self.offset += size


def _check_version(version: Sequence[int]) -> bool:
    """True if ``version`` uses the 4.1 layout; NatNetParseError if it is not supported."""
    key = tuple(version[:2])
    if key not in _SUPPORTED_KEYS:
        supported = ", ".join(f"{v.major}.{v.minor}" for v in SUPPORTED_VERSIONS)
        raise NatNetParseError(f"unsupported NatNet stream version {'.'.join(map(str, version))}; "
                               f"supported: {supported} (request one with 'Bitstream,4.1')")
    return key >= (4, 1)


def _check_limit(what: str, count: int):
    """NatNetParseError if ``count`` items of ``what`` are more than a server sends."""
    if count > ITEM_LIMITS[what]:
        raise NatNetParseError(f"{what} count {count} is above the {ITEM_LIMITS[what]} a NatNet server "
                               f"sends (NatNetTypes.h)")


def _read_section(reader: _Reader, sized: bool, what: str, min_item_size: int,
                  read_item: Callable[[_Reader], T]) -> Tuple[T, ...]:
    """A data set: count, the 4.1 byte size, then the items; the size must match what was read."""
    (count,) = reader.unpack(_I32, f"{what} count")
    available = reader.remaining
    if sized:
        (size,) = reader.unpack(_I32, f"{what} byte size")
        if not 0 <= size <= reader.remaining:
            raise NatNetParseError(f"{what} byte size {size} exceeds the {reader.remaining} "
                                   f"bytes left")
        available = size
    if count < 0 or count * min_item_size > available:
        raise NatNetParseError(f"implausible {what} count {count} with {available} bytes left")
    _check_limit(what, count)
    start = reader.offset
    items = tuple(read_item(reader) for _ in range(count))
    if sized and reader.offset - start != available:
        raise NatNetParseError(f"{what} byte size says {available} but its {count} items take "
                               f"{reader.offset - start}")
    return items


def _read_vector(reader: _Reader) -> Vector3:
    return reader.unpack(_VECTOR3, "marker position")


def _read_marker_set(reader: _Reader) -> MarkerSet:
    name = reader.cstring("marker set name")
    count = reader.count("marker set marker", _VECTOR3.size)
    return MarkerSet(name, tuple(_read_vector(reader) for _ in range(count)))


def _read_rigid_body(reader: _Reader) -> RigidBody:
    body_id, x, y, z, qx, qy, qz, qw, error, params = reader.unpack(_RIGID_BODY, "rigid body")
    return RigidBody(body_id, (x, y, z), (qx, qy, qz, qw), error, params)


def _read_skeleton(reader: _Reader) -> Skeleton:
    (skeleton_id,) = reader.unpack(_I32, "skeleton id")
    count = reader.count("skeleton rigid body", _RIGID_BODY.size)
    return Skeleton(skeleton_id, tuple(_read_rigid_body(reader) for _ in range(count)))


def _read_labeled_marker(reader: _Reader) -> LabeledMarker:
    marker_id, x, y, z, size, params, residual = reader.unpack(_LABELED_MARKER, "labelled marker")
    return LabeledMarker(marker_id, (x, y, z), size, params, residual)


def _read_analog(reader: _Reader) -> AnalogData:
    (analog_id,) = reader.unpack(_I32, "analog id")
    channels = []
    for _ in range(reader.count("analog channel", _I32.size)):
        samples = reader.count("analog sample", _FLOAT.size)
        channels.append(tuple(reader.unpack(_FLOAT, "analog sample")[0] for _ in range(samples)))
    return AnalogData(analog_id, tuple(channels))


def _skip_assets(reader: _Reader):
    """The 4.1 asset data set, skipped with its byte size (as the SDK's PacketClient does)."""
    (count,) = reader.unpack(_I32, "asset count")
    (size,) = reader.unpack(_I32, "asset byte size")
    if not 0 <= size <= reader.remaining or count < 0 or count * _MIN_ASSET_SIZE > size:
        raise NatNetParseError(f"implausible asset data set: {count} assets in {size} bytes with "
                               f"{reader.remaining} bytes left")
    reader.skip(size)


def parse_frame_of_data(data: bytes, version: Sequence[int]) -> FrameOfData:
    """Decode a NAT_FRAMEOFDATA datagram sent with stream ``version`` (from ``ServerInfo``).

    Raises NatNetParseError, and nothing else, for an unsupported version, another message type,
    truncation, implausible counts, 4.1 byte sizes that disagree with the content, or trailing
    bytes other than the 4-byte end-of-data tag.
    """
    sized = _check_version(version)
    reader = _Reader(_expect(data, MessageId.NAT_FRAMEOFDATA))
    (frame_number,) = reader.unpack(_I32, "frame number")
    marker_sets = _read_section(reader, sized, "marker set", 1 + _I32.size, _read_marker_set)
    unlabeled = _read_section(reader, sized, "unlabelled marker", _VECTOR3.size, _read_vector)
    rigid_bodies = _read_section(reader, sized, "rigid body", _RIGID_BODY.size, _read_rigid_body)
    skeletons = _read_section(reader, sized, "skeleton", 2 * _I32.size, _read_skeleton)
    if sized:
        _skip_assets(reader)
    labeled = _read_section(reader, sized, "labelled marker", _LABELED_MARKER.size,
                            _read_labeled_marker)
    force_plates = _read_section(reader, sized, "force plate", 2 * _I32.size, _read_analog)
    devices = _read_section(reader, sized, "device", 2 * _I32.size, _read_analog)
    timecode, subframe, timestamp, mid_exposure, received, transmit = reader.unpack(
        _SUFFIX, "frame suffix")
    precision = reader.unpack(_PRECISION_TIMESTAMP, "precision timestamp") if sized else (0, 0)
    (params,) = reader.unpack(_PARAMS, "frame params")
    if reader.remaining not in (0, _END_OF_DATA.size):
        raise NatNetParseError(f"{reader.remaining} unexpected bytes after the frame params "
                               f"(only a {_END_OF_DATA.size}-byte end-of-data tag may follow)")
    return FrameOfData(
        frame_number=frame_number, rigid_bodies=rigid_bodies, labeled_markers=labeled,
        marker_sets=marker_sets, unlabeled_markers=unlabeled, skeletons=skeletons,
        force_plates=force_plates, devices=devices, timecode=timecode, timecode_subframe=subframe,
        timestamp=timestamp, camera_mid_exposure=mid_exposure, camera_data_received=received,
        transmit_timestamp=transmit, precision_timestamp_secs=precision[0],
        precision_timestamp_frac_secs=precision[1], params=params)


# --- frame of data: building ---------------------------------------------------------------------

def _pack_section(sized: bool, items: Sequence[T], pack_item: Callable[[T], bytes]) -> bytes:
    """Count, the 4.1 byte size of the packed items, then the items."""
    body = b"".join(pack_item(item) for item in items)
    return _I32.pack(len(items)) + (_I32.pack(len(body)) if sized else b"") + body


def _pack_vector(vector: Vector3) -> bytes:
    return _VECTOR3.pack(*vector)


def _pack_marker_set(marker_set: MarkerSet) -> bytes:
    return (_encode_cstring(marker_set.name, "marker set name") + _I32.pack(len(marker_set.markers))
            + b"".join(_pack_vector(vector) for vector in marker_set.markers))


def _pack_rigid_body(body: RigidBody) -> bytes:
    return _RIGID_BODY.pack(body.id, *body.position, *body.orientation, body.mean_error,
                            body.params)


def _pack_skeleton(skeleton: Skeleton) -> bytes:
    return (_I32.pack(skeleton.id) + _I32.pack(len(skeleton.rigid_bodies))
            + b"".join(_pack_rigid_body(body) for body in skeleton.rigid_bodies))


def _pack_labeled_marker(marker: LabeledMarker) -> bytes:
    return _LABELED_MARKER.pack(marker.id, *marker.position, marker.size, marker.params,
                                marker.residual)


def _pack_analog(analog: AnalogData) -> bytes:
    channels = b"".join(_I32.pack(len(samples)) + b"".join(_FLOAT.pack(s) for s in samples)
                        for samples in analog.channels)
    return _I32.pack(analog.id) + _I32.pack(len(analog.channels)) + channels


def build_frame_of_data(version: Sequence[int], frame: FrameOfData) -> bytes:
    """NAT_FRAMEOFDATA datagram for stream ``version``, ending with a zero end-of-data tag.

    4.1 frames get an empty asset data set. ValueError for an unsupported version, a precision
    timestamp on a pre-4.1 stream, values that do not fit their wire types, or more than 65535
    payload bytes.
    """
    try:
        sized = _check_version(version)
    except NatNetParseError as error:
        raise ValueError(str(error)) from None
    precision = (frame.precision_timestamp_secs, frame.precision_timestamp_frac_secs)
    if not sized and any(precision):
        raise ValueError(f"NatNet {'.'.join(map(str, version))} frames carry no precision "
                         f"timestamp; it must be zero")
    try:
        payload = b"".join((
            _I32.pack(frame.frame_number),
            _pack_section(sized, frame.marker_sets, _pack_marker_set),
            _pack_section(sized, frame.unlabeled_markers, _pack_vector),
            _pack_section(sized, frame.rigid_bodies, _pack_rigid_body),
            _pack_section(sized, frame.skeletons, _pack_skeleton),
            _EMPTY_ASSETS if sized else b"",
            _pack_section(sized, frame.labeled_markers, _pack_labeled_marker),
            _pack_section(sized, frame.force_plates, _pack_analog),
            _pack_section(sized, frame.devices, _pack_analog),
            _SUFFIX.pack(frame.timecode, frame.timecode_subframe, frame.timestamp,
                         frame.camera_mid_exposure, frame.camera_data_received,
                         frame.transmit_timestamp),
            _PRECISION_TIMESTAMP.pack(*precision) if sized else b"",
            _PARAMS.pack(frame.params),
            _END_OF_DATA.pack(0),
        ))
    except struct.error as error:
        raise ValueError(f"frame {frame.frame_number} does not fit the wire format: {error}") from None
    return build_packet(MessageId.NAT_FRAMEOFDATA, payload)


# --- stream bookkeeping --------------------------------------------------------------------------

class FrameFilter:
    """Accepts each frame of one stream once and in order; counts what it drops.

    A frame is accepted when its number is above the newest accepted one. Equal numbers are
    ``duplicates``; smaller ones are ``out_of_order`` (late UDP datagrams), except where the stream
    has started again (Motive restarted, a recorded take looped), counted in ``restarts``: a jump
    back by more than ``restart_gap`` frames, or ``restart_run`` frames in a row, each one more than
    the one before, that are more than ``reorder_window`` frames below the newest one. Late
    datagrams come alone or a few together, and close behind the newest; a take that loops after
    fewer than ``restart_gap`` frames counts up again from its start, far below it (each of its first
    ``restart_run - 1`` frames is refused as late).
    """

    def __init__(self, restart_gap: int = 1000, restart_run: int = 3, reorder_window: int = 10):
        if restart_gap < 1:
            raise ValueError(f"restart_gap must be a positive number of frames, got {restart_gap}")
        if restart_run < 2:
            raise ValueError(f"restart_run must be at least 2 frames, got {restart_run}")
        if not 0 <= reorder_window < restart_gap:
            raise ValueError(f"reorder_window must be in [0, restart_gap), got {reorder_window}")
        self.restart_gap, self.restart_run, self.reorder_window = restart_gap, restart_run, reorder_window
        self.reset()

    def reset(self):
        """Forget the stream (e.g. after reconnecting) and zero the counters."""
        self.newest: Optional[int] = None
        self.accepted = 0
        self.duplicates = 0
        self.out_of_order = 0
        self.restarts = 0
        self._run_last: Optional[int] = None   # the row of frames below the newest counting up:
        self._run_length = 0                   # its latest frame number and its length

    def accept(self, frame_number: int) -> bool:
        """True if the frame is new and should be used; False if it is dropped (and counted)."""
        if self.newest is not None and frame_number <= self.newest:
            if frame_number == self.newest:
                self.duplicates += 1
                return False
            behind = self.newest - frame_number
            restarted = behind > self.restart_gap or (
                behind > self.reorder_window and self._extend_run(frame_number) >= self.restart_run)
            if not restarted:
                self.out_of_order += 1
                return False
            self.restarts += 1
        self._run_last, self._run_length = None, 0
        self.newest = frame_number
        self.accepted += 1
        return True

    def _extend_run(self, frame_number: int) -> int:
        """Take ``frame_number`` (far below the newest) into the row of such frames, each one more
        than the one before, or start a row with it; the row's length."""
        follows = self._run_last is not None and frame_number == self._run_last + 1
        self._run_last, self._run_length = frame_number, self._run_length + 1 if follows else 1
        return self._run_length
