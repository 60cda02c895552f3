"""A recorded identification experiment as the fit reads it (ROS-free): the time series a rig
records, split into quasi-static plateaus and the dynamic segments between them.

Only recorded signals are used: the commanded tensions (``tendon/command``) say where the
tensions were held constant; the applied tensions and the encoder shortenings (``tendon/state``)
and the markers (``mocap/markers``) are what the arm did. Nothing of the schedule that produced
them is needed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .identification import IdentificationError, StaticSample

SAME = 1e-6             # N: commands closer than this are the same plateau
SETTLED_LEAD = 0.2      # s: the end of a plateau a dynamic segment starts with (its settled reference)


@dataclass(frozen=True)
class Recording:
    """Time series of one experiment, each on its own stamps [s]: tendon states (``t``; encoder
    shortenings and applied tensions (N, n_t) [m], [N]), commanded tensions (``t_command``,
    ``command`` (C, n_t) [N]) and marker frames (``t_markers``, ``markers`` (M, n_m, 3) [m], in
    the mocap frame as calibrated when recorded; an occluded marker is NaN)."""
    t: np.ndarray
    shortening: np.ndarray
    tension: np.ndarray
    t_command: np.ndarray
    command: np.ndarray
    t_markers: np.ndarray
    markers: np.ndarray

    def window(self, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
        """Boolean selections of the states and of the frames with stamps in [a, b); only the frames
        that saw every marker (the fits compare whole frames with the model)."""
        complete = np.all(np.isfinite(self.markers), axis=(1, 2)) if self.markers.size else \
            np.ones(self.t_markers.size, bool)
        return (self.t >= a) & (self.t < b), (self.t_markers >= a) & (self.t_markers < b) & complete


@dataclass(frozen=True)
class Plateau:
    """Commanded tensions (n_t,) [N] held constant over [start, end) [s]."""
    start: float
    end: float
    command: np.ndarray


@dataclass(frozen=True)
class DynamicSegment:
    """[start, end) [s]: from the settled end of a plateau through what moved the arm (a step, a
    chirp, a change of plateau) into the next plateau."""
    start: float
    end: float


def plateaus(rec: Recording, min_hold: float) -> list:
    """The runs of constant commanded tensions at least ``min_hold`` [s] long (the arm has time to
    settle), in time order."""
    c, t = rec.command, rec.t_command
    if len(t) < 2:
        raise IdentificationError("the recording holds no commanded tensions (tendon/command)")
    change = np.flatnonzero(np.any(np.abs(np.diff(c, axis=0)) > SAME, axis=1)) + 1
    bounds = np.concatenate([[0], change, [len(t)]])
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        end = t[b] if b < len(t) else t[-1]
        if end - t[a] >= min_hold:
            out.append(Plateau(float(t[a]), float(end), c[a].copy()))
    return out


def static_samples(rec: Recording, held: list, average: float) -> list:
    """One :class:`~soft_arm_model.identification.StaticSample` per plateau of ``held``: the means
    of the applied tensions, shortenings and markers over its last ``average`` [s]."""
    out = []
    for k, p in enumerate(held):
        a = max(p.start, p.end - average)
        s, m = rec.window(a, p.end)
        if not s.any() or not m.any():
            raise IdentificationError(f"plateau {k + 1} ({a:.2f}-{p.end:.2f} s) has no "
                                      f"{'tendon states' if not s.any() else 'mocap frames'}")
        out.append(StaticSample(rec.tension[s].mean(axis=0), rec.shortening[s].mean(axis=0),
                                rec.markers[m].mean(axis=0)))
    return out


def dynamic_segments(held: list, lead: float, window: float, moves_only: bool = True) -> list:
    """Segments from ``lead`` [s] before the end of each plateau of ``held`` to ``window`` [s] into
    the next; with ``moves_only``, only those with something between the two plateaus (a step or a
    chirp, not a change from one plateau straight to the next)."""
    out = []
    for p, q in zip(held[:-1], held[1:]):
        if moves_only and q.start - p.end < 1e-6:
            continue
        out.append(DynamicSegment(max(p.start, p.end - lead), min(q.end, q.start + window)))
    return out


def noise_levels(rec: Recording, held: list, average: float,
                 per_reading: bool = False) -> tuple[float, float]:
    """The standard deviations [m] of one static sample's markers and shortenings, from the data:
    the spread of the readings over each plateau's averaged end (the median over plateaus), over
    the square root of their count (``per_reading``: of one reading, not divided); the encoders'
    quantum (their smallest reading step) over sqrt(12) counts when the readings do not move."""
    spread_m, spread_s, n_m, n_s = [], [], [], []
    for p in held:
        s, m = rec.window(max(p.start, p.end - average), p.end)
        if m.sum() > 2:
            spread_m.append(np.median(rec.markers[m].std(axis=0)))
            n_m.append(m.sum())
        if s.sum() > 2:
            spread_s.append(np.median(rec.shortening[s].std(axis=0)))
            n_s.append(s.sum())
    steps = np.abs(np.diff(rec.shortening, axis=0))
    steps = steps[steps > 1e-12]
    quantum = float(steps.min()) if steps.size else 0.0
    marker = float(np.median(spread_m) / (1.0 if per_reading else np.sqrt(np.median(n_m)))) \
        if spread_m else 1e-4
    shortening = float(np.median(spread_s) / (1.0 if per_reading else np.sqrt(np.median(n_s)))) \
        if spread_s else 0.0
    return max(marker, 1e-6), max(shortening, quantum / np.sqrt(12.0), 1e-7)
