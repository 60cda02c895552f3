"""Which of the arm's markers the simulated motion capture sees in a frame, ROS-free.

A marker is seen when at least ``min_cameras`` cameras see it: it lies inside a camera's field of
view (a cone of full angle ``field_of_view`` [rad] around the camera's line to ``aim``) and the
camera's line of sight to it clears the arm's own body. The body is the chain of capsules between
the backbone points (radius: the cone's local radius), the pendulum's contact model's surface; the
capsules of the ring that carries the marker (within two local radii of arc length either side of
it: the marker is placed on the backbone, the ring on the surface around it) do not hide it, since
the ring's outside faces every camera that the rest of the body does not block. On top of the
geometry, each marker drops out of a frame with probability ``dropout`` (a
reflection, a marker turned edge-on) and is lost in bursts: a two-state Markov chain per marker that
is in a burst ``burst_fraction`` of the time, for ``burst_duration`` [s] on average (a hand, a
cable, a camera's view of a tool).

Everything is in ``arm_base`` [m]. The camera layout is :class:`OcclusionConfig` (``plant.mocap.
occlusion`` in ``config/plant.yaml``); :class:`Occlusions` draws the random part from its own seeded
generator, so that switching occlusions on or off does not change the markers' noise.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

_EPS = 1e-12


@dataclass(frozen=True)
class OcclusionConfig:
    """The mocap's cameras and losses: ``cameras`` (C, 3) positions [m] in arm_base (tuples, so that
    the configuration compares and hashes), all aimed at ``aim`` (3,) [m], with a field of view of
    full cone angle ``field_of_view`` [rad]; a marker needs
    ``min_cameras`` of them. ``self_occlusion``: the arm's body blocks lines of sight (False: only
    the fields of view count). ``dropout``: probability per marker per frame; ``burst_fraction``
    (one per marker, base to tip): the fraction of time each marker is lost in bursts of mean
    duration ``burst_duration`` [s]; ``blackout`` = (start, end) [s]: no marker is seen in between
    (the mocap lost, e.g. its network)."""
    cameras: tuple
    aim: tuple
    field_of_view: float
    min_cameras: int = 2
    self_occlusion: bool = True
    dropout: float = 0.0
    burst_fraction: tuple = ()
    burst_duration: float = 0.5
    blackout: tuple = (0.0, 0.0)


@njit(cache=True, nogil=True)
def segment_distance(p, d, a, e) -> float:
    """Smallest distance [m] between the segments p + s d (s in [0, 1]) and a + t e (t in [0, 1]),
    each argument a (3,) array."""
    r0, r1, r2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    ee = max(e[0] * e[0] + e[1] * e[1] + e[2] * e[2], _EPS)
    de = d[0] * e[0] + d[1] * e[1] + d[2] * e[2]
    dr = d[0] * r0 + d[1] * r1 + d[2] * r2
    er = e[0] * r0 + e[1] * r1 + e[2] * r2
    denominator = dd * ee - de * de
    s = 0.0
    if denominator > _EPS * dd * ee:                    # not parallel: the lines' closest points
        s = min(max((de * er - dr * ee) / max(denominator, _EPS), 0.0), 1.0)
    t = (de * s + er) / ee
    if t < 0.0:
        s, t = min(max(-dr / max(dd, _EPS), 0.0), 1.0), 0.0
    elif t > 1.0:
        s, t = min(max((de - dr) / max(dd, _EPS), 0.0), 1.0), 1.0
    g0 = r0 + s * d[0] - t * e[0]
    g1 = r1 + s * d[1] - t * e[1]
    g2 = r2 + s * d[2] - t * e[2]
    return math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)


@njit(cache=True, nogil=True)
def _seeing(cameras, axes, cos_half, markers, ring_low, ring_high, points, capsule_radii, arcs, occlude):
    """(M,) cameras that see each marker: in the field of view (unit ``axes``, cosine of the half
    angle) and, when ``occlude``, with a line of sight that no capsule between consecutive ``points``
    blocks but those whose arc span meets the marker's ring (``ring_low``, ``ring_high``).

    Most capsules lie far from most lines of sight (the cameras stand metres away, a capsule is a
    few centimetres long): a capsule is tested exactly (:func:`segment_distance`) only where the
    line of sight passes within its bounding sphere (centre the segment's midpoint, radius half its
    length plus its own, and a nanometre for rounding). Outside that sphere the segments are
    further apart than the capsule's radius, so the count is the exact test's on every capsule;
    a frame's visibility takes a quarter of the time testing every capsule took
    (``bench/bench_model.py``)."""
    count = np.zeros(markers.shape[0], np.int64)
    sight = np.empty(3)
    n_capsules = points.shape[0] - 1
    edges = np.empty((n_capsules, 3))                   # the capsules' axes, once per frame
    centres = np.empty((n_capsules, 3))
    reach2 = np.empty(n_capsules)                       # their bounding spheres' squared radii
    for k in range(n_capsules):
        length2 = 0.0
        for i in range(3):
            edges[k, i] = points[k + 1, i] - points[k, i]
            centres[k, i] = points[k, i] + 0.5 * edges[k, i]
            length2 += edges[k, i] * edges[k, i]
        reach = 0.5 * math.sqrt(length2) + capsule_radii[k] + 1e-9
        reach2[k] = reach * reach
    for c in range(cameras.shape[0]):
        for m in range(markers.shape[0]):
            norm = 0.0
            along = 0.0
            for i in range(3):
                sight[i] = markers[m, i] - cameras[c, i]
                norm += sight[i] * sight[i]
                along += sight[i] * axes[c, i]
            if along < cos_half * max(math.sqrt(norm), _EPS):
                continue
            clear = True
            if occlude:
                inverse_norm = 1.0 / max(norm, _EPS)
                for k in range(n_capsules):
                    if arcs[k + 1] > ring_low[m] and arcs[k] < ring_high[m]:
                        continue                        # the marker's own ring
                    # the line of sight's point nearest the capsule's centre, and their distance
                    r0 = centres[k, 0] - cameras[c, 0]
                    r1 = centres[k, 1] - cameras[c, 1]
                    r2 = centres[k, 2] - cameras[c, 2]
                    t = min(max((r0 * sight[0] + r1 * sight[1] + r2 * sight[2]) * inverse_norm, 0.0), 1.0)
                    g0, g1, g2 = r0 - t * sight[0], r1 - t * sight[1], r2 - t * sight[2]
                    if g0 * g0 + g1 * g1 + g2 * g2 > reach2[k]:
                        continue
                    if segment_distance(cameras[c], sight, points[k], edges[k]) < capsule_radii[k]:
                        clear = False
                        break
            if clear:
                count[m] += 1
    return count


@njit(cache=True, nogil=True)
def _seeing_arm(cameras, axes, cos_half, p, marker_p, order, ring_low, ring_high, capsule_radii, arcs,
                occlude):
    """:func:`_seeing` of a model's workspace: its points ``p`` (P, 3) and markers ``marker_p``
    (M, 3) [m] put in ``order`` of arc length here, so that a frame is one compiled call."""
    n_points = p.shape[0]
    points = np.empty((order.shape[0], 3))
    for i in range(order.shape[0]):
        k = order[i]
        for a in range(3):
            points[i, a] = p[k, a] if k < n_points else marker_p[k - n_points, a]
    return _seeing(cameras, axes, cos_half, marker_p, ring_low, ring_high, points, capsule_radii, arcs,
                   occlude)


@functools.lru_cache(maxsize=16)
def _layout(config: OcclusionConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """The cameras (C, 3) [m], their unit optical axes (C, 3) and the cosine of half the field of
    view, computed once per configuration (it is frozen)."""
    cameras = np.ascontiguousarray(config.cameras, dtype=float).reshape(-1, 3)
    axes = np.asarray(config.aim, dtype=float)[None, :] - cameras
    axes = np.ascontiguousarray(axes / np.linalg.norm(axes, axis=1, keepdims=True))
    return cameras, axes, math.cos(0.5 * config.field_of_view)


def cameras_seeing(config: OcclusionConfig, markers, marker_arcs=None, points=None, radii=None,
                   arcs=None) -> np.ndarray:
    """(M,) int: how many cameras see each marker (M, 3) [m]. Each camera sees the markers inside
    its field of view (a cone of full angle ``config.field_of_view`` around its line to
    ``config.aim``); the body, when given and ``config.self_occlusion``, blocks lines of sight: the
    capsules between consecutive backbone ``points`` (P, 3) [m] (ordered by arc length ``arcs``
    (P,) [m], cone radius ``radii`` (P,) [m]) but those of the marker's own ring (two radii either
    side of its arc length ``marker_arcs`` (M,) [m])."""
    markers = np.ascontiguousarray(markers, dtype=float).reshape(-1, 3)
    cameras, axes, cos_half = _layout(config)
    occlude = bool(config.self_occlusion and points is not None)
    if occlude:
        points, radii, arcs = (np.ascontiguousarray(v, dtype=float) for v in (points, radii, arcs))
        low, high, capsule_radii = _rings(marker_arcs, arcs, radii)
    else:
        points = np.zeros((1, 3))
        arcs = np.zeros(1)
        low = high = np.zeros(markers.shape[0])
        capsule_radii = np.zeros(0)
    return _seeing(cameras, axes, cos_half, markers, low, high, points, capsule_radii, arcs, occlude)


def _rings(marker_arcs, arcs, radii) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arc spans [m] of the markers' rings (low, high: two local radii either side of each
    marker's arc length ``marker_arcs``) and the capsules' radii (P - 1,) [m] (the larger of their
    ends') of a body whose points lie at ``arcs`` with cone radius ``radii``."""
    marker_arcs = np.asarray(marker_arcs, dtype=float).reshape(-1)
    ring = 2.0 * np.interp(marker_arcs, arcs, radii)
    return marker_arcs - ring, marker_arcs + ring, np.maximum(radii[:-1], radii[1:])


