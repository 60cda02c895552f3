"""A CAN bus between two processes of one machine: python-can's ``soft_arm_loopback`` interface.

python-can's ``virtual`` bus does not leave its process, SocketCAN's ``vcan`` needs a kernel module
that containers and CI machines often lack, and ``udp_multicast`` sends to a multicast group. This
bus carries CAN 2.0 frames as UDP datagrams between two ends on 127.0.0.1 only: ``channel`` is
``"LOCAL:PEER"``, the UDP port this end binds and the one the other end binds (the other end's
channel is ``"PEER:LOCAL"``). It is registered as a python-can plugin (entry point group
``can.interface``), so ``can.Bus(interface="soft_arm_loopback", channel="29536:29537")`` opens it
and the motor driver takes it from ``rig.motors.interface`` like any other interface.

Like a bus without the other node on it, a frame sent while the other end is not listening is lost;
the sender does not know (the motor driver's watchdog notices the silence). Each datagram carries a
sequence number and its sender's epoch (a random number drawn when the sender opens the bus, which
tells a restarted sender from the one before it): frames that never arrived or arrived out of order
are counted (``lost``, ``reordered``; a new epoch starts a new count). A received frame's
``timestamp`` [s, system time] is the sender's (the time it was sent, or the message's own with
``preserve_timestamps``), like a hardware bus's receive stamp up to the loopback's latency; frames
are delivered in the order they were sent.
"""
from __future__ import annotations

import os
import random
import select
import socket
import struct
import time

import can

from soft_arm_ros.localhost_discovery import DOMAIN_GAIN, PORT_BASE

INTERFACE = "soft_arm_loopback"
HOST = "127.0.0.1"
# sender's epoch, sequence number, time stamp [s], arbitration id, dlc, flags, 8 data bytes
_WIRE = struct.Struct("<IIdIBB8s")
_EXTENDED, _REMOTE, _ERROR = 1, 2, 4
# bytes of the socket's receive buffer (the kernel caps it at net.core.rmem_max): some 1300 frames,
# over half a second of the rig's 2000 frames/s, so that a reader that stalls loses none
RECEIVE_BUFFER = 1 << 20
_LOWEST_DRAWN = 20000       # free_udp_ports draws from here up to the ephemeral range
# DDS (RTPS) binds PORT_BASE + DOMAIN_GAIN d + offset for domain d: 0-1 multicast, 10 + 2 p and
# 11 + 2 p unicast for participant p. The ports drawn keep clear of the offsets of the first 60
# participants of any domain (the draw's range holds domains 51-101's, where a test run or a lab
# may be).
_DDS_OFFSETS = 130


def free_udp_ports(n: int = 2) -> list:
    """``n`` different UDP ports of 127.0.0.1, each free a moment ago: a channel's two ends, an
    emulated server's port.

    They are drawn below the kernel's ephemeral range (``net.ipv4.ip_local_port_range``), where no
    socket bound to port 0 is given a port, and clear of the ports DDS binds: a port drawn in the
    ephemeral range is handed to any other process's socket between this call and the bind of
    whoever it is for (a graph's node binds it seconds later, after its imports), and that bind then
    fails. Two callers can still draw the same port (about one chance in 6000 per pair). Where the
    range leaves too little below it, the ports are the kernel's (bound to port 0 together, then
    released)."""
    low = _ephemeral_low()
    if low - _LOWEST_DRAWN >= 1000:
        rng = random.SystemRandom()
        ports = []
        for _ in range(64 * n):
            port = rng.randrange(_LOWEST_DRAWN, low)
            if (port - PORT_BASE) % DOMAIN_GAIN >= _DDS_OFFSETS and port not in ports \
                    and _bindable(port):
                ports.append(port)
                if len(ports) == n:
                    return ports
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        for sock in socks:
            sock.bind((HOST, 0))
        return [sock.getsockname()[1] for sock in socks]
    finally:
        for sock in socks:
            sock.close()


