"""Who may command the motors: the one publisher of ``tendon/command`` the graph expects.

A ROS topic takes messages from any process on the same domain: a second computer in the lab with
the same ``ROS_DOMAIN_ID``, a stray ``ros2 topic pub``. rclpy does not say which publisher sent a
message, so the motor driver judges the topic's publishers as a whole (:class:`CommandSource`):
commands are taken only while exactly one publisher is matched and the graph names it as the
expected node (``rig.motors.command_publisher``, the inner loop). The graph learns a publisher's
node name a little after it matches (the name travels on ``ros_discovery_info``); until then the
publisher is ``unidentified``: commands wait, nothing is latched (the watchdog still counts).
A publisher known to be another node's, or a second one, is ``foreign``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"     # the name the graph gives a node it has not heard name itself


def node_path(namespace: str, name: str) -> str:
    """The fully qualified node name of ``name`` in ``namespace`` (``/`` + ``inner_loop``)."""
    return f"{namespace.rstrip('/')}/{name}"


@dataclass(frozen=True)
class Verdict:
    """The publishers of the command topic, judged: ``status`` is ``ok`` (the expected publisher
    alone), ``none`` (no publisher), ``unidentified`` (a publisher the graph cannot name yet) or
    ``foreign`` (another node, or more than one publisher); ``publishers``: their node names."""
    status: str
    publishers: tuple

    @property
    def accepts(self) -> bool:
        """Commands may drive the motors."""
        return self.status == "ok"

    def describe(self, expected: str) -> str:
        names = ", ".join(self.publishers) or "none"
        return {"ok": f"commands from {expected}",
                "none": "no publisher",
                "unidentified": f"a publisher the graph cannot name yet ({names})",
                "foreign": f"tendon/command has publishers other than {expected} alone: {names}"}[self.status]


def judge(publishers: Iterable[tuple], expected: str, matched: int) -> Verdict:
    """The verdict on the publishers the graph lists, as (namespace, node name) pairs, of which the
    subscription has ``matched``; ``expected``: the fully qualified name of the one allowed."""
    names = tuple(node_path(ns, name) for ns, name in publishers)
    known = tuple(n for n in names if not n.endswith("/" + UNKNOWN_NODE))
    if matched == 0 and not names:
        return Verdict("none", ())
    if any(n != expected for n in known) or len(names) > 1 or matched > 1:
        return Verdict("foreign", names)
    if len(known) == 1 and matched == 1:
        return Verdict("ok", names)
    return Verdict("unidentified", names)


class CommandSource:
    """The verdict kept current: :meth:`update` with the subscription's matched count on every
    command; the graph (``list_publishers()``: (namespace, name) pairs) is asked when that count
    changed, when the last verdict was not final, when it is older than ``max_age`` [s] and when
    the caller asks for a fresh one (activation). The count alone does not tell a publisher
    replaced by another between two commands (the inner loop gone, a stray ``ros2 topic pub``
    come: one publisher before and after), so a verdict is kept at most ``max_age``, and an
    activation never takes a kept one."""

    def __init__(self, expected: str, list_publishers, max_age: float = 0.5):
        self.expected = expected
        self._list = list_publishers
        self.max_age = float(max_age)
        self._matched = None
        self._judged_at = -float("inf")     # the caller's monotonic time [s] of the last verdict
        self.verdict = Verdict("none", ())
        self.refused = 0            # commands refused since start

    def update(self, matched: int, now: float, fresh: bool = False) -> Verdict:
        """The verdict with ``matched`` publishers at ``now`` [s, a monotonic clock]; ``fresh``:
        ask the graph whatever was kept."""
        if (fresh or matched != self._matched or self.verdict.status == "unidentified"
                or not now - self._judged_at < self.max_age):
            self._matched, self._judged_at = matched, now
            self.verdict = judge(self._list(), self.expected, matched)
        return self.verdict
