"""A NatNet server emulator (OptiTrack Motive stand-in) streaming the simulated arm's markers.

It serves loopback only (127.0.0.0/8; a ValueError otherwise) over unicast UDP:

- on its command socket it answers a connect request with server info (its stream version, a
  high-resolution clock of ``clock_frequency`` ticks/s), registers the client, honours
  ``Bitstream,<major>.<minor>`` requests (NAT_RESPONSE int32 0, or -1 if refused), refreshes the
  client on keep-alives, forgets it on a disconnect or after ``client_timeout`` of silence, and
  answers other requests with NAT_UNRECOGNIZED_REQUEST. A version asked for in the connect request
  itself is ignored, as the SDK clients follow it with the Bitstream command anyway;
- it sends frames of data (stream version 3.0, 3.1, 4.0 or 4.1) to every client: to the address the
  client connected from (what Motive does in unicast, as its SDK's Python sample reads frames on the
  command socket) or, if ``data_port`` is set, to that port of the client's host.

Frames hold the arm's markers as rigid bodies (ids 1..n by default, position = marker, identity
orientation), labelled markers (asset 1: ids ``1 << 16 | k`` for k = 1..n) or both, plus
``extra_markers`` markers of another asset, in shuffled order, expressed in the mocap system's frame
(``calibration.to_mocap``, the inverse of the bridge's calibration). Each frame carries its
mid-exposure time in server ticks, the data-received and transmit ticks, and Motive's software
timestamp. Faults can be injected with a seeded :class:`Faults`.

Marker positions come from ``markers(t)``: (n, 3) [m] in ``arm_base`` at the mid-exposure time
``t`` [s, emulator clock], a NaN row for a marker the cameras did not see (it goes out occluded, as
Motive marks it: a rigid body without its tracking-valid bit, a labelled marker with its occluded
bit, position zero); :func:`plant_markers` reads a :class:`~.simulated_rig.Plant` (of a
``SimulatedRig``: ``rig.plant``). Either :meth:`NatNetEmulator.start` streams at ``rate`` on a
thread (real time), or ``start(stream=False)`` only serves requests and the caller sends each frame
with :meth:`NatNetEmulator.send_frame` (stepped, e.g. once per exposure of a ``SimulatedRig``). The
stream exposes on a fixed grid of ``1 / rate`` and sends each frame ``latency`` later.

A simulated arm in real time is held now and then by a loaded machine, and then catches up: at an
exposure time it may not be there yet. A real camera never sees an arm behind its stamp, so given
``reached(t)`` (whether the simulation has reached time t) the stream reads an exposure's markers
only once it has, and sends its frame then if that is after its due time; a frame whose exposure the
simulation does not reach within ``reach_timeout`` is not sent (counted ``unreached``; like an
exposure the stream's thread slept through, counted ``missed``, it takes its frame number, so that a
client sees the gap and counts the frame lost). Markers read
early instead would be the arm of some milliseconds before the stamp, and the next frame's the arm
caught up: a jump that the bridge measures as a speed the arm never had.
"""
from __future__ import annotations

import ipaddress
import random
import select
import socket
import struct
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from soft_arm_drivers.mocap.bridge_config import Calibration
from soft_arm_drivers.mocap.natnet import (SUPPORTED_VERSIONS, FrameOfData, LabeledMarker, MessageId,
                                           NatNetParseError, RigidBody, ServerInfo, Version,
                                           build_frame_of_data, build_packet, build_server_info, parse_packet)

__all__ = ["Faults", "NatNetEmulator", "plant_markers"]

LAYOUTS = ("rigid_bodies", "labeled_markers", "both")
_RESPONSE_CODE = struct.Struct("<i")
_ASSET = 1                 # asset of the arm's labelled markers
_OTHER_ASSET = 2           # asset of the extra markers
_TICK_BASE = 987_654_321   # the server clock's tick count at start (anything but zero)
_EXPOSURE_LOG = 4096       # frames whose exposure time is kept for exposure_time()
_OCCLUDED = 0x01           # labelled marker params bit 0
_REACH_POLL = 5e-4         # s: how often a frame waiting for the arm to reach its exposure looks again