def _ephemeral_low(path: str = "/proc/sys/net/ipv4/ip_local_port_range") -> int:
    """The first port of the kernel's ephemeral range (32768, Linux's default, if unreadable)."""
    try:
        with open(path, encoding="ascii") as fh:
            return int(fh.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _bindable(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((HOST, port))
        except OSError:
            return False
    return True


def parse_channel(channel) -> tuple[int, int]:
    """(local, peer) UDP ports of a ``"LOCAL:PEER"`` channel; CanInitializationError otherwise."""
    try:
        local, peer = (int(p) for p in str(channel).split(":"))
    except ValueError:
        local = peer = -1
    if not (1024 <= local <= 65535 and 1024 <= peer <= 65535 and local != peer):
        raise can.CanInitializationError(
            f"{INTERFACE} channel {channel!r} is not valid: expected 'LOCAL:PEER', two different UDP "
            "ports in [1024, 65535] on 127.0.0.1 (this end's and the other end's)")
    return local, peer


class LoopbackBus(can.BusABC):
    """One end of a two-ended CAN bus over loopback UDP (see the module's docstring)."""

    def __init__(self, channel, preserve_timestamps: bool = False, **kwargs):
        local, peer = parse_channel(channel)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        try:
            self._sock.bind((HOST, local))
        except OSError as exc:
            self._sock.close()
            raise can.CanInitializationError(f"{INTERFACE} channel {channel!r}: cannot bind "
                                             f"{HOST}:{local}: {exc.strerror}") from None
        self._peer = (HOST, peer)
        self._preserve = bool(preserve_timestamps)
        self._epoch = int.from_bytes(os.urandom(4), "little")      # a restarted sender is a new one
        self._sent = 0
        self._peer_epoch = None
        self._next = None                   # the sequence number expected next
        self.lost = 0
        self.reordered = 0
        self.channel_info = f"{INTERFACE} {HOST}:{local} -> {HOST}:{peer}"
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_fd or len(msg.data) > 8:
            raise can.CanOperationError(f"{INTERFACE} carries CAN 2.0 frames (at most 8 data bytes)")
        flags = ((_EXTENDED * msg.is_extended_id) | (_REMOTE * msg.is_remote_frame)
                 | (_ERROR * msg.is_error_frame))
        stamp = msg.timestamp if self._preserve else time.time()
        frame = _WIRE.pack(self._epoch, self._sent & 0xFFFFFFFF, stamp, msg.arbitration_id, msg.dlc,
                           flags, bytes(msg.data).ljust(8, b"\0"))
        self._sent += 1
        try:
            self._sock.sendto(frame, self._peer)
        except OSError as exc:
            raise can.CanOperationError(f"{INTERFACE}: send failed: {exc.strerror}") from None

    def _recv_internal(self, timeout: float | None):
        if timeout is not None and timeout <= 0.0:      # a poll: one non-blocking read, no select
            try:
                frame = self._sock.recv(64, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return None, False
        else:
            ready, _, _ = select.select([self._sock], [], [], timeout)
            if not ready:
                return None, False
            frame = self._sock.recv(64)
        if len(frame) != _WIRE.size:
            raise can.CanOperationError(f"{INTERFACE}: a datagram of {len(frame)} bytes is not a frame")
        epoch, seq, stamp, arbitration_id, dlc, flags, data = _WIRE.unpack(frame)
        if epoch != self._peer_epoch:                # the other end (re)started: count from here
            self._peer_epoch, self._next = epoch, None
        if self._next is not None and seq != self._next:
            if (seq - self._next) & 0xFFFFFFFF < 1 << 31:
                self.lost += (seq - self._next) & 0xFFFFFFFF
            else:
                self.reordered += 1
        if self._next is None or (seq - self._next) & 0xFFFFFFFF < 1 << 31:
            self._next = (seq + 1) & 0xFFFFFFFF
        remote = bool(flags & _REMOTE)
        msg = can.Message(timestamp=stamp, arbitration_id=arbitration_id,
                          is_extended_id=bool(flags & _EXTENDED), is_remote_frame=remote,
                          is_error_frame=bool(flags & _ERROR), dlc=dlc, data=b"" if remote else data[:dlc],
                          channel=self.channel_info, check=False)
        return msg, False

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
