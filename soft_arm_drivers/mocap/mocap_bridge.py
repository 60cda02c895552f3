"""NatNet (OptiTrack Motive) motion-capture client for the arm, without ROS.

:class:`MocapBridge` speaks NatNet over UDP (the codec is :mod:`soft_arm_drivers.mocap.natnet`):

- a command socket (bound to ``local_address``, any port) sends the connect request, the
  ``Bitstream,<major>.<minor>`` version request and, in unicast, a keep-alive every
  ``keepalive_period``; all of it goes to ``server_address:command_port`` only;
- a data socket bound to ``data_port`` receives the frames; with ``multicast_group`` set it joins
  that group on ``multicast_interface`` (Motive's multicast mode). Frames are taken from both
  sockets, because unicast servers differ in where they send them: Motive's own Python sample
  reads them on its command socket (the address the connect came from), other servers send them to
  the client's data port.

Each frame is read for the stream version the server announced (or the one it accepted after the
version request) by :func:`~.natnet_scan.scan_frame_of_data` (one compiled pass over the bytes: a
frame's cost does not depend on what its sender packed into it), passed through
:class:`~soft_arm_drivers.mocap.natnet.FrameFilter` (duplicates and late frames are dropped), and
the arm's markers are selected: rigid bodies or labelled markers by id, ordered base to tip
(``ids``). They are transformed into ``arm_base`` with the calibration
``p_arm = R p_mocap + t`` (the pose of the mocap system's frame in ``arm_base``) and stamped with
the mid-exposure time on the local clock (see :class:`ClockMap`); a frame whose ticks are
impossible (its server latency, or its exposure mapped onto the local clock, beyond what a
transport delay explains) is counted ``invalid``.

A selected marker that is occluded (labelled marker with the occluded bit, rigid body without the
tracking-valid bit), absent or not a finite position is an *unseen* marker: the frame is delivered
with NaN in its row, never filled in (``partial`` counts such frames, :attr:`MocapBridge.unseen`
each marker's). A frame in which no selected marker was seen is skipped and recorded in
:attr:`MocapBridge.last_skipped`. Every datagram ends in exactly one of :data:`PACKET_OUTCOMES`
(malformed, truncated and unknown packets included; the handler never raises for received bytes),
and the counts are in :attr:`MocapBridge.counters` for diagnostics.

The configuration is ``rig.mocap`` in ``config/mocap.yaml`` (ROS parameter layout), validated with
:data:`MOCAP_SCHEMA` by :func:`load_mocap_config`; a bad value raises ConfigError naming
``rig.mocap.<key>``, the value and what is allowed.
"""
from __future__ import annotations

import math
import select
import socket
import struct
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from .bridge_config import BridgeConfig
from .clock_map import ClockMap
from .natnet import (SUPPORTED_VERSIONS, FrameFilter, MessageId, NatNetParseError, ServerInfo, Version,
                     build_connect_request, build_packet, build_request, parse_packet, parse_server_info)
from .natnet_scan import FrameScan, scan_frame_of_data, warm_up

__all__ = ["MarkerFrame", "MocapBridge", "PACKET_OUTCOMES", "SkippedFrame"]

#: What becomes of a received datagram; each one is counted in exactly one of these.
PACKET_OUTCOMES = ("delivered", "occluded", "missing", "invalid", "duplicates", "out_of_order",
                   "malformed", "before_handshake", "control")
_RECV_SIZE = 65535
_MAX_BATCH = 256          # datagrams read from one socket per poll, so that no socket starves
_RESPONSE_CODE = struct.Struct("<i")


# --- calibration ---------------------------------------------------------------------------------


# --- configuration -------------------------------------------------------------------------------


def _name(version: Version) -> str:
    """``major.minor`` of a NatNet version."""
    return f"{version.major}.{version.minor}"


# --- clock mapping -------------------------------------------------------------------------------