@dataclass(frozen=True)
class Faults:
    """Per-frame probabilities of injected faults (seeded): ``occlusion`` (one of the arm's markers
    occluded: labelled marker flagged occluded, rigid body not tracked, position zero), ``absence``
    (one of the arm's markers left out), ``drop`` (frame not sent; its number is used up),
    ``duplicate`` (sent twice), ``reorder`` (held back and sent after the next frame)."""

    occlusion: float = 0.0
    absence: float = 0.0
    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    seed: int = 0

    def __post_init__(self):
        for name in ("occlusion", "absence", "drop", "duplicate", "reorder"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"Faults.{name} must be a probability in [0, 1], got {value!r}")


def plant_markers(plant) -> Callable[[float], np.ndarray]:
    """``markers(t)`` reading the true marker positions [m, arm_base] of a
    :class:`~.simulated_rig.Plant` at its last state sensed with markers (a ``SimulatedRig`` senses
    them at each of its mocap exposures)."""
    return lambda t: plant.markers()[0]


class NatNetEmulator:
    """NatNet server on ``address:command_port`` (port 0: a free one, see :attr:`command_port`).

    ``markers(t)``: the arm's markers (n, 3) [m] in ``arm_base`` at mid-exposure ``t`` [s].
    ``version``: the stream version ("3.1", (4, 1), ...). ``rate`` [Hz] of :meth:`start`'s stream.
    ``layout``: rigid_bodies, labeled_markers or both; ``rigid_body_ids`` and ``labeled_marker_ids``
    (one per marker, base to tip) and ``extra_markers`` of another asset, see the module doc.
    ``calibration``: the bridge's (frames go out in ``calibration.to_mocap`` coordinates).
    ``data_port``: None (frames to the client's command socket) or the client port frames go to; it
    is read at each frame, so it may be set after construction. ``clock()``: the emulator's clock [s]
    (default ``time.time``, the bridge's default, so that stamps can be compared);
    ``clock_frequency`` [ticks/s] of the emulated server clock; ``latency`` [s]: mid-exposure to
    transmit (Motive's processing). ``accept_bitstream``: whether version requests are honoured.
    ``client_timeout`` [s]: clients silent for longer (no keep-alive) get no more frames.
    ``reached(t)``: whether the arm has reached time ``t`` [s, emulator clock] (None: always);
    ``reach_timeout`` [s]: how long a streamed frame waits for it (see the module doc).
    Counters: :attr:`counters`.

    Wired to the bridge as the tests do (loopback, ephemeral ports)::

        config = load_mocap_config()
        emulator = NatNetEmulator(plant_markers(rig.plant), layout="both",
                                  calibration=config.calibration).start()
        bridge = MocapBridge(dataclasses.replace(config, command_port=emulator.command_port,
                                                 data_port=0))
        bridge.connect()          # then bridge.poll(timeout) in a loop

    Stepped instead of streamed: ``start(stream=False)`` (requests served on the thread), or no
    thread at all with :meth:`serve_requests` and :meth:`send_frame` called by the stepping loop.
    """

    def __init__(self, markers: Callable[[float], np.ndarray], *, version="4.1", rate: float = 240.0,
                 layout: str = "rigid_bodies", calibration: Optional[Calibration] = None,
                 rigid_body_ids: Optional[Sequence[int]] = None,
                 labeled_marker_ids: Optional[Sequence[int]] = None, extra_markers: int = 2,
                 address: str = "127.0.0.1", command_port: int = 0, data_port: Optional[int] = None,
                 clock: Callable[[], float] = time.time, clock_frequency: int = 10_000_000,
                 latency: float = 0.004, faults: Faults = Faults(), accept_bitstream: bool = True,
                 client_timeout: float = 10.0, app_name: str = "soft_arm NatNet emulator",
                 reached: Optional[Callable[[float], bool]] = None, reach_timeout: float = 0.5):
        self.version = _version(version)
        if not 1.0 <= rate <= 1000.0:
            raise ValueError(f"rate must be in [1, 1000] Hz, got {rate!r}")
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        if not ipaddress.IPv4Address(address).is_loopback:
            raise ValueError(f"the emulator serves loopback addresses only, got {address!r}")
        if not 0.0 <= latency <= 1.0 or clock_frequency <= 0 or extra_markers < 0:
            raise ValueError("latency must be in [0, 1] s, clock_frequency > 0, extra_markers >= 0")
        if not 0.0 < reach_timeout <= 10.0:
            raise ValueError(f"reach_timeout must be in (0, 10] s, got {reach_timeout!r}")
        self._markers = markers
        self._clock = clock
        self._reached, self.reach_timeout = reached, float(reach_timeout)
        self.n_markers = len(self._arm_markers(clock()))
        self.rigid_body_ids = tuple(rigid_body_ids or range(1, self.n_markers + 1))
        self.labeled_marker_ids = tuple(labeled_marker_ids or (
            _ASSET << 16 | k for k in range(1, self.n_markers + 1)))
        if len(self.rigid_body_ids) != self.n_markers or len(self.labeled_marker_ids) != self.n_markers:
            raise ValueError(f"give one id per marker ({self.n_markers})")
        self.rate, self.layout, self.latency = float(rate), layout, float(latency)
        self.calibration = calibration or Calibration.identity()
        self.extra_markers, self.data_port = extra_markers, data_port
        self.clock_frequency = int(clock_frequency)
        self.faults, self.accept_bitstream = faults, accept_bitstream
        self.client_timeout, self.app_name = client_timeout, app_name
        self.counters = dict.fromkeys(("connects", "requests", "bad_requests", "frames", "sent",
                                       "dropped", "duplicated", "reordered", "occluded", "absent",
                                       "missed", "unreached"), 0)
        self._rng = random.Random(faults.seed)
        self._start = clock()
        self._frame_number = 0
        self._held: Optional[bytes] = None
        self._clients: dict = {}             # address -> last heard (monotonic)
        self._exposures: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            self._socket.bind((address, command_port))
        except OSError:
            self._socket.close()
            raise
        self._socket.setblocking(False)

    # -- life cycle --

    @property
    def command_address(self) -> tuple:
        return self._socket.getsockname()

    @property
    def command_port(self) -> int:
        return self._socket.getsockname()[1]

    @property
    def clients(self) -> list:
        """Addresses of the connected clients."""
        with self._lock:
            return list(self._clients)

    def start(self, stream: bool = True) -> "NatNetEmulator":
        """Serve requests on a thread and, if ``stream``, send frames at ``rate``."""
        if self._thread is not None:
            raise RuntimeError("the emulator is already running")
        self._thread = threading.Thread(target=self._run, args=(stream,), name="natnet-emulator",
                                        daemon=True)
        self._thread.start()
        return self

    def close(self):
        """Stop the thread and close the socket (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._socket.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _run(self, stream: bool):
        """Serve requests; streaming, expose a frame on a fixed grid of periods, as cameras do
        (stamped with the grid time; exposures the thread slept through are counted as missed) and
        send it ``latency`` later, or once the arm has reached its exposure (module doc)."""
        period = 1.0 / self.rate
        due = time.monotonic()
        # [send time [monotonic s], exposure time [s], markers or None, frame number]
        pending: deque = deque()
        while not self._stop.is_set():
            wake = min(due, pending[0][0]) if pending else due
            if pending and pending[0][2] is None:      # its arm not there yet: look again shortly
                wake = min(due, max(wake, time.monotonic() + _REACH_POLL))
            wait = max(0.0, wake - time.monotonic()) if stream else 0.05
            try:
                ready, _, _ = select.select([self._socket], [], [], wait)
            except (OSError, ValueError):          # closed under us
                return
            if ready:
                self.serve_requests()
            if not stream:
                continue
            now = time.monotonic()
            if now >= due:
                late = now - due
                if late >= period:             # held past whole periods: those exposures are lost
                    missed = int(late // period)
                    self.counters["missed"] += missed
                    self._numbers(missed)
                    due, late = due + missed * period, late - missed * period
                exposure = self._clock() - late    # on the camera's grid
                pending.append([due + self.latency, exposure, self._exposed(exposure), self._numbers(1)])
                due += period
            while pending and time.monotonic() >= pending[0][0]:
                send_at, exposure, markers, number = pending[0]
                if markers is None:
                    markers = pending[0][2] = self._exposed(exposure)
                if markers is None:
                    if time.monotonic() - send_at < self.reach_timeout:
                        break
                    self.counters["unreached"] += 1
                else:
                    self._send(number, markers, exposure, self._clock())
                pending.popleft()

    # -- requests --

    def serve_requests(self):
        """Answer every queued request (the thread of :meth:`start` calls this)."""
        while True:
            try:
                data, address = self._socket.recvfrom(65535)
            except (BlockingIOError, OSError):
                return
            self.counters["requests"] += 1
            try:
                message_id, payload = parse_packet(data)
            except NatNetParseError:
                self.counters["bad_requests"] += 1
                continue
            reply = self._answer(message_id, payload, address)
            if reply is not None:
                self._socket.sendto(reply, address)

    def _answer(self, message_id: MessageId, payload: bytes, address) -> Optional[bytes]:
        now = time.monotonic()
        with self._lock:
            if message_id == MessageId.NAT_CONNECT:
                self.counters["connects"] += 1
                self._clients[address] = now
                return build_server_info(ServerInfo(
                    self.app_name, Version(3, 1, 0, 0), self.version,
                    clock_frequency=self.clock_frequency, data_port=self.data_port or 0,
                    multicast=False, multicast_group="0.0.0.0"))
            if message_id == MessageId.NAT_KEEPALIVE:
                if address in self._clients:
                    self._clients[address] = now
                return None
            if message_id == MessageId.NAT_DISCONNECT:
                self._clients.pop(address, None)
                return None
            if message_id == MessageId.NAT_REQUEST:
                command = payload.split(b"\0", 1)[0].decode("utf-8", errors="replace")
                if command.startswith("Bitstream,"):
                    return build_packet(MessageId.NAT_RESPONSE,
                                        _RESPONSE_CODE.pack(self._switch(command[len("Bitstream,"):])))
            self.counters["bad_requests"] += 1
            return build_packet(MessageId.NAT_UNRECOGNIZED_REQUEST)

    def _switch(self, text: str) -> int:
        """Switch the stream version for a Bitstream request: 0 on success, -1 if refused."""
        try:
            version = _version(text)
        except ValueError:
            return -1
        if not self.accept_bitstream:
            return -1
        self.version = version
        return 0

    # -- frames --

    def ticks(self, t: float) -> int:
        """Time ``t`` [s, emulator clock] in ticks of the emulated server clock."""
        return _TICK_BASE + int(round((t - self._start) * self.clock_frequency))

    def exposure_time(self, frame_number: int) -> Optional[float]:
        """Mid-exposure time [s, emulator clock] of one of the last frames built, else None."""
        with self._lock:
            return self._exposures.get(frame_number)

    def send_frame(self, markers=None, exposure_time: Optional[float] = None,
                   transmit_offset: float = 0.0) -> int:
        """Build the next frame and send it to every client (faults permitting); its number.

        ``markers`` (n, 3) [m, arm_base] default to ``markers(exposure_time)``; ``exposure_time``
        [s, emulator clock] defaults to now minus ``latency``; ``transmit_offset`` [s] moves the
        frame's transmit and data-received ticks (a frame whose server stamps are wrong).
        """
        now = self._clock()
        exposure = now - self.latency if exposure_time is None else float(exposure_time)
        arm = self._arm_markers(exposure) if markers is None else np.asarray(markers, dtype=float)
        if arm.shape != (self.n_markers, 3):
            raise ValueError(f"markers must be ({self.n_markers}, 3) [m], got {arm.shape}")
        return self._send(self._numbers(1), arm, exposure, now, transmit_offset)

    def _numbers(self, count: int) -> int:
        """Take the next ``count`` frame numbers; the last. Frames of the stream's grid that are
        not sent take theirs all the same, as Motive's do: a client sees the gap and counts them
        lost."""
        with self._lock:
            self._frame_number += count
            return self._frame_number

    def _send(self, number: int, arm: np.ndarray, exposure: float, now: float,
              transmit_offset: float = 0.0) -> int:
        """Build frame ``number`` of ``arm`` exposed at ``exposure`` [s] and send it to every client
        (faults permitting); its number."""
        with self._lock:
            self._exposures[number] = exposure
            if len(self._exposures) > _EXPOSURE_LOG:
                self._exposures.popitem(last=False)
            self._expire_clients()
            packet = build_frame_of_data(self.version, self._frame(number, arm, exposure, now,
                                                                   transmit_offset))
            self.counters["frames"] += 1
            for datagram in self._faulty(packet):
                for address in self._clients:
                    destination = address if self.data_port is None else (address[0], self.data_port)
                    self._socket.sendto(datagram, destination)
                    self.counters["sent"] += 1
        return number

    def _exposed(self, t: float) -> Optional[np.ndarray]:
        """The arm's markers at exposure time ``t`` [s], None while the arm has not reached it."""
        if self._reached is not None and not self._reached(t):
            return None
        return self._arm_markers(t)

    def _arm_markers(self, t: float) -> np.ndarray:
        arm = np.asarray(self._markers(t), dtype=float)
        if arm.ndim != 2 or arm.shape[1] != 3 or len(arm) != getattr(self, "n_markers", len(arm)) \
                or len(arm) == 0:
            raise ValueError(f"markers(t) must return (n, 3) positions [m] of the same n, got shape "
                             f"{arm.shape}")
        return arm

    def _expire_clients(self):
        deadline = time.monotonic() - self.client_timeout
        for address in [a for a, heard in self._clients.items() if heard < deadline]:
            del self._clients[address]

    def _frame(self, number: int, arm: np.ndarray, exposure: float, now: float,
               transmit_offset: float = 0.0) -> FrameOfData:
        """The frame in the mocap system's frame, with the occlusion and absence faults; its
        transmit ticks ``transmit_offset`` [s] off."""
        positions = [tuple(float(v) for v in p) for p in self.calibration.to_mocap(arm)]
        visible = [bool(np.all(np.isfinite(p))) for p in positions]       # NaN: the cameras missed it
        present = [True] * self.n_markers
        if self._rng.random() < self.faults.occlusion:
            visible[self._rng.randrange(self.n_markers)] = False
            self.counters["occluded"] += 1
        if self._rng.random() < self.faults.absence:
            present[self._rng.randrange(self.n_markers)] = False
            self.counters["absent"] += 1
        bodies, labelled = [], []
        for k in range(self.n_markers):
            if not present[k]:
                continue
            position = positions[k] if visible[k] else (0.0, 0.0, 0.0)
            bodies.append(RigidBody(self.rigid_body_ids[k], position, (0.0, 0.0, 0.0, 1.0),
                                    params=int(visible[k])))
            labelled.append(LabeledMarker(self.labeled_marker_ids[k], position, 0.014,
                                          0 if visible[k] else _OCCLUDED))
        labelled += [LabeledMarker(_OTHER_ASSET << 16 | k, (0.1 * k, 1.0, 0.5), 0.014)
                     for k in range(1, self.extra_markers + 1)]
        bodies += [RigidBody(100 + k, (0.1 * k, 1.0, 0.5), (0.0, 0.0, 0.0, 1.0))
                   for k in range(1, self.extra_markers + 1)]
        self._rng.shuffle(bodies)
        self._rng.shuffle(labelled)
        mid = self.ticks(exposure)
        transmit = max(self.ticks(now + transmit_offset), mid)
        return FrameOfData(
            frame_number=number,
            rigid_bodies=tuple(bodies) if self.layout != "labeled_markers" else (),
            labeled_markers=tuple(labelled) if self.layout != "rigid_bodies" else (),
            timestamp=exposure - self._start, camera_mid_exposure=mid,
            camera_data_received=(mid + transmit) // 2, transmit_timestamp=transmit)

    def _faulty(self, packet: bytes) -> list:
        """The datagrams to send now for ``packet``, after the drop, duplicate and reorder faults;
        a datagram held back by a reorder goes out after the next frame."""
        f, rng = self.faults, self._rng
        out = []
        if rng.random() < f.drop:
            self.counters["dropped"] += 1
        else:
            out.append(packet)
            if rng.random() < f.duplicate:
                self.counters["duplicated"] += 1
                out.append(packet)
        if self._held is not None:
            out.append(self._held)
            self._held = None
        elif out and rng.random() < f.reorder:
            self.counters["reordered"] += 1
            self._held = out.pop()
        return out


def _version(value) -> Version:
    """A supported stream version from "4.1", (4, 1) or a Version; ValueError otherwise."""
    if isinstance(value, str):
        try:
            parts = tuple(int(p) for p in value.split("."))
        except ValueError:
            raise ValueError(f"not a NatNet version: {value!r}") from None
    else:
        parts = tuple(value)
    version = Version(*parts[:2]) if len(parts) >= 2 else None
    if version not in SUPPORTED_VERSIONS:
        supported = ", ".join(f"{v.major}.{v.minor}" for v in SUPPORTED_VERSIONS)
        raise ValueError(f"unsupported NatNet version {value!r}; supported: {supported}")
    return version
