"""Room on this host for a run's processes under localhost discovery.

With ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` rmw_fastrtps_cpp (ROS 2 Jazzy) has no multicast:
each participant (one per process) announces itself to the discovery ports of participants 0-31
of its domain on this host (its UDP transport's ``maxInitialPeersRange``, 32), and takes the lowest
participant id whose port is free. A participant of id 32 or above still meets the first 32, which
answer its announcements, but two of them never meet each other: with the first 32 ids of the
domain taken by other processes, a run's nodes would never see each other's topics, and its
bring-up would wait its whole bound for them. A run checks that all its processes but one find ids
below 32 before it starts them, and says what it found when they do not.

Linux only: the ports in use are read from ``/proc/net/udp`` and ``/proc/net/udp6``, which list the
sockets of this process's network namespace (a container's own, the host's otherwise).
"""
from __future__ import annotations

import os

# RTPS's well-known ports (the specification's 9.6.1.1, the defaults Fast DDS uses): port base,
# domain gain, participant gain and the metatraffic unicast offset
PORT_BASE, DOMAIN_GAIN, PARTICIPANT_GAIN, DISCOVERY_OFFSET = 7400, 250, 2, 10
# participant ids a localhost announcement reaches (rmw_fastrtps_cpp's maxInitialPeersRange)
REACHED = 32
UDP_TABLES = ("/proc/net/udp", "/proc/net/udp6")


def discovery_port(domain: int, participant: int) -> int:
    """The UDP port on which participant ``participant`` of ROS domain ``domain`` listens for
    discovery (metatraffic unicast)."""
    return PORT_BASE + DOMAIN_GAIN * domain + DISCOVERY_OFFSET + PARTICIPANT_GAIN * participant


def taken_participants(domain: int, tables=UDP_TABLES) -> set:
    """The participant ids below :data:`REACHED` whose discovery port of ``domain`` a socket of this
    host holds (a participant of any process, or anything else bound there), from the kernel's UDP
    ``tables`` (a table that cannot be read, as ``/proc/net/udp6`` without IPv6, is skipped)."""
    ids = {discovery_port(domain, p): p for p in range(REACHED)}
    taken = set()
    for table in tables:
        try:
            with open(table, encoding="ascii") as fh:
                next(fh, None)                               # the header
                for line in fh:
                    fields = line.split()
                    if len(fields) > 1 and ":" in fields[1]:
                        port = int(fields[1].rsplit(":", 1)[1], 16)
                        if port in ids:
                            taken.add(ids[port])
        except OSError:
            continue
    return taken


def applies(environ=os.environ) -> bool:
    """Whether the limit holds for processes started with ``environ``: localhost discovery on
    rmw_fastrtps (the default middleware, or named by ``RMW_IMPLEMENTATION``)."""
    return (environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
            and (environ.get("RMW_IMPLEMENTATION") or "rmw_fastrtps_cpp").startswith("rmw_fastrtps"))


def check_room(processes: int, environ=os.environ, tables=UDP_TABLES):
    """RuntimeError, naming what it found, when fewer than ``processes - 1`` participant ids below
    :data:`REACHED` are free on the domain of ``environ`` (``ROS_DOMAIN_ID``, 0 when unset) and the
    limit :func:`applies` (one process of the run past them still meets the others, two do not);
    the processes of a run are to start after it."""
    if not applies(environ):
        return
    try:
        domain = int(environ.get("ROS_DOMAIN_ID") or 0)
    except ValueError:
        raise RuntimeError(f"ROS_DOMAIN_ID = {environ['ROS_DOMAIN_ID']!r} is not a domain id "
                           f"(a whole number, 0-232 on Linux)") from None
    taken = taken_participants(domain, tables)
    free = REACHED - len(taken)
    if free < processes - 1:
        raise RuntimeError(
            f"ROS domain {domain} has {len(taken)} of the {REACHED} participant ids that localhost "
            f"discovery reaches taken on this computer (their discovery ports are in use), and this "
            f"run's {processes} processes need {processes - 1} of them free: two processes past them "
            f"never meet. End some of the domain's other processes (`ros2 daemon stop`; `ss -uap` "
            f"lists who holds the ports), or run on another ROS_DOMAIN_ID")