# --- bridge --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MarkerFrame:
    """The arm's markers in one mocap frame: ``markers`` (n, 3) [m] in ``arm_base``, base to tip
    (NaN rows: markers the cameras did not see); ``stamp``: mid-exposure on the local clock [s];
    ``received_at``: when the datagram was read [s, local clock]; ``frame_number``: the server's."""

    stamp: float
    markers: np.ndarray
    frame_number: int
    received_at: float

    @property
    def latency(self) -> float:
        """Mid-exposure to reception [s]."""
        return self.received_at - self.stamp


# s: a change of the local clock against the steady one between two frames larger than this is a step
# of the local clock (NTP slews at most 0.5 ms per second; a step is 0.128 s or more)
LOCAL_STEP = 0.01


@dataclass(frozen=True)
class SkippedFrame:
    """A frame that was not delivered: its number, the reason (``occluded``, ``missing`` or
    ``invalid``) and the selected ids concerned (empty for ``invalid``)."""

    frame_number: int
    reason: str
    ids: tuple


class MocapBridge:
    """NatNet client that turns frames into :class:`MarkerFrame` s of the arm.

    ``clock()`` is the local clock the stamps are mapped onto [s] (default ``time.time``; the ROS node
    passes its clock); ``timer()`` the clock of the bridge's own timeouts [s] (the silence before a
    reconnect, the version request, the keep-alives; default ``clock``: the node passes
    ``time.monotonic``, so that a step of its clock neither holds them off for the step's length nor
    fires them early). Opens the sockets (OSError if they cannot be bound); :meth:`connect` starts
    the handshake and :meth:`poll` does the rest: read datagrams, handle them, resend the connect
    request when the server is silent for ``timeout``, send unicast keep-alives.

    Usage::

        with MocapBridge(BridgeConfig(command_port=emulator.command_port, data_port=0)) as bridge:
            bridge.connect()
            while True:
                for frame in bridge.poll(timeout=0.1):
                    use(frame.stamp, frame.markers)
    """

    def __init__(self, config: BridgeConfig, clock: Callable[[], float] = time.time,
                 timer: Optional[Callable[[], float]] = None):
        self.config = config
        self._clock = clock
        self._timer = clock if timer is None else timer
        self._wanted = {marker_id: k for k, marker_id in enumerate(config.ids)}
        self._server = (config.server_address, config.command_port)
        self._counts = dict.fromkeys(PACKET_OUTCOMES + ("restarts", "lost", "foreign", "partial",
                                                        "socket_errors", "connect_requests",
                                                        "local_clock_steps", "implausible"), 0)
        self._unseen = np.zeros(len(self._wanted), dtype=int)
        self._filter = FrameFilter()
        self._outbox: deque = deque(maxlen=8)
        self.state = "disconnected"
        self.note = ""
        self.server_info: Optional[ServerInfo] = None
        self.version: Optional[Version] = None
        self.clock_map: Optional[ClockMap] = None
        self.last_skipped: Optional[SkippedFrame] = None
        self._last_heard = self._last_connect = self._last_keepalive = self._asked_at = -math.inf
        self._skew: Optional[float] = None    # the local clock less the steady one at the last frame [s]
        self._command = self._data = None
        warm_up()                       # compile the frame reader now, not at the first frame
        try:
            self._command = self._open_command_socket()
            self._data = self._open_data_socket()
        except OSError:
            self.close()
            raise

    # -- sockets --

    def _open_command_socket(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            sock.setblocking(False)
            sock.bind((self.config.local_address, 0))
        except OSError:
            sock.close()
            raise
        return sock

    def _open_data_socket(self) -> socket.socket:
        c = self.config
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            sock.setblocking(False)
            if c.multicast:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(("", c.data_port))
                interface = c.multicast_interface or c.local_address
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                                socket.inet_aton(c.multicast_group) + socket.inet_aton(interface))
            else:
                sock.bind((c.local_address, c.data_port))
        except OSError:
            sock.close()
            raise
        return sock

    @property
    def command_address(self) -> tuple:
        """(host, port) of the command socket: where unicast servers may send frames."""
        return self._command.getsockname()

    @property
    def data_address(self) -> tuple:
        """(host, port) of the data socket."""
        return self._data.getsockname()

    def close(self):
        """Tell a unicast server that this client leaves, close the sockets (idempotent)."""
        if self._command is not None and self._command.fileno() >= 0 \
                and self.server_info is not None and not self.config.multicast:
            self._send(build_packet(MessageId.NAT_DISCONNECT))
        for sock in (self._command, self._data):
            if sock is not None:
                sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- protocol --

    def connect(self):
        """Send the connect request now (the handshake finishes in :meth:`poll`)."""
        self.state = "connecting"
        self._send_connect(self._timer())

    def _send_connect(self, now: float):
        self._counts["connect_requests"] += 1
        self._last_connect = now
        self._send(build_connect_request(bitstream_version=self.config.requested_version))

    def _send(self, packet: bytes):
        try:
            self._command.sendto(packet, self._server)
        except OSError:
            self._counts["socket_errors"] += 1

    def _service(self, now: float):
        """Queued requests out; reconnect after ``timeout`` of silence; unicast keep-alives."""
        while self._outbox:
            self._send(self._outbox.popleft())
        c = self.config
        if self.state == "disconnected":
            return
        if self.state == "negotiating" and now - self._asked_at > c.timeout:
            self._keep_served_version("did not answer the request for")
        if now - max(self._last_heard, self._last_connect) > c.timeout:
            if self.state in ("streaming", "negotiating"):
                self.state = "stale"
                self.note = f"nothing from the server for {c.timeout:g} s; reconnecting"
            self._send_connect(now)
        if not c.multicast and self.server_info is not None \
                and now - self._last_keepalive >= c.keepalive_period:
            self._last_keepalive = now
            self._send(build_packet(MessageId.NAT_KEEPALIVE))

    def poll(self, timeout: float = 0.0) -> list:
        """Wait up to ``timeout`` [s] for datagrams, handle those queued for at most
        ``poll_budget`` [s] (and :data:`_MAX_BATCH` per socket; the rest wait in the socket for the
        next poll), and return the :class:`MarkerFrame` s they gave, in the order they were read.
        Datagrams from another host than ``server_address`` are counted as ``foreign`` and
        dropped."""
        self._service(self._timer())
        try:
            ready, _, _ = select.select([self._command, self._data], [], [], timeout)
        except (OSError, ValueError):       # a socket closed by another thread
            return []
        frames = []
        deadline = time.perf_counter() + self.config.poll_budget
        for sock in ready:
            for _ in range(_MAX_BATCH):
                if time.perf_counter() > deadline:
                    break
                try:
                    data, (host, _) = sock.recvfrom(_RECV_SIZE)
                except BlockingIOError:
                    break
                except OSError:
                    self._counts["socket_errors"] += 1
                    break
                received_at, steady = self._clock(), self._timer()
                if host != self.config.server_address:
                    self._counts["foreign"] += 1
                    continue
                frame = self.handle_packet(data, received_at, steady)
                if frame is not None:
                    frames.append(frame)
        if self._outbox:
            self._service(self._timer())
        return frames

    def handle_packet(self, data: bytes, received_at: float,
                      steady: Optional[float] = None) -> Optional[MarkerFrame]:
        """Handle one datagram read at ``received_at`` [s, local clock] (and ``steady`` [s] on the
        timeouts' clock, read with it; None: read now); the arm's markers if it was a new, complete
        frame, else None. Never raises for any bytes; each datagram is counted in
        exactly one of :data:`PACKET_OUTCOMES`. Replies it needs (the version request) are queued
        and sent by :meth:`poll`. Only a datagram that parses counts as the server heard: a stream
        this bridge cannot read (a version switch whose answer was lost) goes stale and reconnects."""
        heard = received_at if self._timer is self._clock else (self._timer() if steady is None else steady)
        try:
            message_id, payload = parse_packet(data)
            if message_id == MessageId.NAT_FRAMEOFDATA:
                self._follow_local_clock(received_at - heard)
                frame = self._on_frame(data, received_at)
                self._last_heard = heard
                return frame
            if message_id == MessageId.NAT_SERVERINFO:
                self._on_server_info(parse_server_info(data), heard)
            elif message_id in (MessageId.NAT_RESPONSE, MessageId.NAT_UNRECOGNIZED_REQUEST):
                self._on_response(payload if message_id == MessageId.NAT_RESPONSE else None)
        except NatNetParseError as exc:
            self._counts["malformed"] += 1
            self.note = f"malformed packet: {exc}"
            return None
        self._last_heard = heard
        self._counts["control"] += 1
        return None

    def _on_server_info(self, info: ServerInfo, now: float):
        """A (new) stream: pick its version, request ours if it differs and the server can switch."""
        self.server_info = info
        self._new_filter()
        served = Version(info.natnet_version.major, info.natnet_version.minor)
        requested = self.config.requested_version
        self.version = served if served in SUPPORTED_VERSIONS else None
        self.clock_map = None
        self.state, self.note = "streaming", ""
        if not info.clock_frequency:
            self.version = None
            self.state, self.note = "unsupported", (f"unsupported NatNet version {_name(served)}: "
                                                    f"its server info has no clock frequency")
            return
        self.clock_map = ClockMap(info.clock_frequency, self.config.clock_window)
        if requested is not None and requested != served:
            if served >= (4, 0) and not self.config.multicast:
                self.state, self._asked_at = "negotiating", now
                self._outbox.append(build_request(f"Bitstream,{requested.major}.{requested.minor}"))
                return
            self.note = (f"NatNet {_name(served)} cannot switch to {_name(requested)} (multicast "
                         f"or before 4.0)")
        if self.version is None:
            self.state, self.note = "unsupported", f"unsupported NatNet version {_name(served)}"

    def _new_filter(self):
        """A fresh frame filter for a new stream; the old one's counts are kept."""
        for key in ("duplicates", "out_of_order", "restarts"):
            self._counts[key] += getattr(self._filter, key)
        self._filter = FrameFilter()

    def _on_response(self, payload: Optional[bytes]):
        """The answer to the version request: a NAT_RESPONSE int32 0 is success, anything else (or
        NAT_UNRECOGNIZED_REQUEST, ``payload`` None) a refusal."""
        if self.state != "negotiating":
            return
        if payload is not None and len(payload) == _RESPONSE_CODE.size \
                and _RESPONSE_CODE.unpack(payload)[0] == 0:
            self.version = self.config.requested_version
            self.state, self.note = "streaming", ""
            return
        self._keep_served_version("refused")

    def _keep_served_version(self, why: str):
        """The version request failed (``why``): stream the server's version if it is supported."""
        requested = _name(self.config.requested_version)
        if self.version is None:
            self.state, self.note = "unsupported", (f"the server {why} NatNet {requested} and streams "
                                                    f"an unsupported version")
        else:
            self.state, self.note = "streaming", (f"the server {why} NatNet {requested}; streaming "
                                                  f"{_name(self.version)}")

    def _follow_local_clock(self, skew: float):
        """``skew`` [s]: the local clock's reading less the timeouts' steady one at this read. A
        change of more than :data:`LOCAL_STEP` since the last frame is a step of the local clock (an
        NTP correction): the clock map starts again (counted, ``local_clock_steps``), for its window
        would keep the offset from before the step, and stamp every frame late (or early) by the
        step until it slid past. A single clock for both (the default) has no skew to follow."""
        if self._timer is self._clock:
            return
        if self._skew is not None and abs(skew - self._skew) > LOCAL_STEP and self.clock_map is not None:
            self.clock_map = ClockMap(self.clock_map.frequency, self.config.clock_window)
            self._counts["local_clock_steps"] += 1
        self._skew = skew

    def _on_frame(self, data: bytes, received_at: float) -> Optional[MarkerFrame]:
        if self.version is None:
            self._counts["before_handshake"] += 1
            return None
        frame = scan_frame_of_data(data, self.version)
        newest, restarts = self._filter.newest, self._filter.restarts
        if not self._filter.accept(frame.frame_number):
            return None                                     # counted by the filter
        if self._filter.restarts != restarts:
            self.clock_map = ClockMap(self.clock_map.frequency, self.config.clock_window)
        elif newest is not None:
            self._counts["lost"] += frame.frame_number - newest - 1
        reference = frame.transmit_timestamp or frame.camera_data_received or frame.camera_mid_exposure
        if self.state == "stale":
            self.state, self.note = "streaming", ""
        clock = self.clock_map
        if not 0 < frame.camera_mid_exposure <= reference \
                or (reference - frame.camera_mid_exposure) / clock.frequency > clock.max_delay:
            return self._skip(frame.frame_number, "invalid", ())      # impossible ticks
        clock.observe(reference, received_at)
        stamp = clock.to_local(frame.camera_mid_exposure)
        if not received_at - 2 * clock.max_delay <= stamp <= received_at + clock.tolerance:
            return self._skip(frame.frame_number, "invalid", ())      # exposed after, or long before, it came
        positions, problems = self._select(frame)
        if len(problems) == len(self._wanted):
            reason = "missing" if "missing" in problems.values() else "occluded"
            return self._skip(frame.frame_number, reason, tuple(problems))
        unseen = ~np.all(np.isfinite(positions), axis=1)
        for marker_id in problems:
            unseen[self._wanted[marker_id]] = True
        positions[unseen] = 0.0
        markers = self.config.calibration.to_arm(positions)
        unseen |= ~np.all(np.isfinite(markers), axis=1)          # finite, but beyond a double
        # no position of the arm: a calibration gone wrong, or Motive streaming millimetres
        distance = np.linalg.norm(np.where(unseen[:, None], 0.0, markers), axis=1)
        far = ~unseen & (distance > self.config.max_distance)
        if far.any():
            self._counts["implausible"] += int(far.sum())
            unseen |= far
            if unseen.all():
                self.note = (f"every marker beyond {self.config.max_distance:g} m of arm_base: the "
                             "calibration, or Motive's streaming units (metres wanted)?")
        if unseen.all():
            return self._skip(frame.frame_number, "invalid", ())
        markers[unseen] = np.nan
        self._counts["delivered"] += 1
        if unseen.any():
            self._counts["partial"] += 1
            self._unseen += unseen
        return MarkerFrame(stamp, markers, frame.frame_number, received_at)

    def _select(self, frame: FrameScan):
        """Positions (n, 3) in the mocap frame, base to tip, and {id: "occluded" | "missing"}: the
        first item of each wanted id (rigid bodies without the tracking-valid bit and labelled
        markers with the occluded bit are occluded)."""
        positions = np.zeros((len(self._wanted), 3))       # a missing marker's row stays zero
        if self.config.source == "rigid_bodies":
            items = frame.rigid_bodies
            occluded = (items["params"] & 1) == 0
        else:
            items = frame.labeled_markers
            occluded = (items["params"] & 1) != 0
        ids, problems = items["id"], {}
        for marker_id in self.config.ids:
            hits = np.flatnonzero(ids == marker_id)
            if hits.size == 0:
                problems[marker_id] = "missing"
                continue
            positions[self._wanted[marker_id]] = items["position"][hits[0]]
            if occluded[hits[0]]:
                problems[marker_id] = "occluded"
        return positions, problems

    @property
    def unseen(self) -> list:
        """How many delivered frames lacked each selected marker (base to tip)."""
        return self._unseen.tolist()

    def _skip(self, frame_number: int, reason: str, ids: tuple) -> None:
        self._counts[reason] += 1
        self.last_skipped = SkippedFrame(frame_number, reason, ids)
        return None

    @property
    def counters(self) -> dict:
        """Datagram outcomes (:data:`PACKET_OUTCOMES`, from the frame filter: ``duplicates``,
        ``out_of_order``) and ``packets`` (their sum), ``lost`` (frame numbers skipped by the
        stream: lost or late), ``partial`` (delivered frames with unseen markers), ``restarts`` (the
        stream's frame numbers jumped back), ``foreign``
        (datagrams from other hosts), ``socket_errors`` and ``connect_requests``."""
        counts = dict(self._counts)
        for key in ("duplicates", "out_of_order", "restarts"):
            counts[key] += getattr(self._filter, key)
        counts["packets"] = sum(counts[k] for k in PACKET_OUTCOMES)
        return counts