def arc_layout(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The order that sorts the model's points then markers by arc length ((P,) int64 indices, as
    the compiled gathers of a frame take them), their arc lengths in that order (P,) [m] and the
    cone's radius at each (P,) [m]: what :func:`body`, :meth:`Occlusions.of_arm` and the contact's
    surface (:meth:`.simulated_rig.Plant.surface`) take from the model, which does not change
    between frames."""
    X = np.concatenate([model.X, model.marker_X])
    order = np.argsort(X, kind="stable").astype(np.int64)
    g = model.config.geometry
    arcs = X[order]
    radii = g.base_radius + (g.tip_radius - g.base_radius) * arcs / g.length
    return order, arcs, radii


def body(model, data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arm's body as the cameras see it, from a workspace ``data`` of ``model`` evaluated with
    its markers: backbone points (P, 3) [m] in arm_base ordered by arc length (the model's points
    and the markers), the cone's radius at each (P,) [m] and their arc lengths (P,) [m]."""
    order, arcs, radii = arc_layout(model)
    return np.concatenate([data.p, data.marker_p])[order], radii, arcs


class Occlusions:
    """Seeded occlusion process for frames ``frame_period`` [s] apart: :meth:`visible` of each frame
    in turn (:meth:`of_arm`: from a model's workspace)."""

    def __init__(self, config: OcclusionConfig, n_markers: int, frame_period: float, seed):
        if config.burst_fraction and len(config.burst_fraction) != n_markers:
            raise ValueError(f"burst_fraction needs one value per marker ({n_markers})")
        self.config = config
        self.rng = np.random.default_rng(seed)
        fraction = np.array(config.burst_fraction or [0.0] * n_markers, dtype=float)
        self.p_end = min(1.0, frame_period / config.burst_duration)
        self.p_start = np.minimum(1.0, fraction / np.maximum(1.0 - fraction, _EPS) * self.p_end)
        self.in_burst = self.rng.random(n_markers) < fraction          # the chain's stationary state
        # a marker in a burst has a fraction > 0, hence p_start > 0: without any, none ever starts
        self._bursts = bool(self.p_start.any())
        self._arm = None       # (model, order, arcs, ring lows, ring highs, capsule radii) of of_arm

    @classmethod
    def for_plant(cls, plant, n_markers: int) -> "Occlusions | None":
        """The occlusions of a :class:`~.plant_config.PlantConfig`'s mocap (its ``occlusion``, frame
        rate and seed; their own stream of the seed, apart from the markers' noise), None when
        ``plant.mocap.occlusion`` is off."""
        if plant.occlusion is None:
            return None
        return cls(plant.occlusion, n_markers, 1.0 / plant.mocap_rate, [plant.mocap_seed, 1])

    def visible(self, markers, marker_arcs=None, points=None, radii=None, arcs=None,
                t: float | None = None) -> np.ndarray:
        """(M,) bool: the markers the frame exposed at ``t`` [s] shows (the other arguments: those of
        :func:`cameras_seeing`); advances the random losses by one frame."""
        c = self.config
        if t is not None and c.blackout[0] <= t < c.blackout[1]:
            return np.zeros(len(markers), bool)
        return self._losses(cameras_seeing(c, markers, marker_arcs, points, radii, arcs) >= c.min_cameras)

    def of_arm(self, model, data, t: float | None = None) -> np.ndarray:
        """:meth:`visible` at ``t`` [s] for the markers of ``model`` at its workspace ``data``
        (evaluated with markers). What depends on the model alone (the points' order by arc length,
        the rings, the capsules' radii) is computed at the first frame of a model and kept: a frame
        then costs one compiled call (:func:`_seeing_arm`) and the random draws."""
        c = self.config
        if t is not None and c.blackout[0] <= t < c.blackout[1]:
            return np.zeros(model.marker_X.size, bool)
        if self._arm is None or self._arm[0] is not model:
            order, arcs, radii = arc_layout(model)
            self._arm = (model, order, arcs) + _rings(model.marker_X, arcs, radii)
        _, order, arcs, low, high, capsule_radii = self._arm
        cameras, axes, cos_half = _layout(c)
        seen = _seeing_arm(cameras, axes, cos_half, data.p, data.marker_p, order, low, high, capsule_radii,
                           arcs, bool(c.self_occlusion))
        return self._losses(seen >= c.min_cameras)

    def _losses(self, geometric) -> np.ndarray:
        """The markers of ``geometric`` (M,) bool (those the cameras' geometry lets through) that
        this frame's random dropouts and bursts leave; advances the random losses by one frame (a
        draw per marker for the dropouts if any, one for the bursts if any marker has them)."""
        c = self.config
        seen = geometric
        if c.dropout > 0:
            seen = seen & (self.rng.random(geometric.size) >= c.dropout)
        if self._bursts:
            draw = self.rng.random(geometric.size)
            self.in_burst = np.where(self.in_burst, draw >= self.p_end, draw < self.p_start)
            seen = seen & ~self.in_burst
        return seen
