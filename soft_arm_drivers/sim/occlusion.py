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

from dataclasses import dataclass

import numpy as np

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

    @property
    def losses(self) -> bool:
        """True when markers drop out at random (dropouts or bursts)."""
        return self.dropout > 0 or any(f > 0 for f in self.burst_fraction)


def segment_distances(p, d, a, e) -> np.ndarray:
    """Smallest distances [m] between segments p + s d (s in [0, 1]) and a + t e (t in [0, 1]),
    broadcast over the leading axes of the four (..., 3) arrays."""
    r = p - a
    dd = np.einsum("...i,...i", d, d)
    ee = np.maximum(np.einsum("...i,...i", e, e), _EPS)
    de = np.einsum("...i,...i", d, e)
    dr = np.einsum("...i,...i", d, r)
    er = np.einsum("...i,...i", e, r)
    denominator = dd * ee - de * de
    s = np.where(denominator > _EPS * dd * ee,
                 np.clip((de * er - dr * ee) / np.maximum(denominator, _EPS), 0.0, 1.0), 0.0)
    t = (de * s + er) / ee
    low, high = t < 0.0, t > 1.0
    s = np.where(low, np.clip(-dr / np.maximum(dd, _EPS), 0.0, 1.0), s)
    s = np.where(high, np.clip((de - dr) / np.maximum(dd, _EPS), 0.0, 1.0), s)
    t = np.clip(t, 0.0, 1.0)
    gap = r + s[..., None] * d - t[..., None] * e
    return np.sqrt(np.einsum("...i,...i", gap, gap))


def in_view(config: OcclusionConfig, markers) -> np.ndarray:
    """(C, M) bool: marker m inside camera c's field of view."""
    cameras = np.asarray(config.cameras, dtype=float)
    to_marker = np.asarray(markers, dtype=float)[None, :, :] - cameras[:, None, :]
    axis = np.asarray(config.aim, dtype=float)[None, :] - cameras
    axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    cosine = np.einsum("cmi,ci->cm", to_marker, axis) / np.maximum(np.linalg.norm(to_marker, axis=2), _EPS)
    return cosine >= np.cos(0.5 * config.field_of_view)


def unblocked(config: OcclusionConfig, markers, marker_arcs, points, radii, arcs) -> np.ndarray:
    """(C, M) bool: camera c's line of sight to marker m clears the body, the capsules between
    consecutive backbone ``points`` (P, 3) [m] (ordered by arc length ``arcs`` (P,) [m], cone radius
    ``radii`` (P,) [m]) but those of the marker's own ring (two radii either side)."""
    markers = np.asarray(markers, dtype=float)
    points, radii, arcs = (np.asarray(v, dtype=float) for v in (points, radii, arcs))
    start, end = points[:-1], points[1:]
    capsule_radius = np.maximum(radii[:-1], radii[1:])
    ring = 2.0 * np.interp(marker_arcs, arcs, radii)            # half-width of the marker's ring
    own = ((arcs[None, 1:] > np.asarray(marker_arcs)[:, None] - ring[:, None])
           & (arcs[None, :-1] < np.asarray(marker_arcs)[:, None] + ring[:, None]))      # (M, K)
    cams = np.asarray(config.cameras, dtype=float)[:, None, None, :]
    sight = markers[None, :, None, :] - cams
    distance = segment_distances(cams, sight, start[None, None], (end - start)[None, None])   # (C, M, K)
    blocked = (distance < capsule_radius[None, None, :]) & ~own[None, :, :]
    return ~blocked.any(axis=2)


def cameras_seeing(config: OcclusionConfig, markers, marker_arcs=None, points=None, radii=None,
                   arcs=None) -> np.ndarray:
    """(M,) int: how many cameras see each marker (the body, when given and ``self_occlusion``,
    blocks lines of sight)."""
    seen = in_view(config, markers)
    if config.self_occlusion and points is not None:
        seen &= unblocked(config, markers, marker_arcs, points, radii, arcs)
    return seen.sum(axis=0)


def body(model, data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arm's body as the cameras see it, from a workspace ``data`` of ``model`` evaluated with
    its markers: backbone points (P, 3) [m] in arm_base ordered by arc length (the model's points
    and the markers), the cone's radius at each (P,) [m] and their arc lengths (P,) [m]."""
    X = np.concatenate([model.X, model.marker_X])
    order = np.argsort(X, kind="stable")
    g = model.config.geometry
    arcs = X[order]
    radii = g.base_radius + (g.tip_radius - g.base_radius) * arcs / g.length
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
        self.counts = {"geometry": np.zeros(n_markers, int), "dropout": np.zeros(n_markers, int),
                       "burst": np.zeros(n_markers, int), "frames": 0}

    def visible(self, markers, marker_arcs=None, points=None, radii=None, arcs=None,
                t: float | None = None) -> np.ndarray:
        """(M,) bool: the markers the frame exposed at ``t`` [s] shows (the other arguments: those of
        :func:`cameras_seeing`); advances the random losses by one frame."""
        c = self.config
        if t is not None and c.blackout[0] <= t < c.blackout[1]:
            self.counts["frames"] += 1
            return np.zeros(len(markers), bool)
        geometric = cameras_seeing(c, markers, marker_arcs, points, radii, arcs) >= c.min_cameras
        n = geometric.size
        dropped = self.rng.random(n) < c.dropout if c.dropout > 0 else np.zeros(n, bool)
        if self.p_start.any() or self.in_burst.any():
            draw = self.rng.random(n)
            self.in_burst = np.where(self.in_burst, draw >= self.p_end, draw < self.p_start)
        self.counts["frames"] += 1
        self.counts["geometry"] += ~geometric
        self.counts["dropout"] += dropped
        self.counts["burst"] += self.in_burst
        return geometric & ~dropped & ~self.in_burst

    def of_arm(self, model, data, t: float | None = None) -> np.ndarray:
        """:meth:`visible` at ``t`` [s] for the markers of ``model`` at its workspace ``data``
        (evaluated with markers)."""
        points, radii, arcs = body(model, data)
        return self.visible(data.marker_p, model.marker_X, points, radii, arcs, t)
