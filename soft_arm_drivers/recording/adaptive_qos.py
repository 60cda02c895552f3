"""How the recorder subscribes, as rosbag2 does, without ROS: to what the publishers offer.

A recording subscription must match every publisher of its topic. It is reliable only when every
publisher offers reliable (a reliable subscription receives nothing from a best-effort publisher),
transient local only when every publisher offers it (then the last messages published before the
recorder started reach it), and best effort / volatile otherwise. A topic without publishers is not
subscribed yet: its QoS is unknown until one appears. When a publisher appears later whose offer the
current subscription does not match, the subscription is made again to the new common profile
(only ever downward: to best effort or volatile, so that latched messages are not received twice).

Losses: every message carries its publisher's sequence number (``publication_sequence_number`` of
rclpy's message info, counted per publisher from 1). On a topic with one publisher a jump of the
number is the count of messages the recorder did not receive (a best-effort stream the recorder
could not keep up with, or its history overflowed). On a topic with several publishers the numbers
interleave and losses are not counted there.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Sequence

from .rosbag_writer import Durability, History, QosProfile, Reliability

RECORDING_DEPTH = 1000      # messages a recording subscription buffers while the writer is busy


def adapt_to_offers(offered: Sequence[QosProfile], depth: int = RECORDING_DEPTH) -> QosProfile | None:
    """The subscription profile that receives from every publisher offering ``offered`` (None when
    there is none): reliable and transient local only where all offer them, keep-last ``depth``."""
    if not offered:
        return None
    reliable = all(p.reliability == Reliability.RELIABLE for p in offered)
    latched = all(p.durability == Durability.TRANSIENT_LOCAL for p in offered)
    return QosProfile(reliability=Reliability.RELIABLE if reliable else Reliability.BEST_EFFORT,
                      durability=Durability.TRANSIENT_LOCAL if latched else Durability.VOLATILE,
                      history=History.KEEP_LAST, depth=depth)


def matches(subscription: QosProfile, offer: QosProfile) -> bool:
    """Whether a subscription with ``subscription`` receives from a publisher offering ``offer``
    (a request may not be stricter than the offer in reliability or durability)."""
    reliability_ok = (subscription.reliability != Reliability.RELIABLE
                      or offer.reliability == Reliability.RELIABLE)
    durability_ok = (subscription.durability != Durability.TRANSIENT_LOCAL
                     or offer.durability == Durability.TRANSIENT_LOCAL)
    return reliability_ok and durability_ok


def resubscription(current: QosProfile | None, offered: Sequence[QosProfile],
                   depth: int = RECORDING_DEPTH) -> QosProfile | None:
    """The profile to subscribe with now: the adapted one when there is no subscription yet, a
    weaker one when some publisher's offer does not match ``current`` (only the policies that must
    change are lowered), or None when the current subscription stands (or nobody publishes)."""
    if current is None:
        return adapt_to_offers(offered, depth)
    if all(matches(current, p) for p in offered):
        return None
    out = current
    if any(p.reliability != Reliability.RELIABLE for p in offered):
        out = replace(out, reliability=Reliability.BEST_EFFORT)
    if any(p.durability != Durability.TRANSIENT_LOCAL for p in offered):
        out = replace(out, durability=Durability.VOLATILE)
    return out


class LossCounter:
    """Messages not received per topic, from the publishers' sequence numbers (module docstring)."""

    def __init__(self):
        self.lost: dict = {}
        self._last: dict = {}

    def received(self, topic: str, sequence: int | None, publishers: int) -> int:
        """A message on ``topic`` with its publisher's ``sequence`` number (None when the middleware
        gives none) while ``publishers`` publish on it: the messages found lost before it."""
        if sequence is None or publishers != 1:
            self._last.pop(topic, None)
            return 0
        last = self._last.get(topic)
        self._last[topic] = sequence
        if last is None or sequence <= last:            # the first, or a publisher that restarted
            return 0
        gap = sequence - last - 1
        if gap:
            self.lost[topic] = self.lost.get(topic, 0) + gap
        return gap

    @property
    def total(self) -> int:
        return sum(self.lost.values())
