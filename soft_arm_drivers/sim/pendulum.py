"""The pendulum of the paper's strike experiment and its contact with the arm, ROS-free.

**The pendulum.** A ball (point mass ``mass`` [kg], radius ``ball_radius`` [m]) on a massless rod of
length ``length`` [m] from ``pivot`` [m, arm_base]: a spherical pendulum, so that a blow from the
side sends it out of its plane as the paper's Fig. 5B shows (its cable is taken as taut). It is held
at ``release_angle`` [rad] from the vertical on the side ``direction`` (horizontal, from below the
pivot towards the held ball) until :meth:`Pendulum.release`. With r = p - pivot (``|r| = L``) and F
the contact force on the ball, the acceleration is::

    a = (I - r_hat r_hat^T) (g + F / m) - (|v|^2 / L) r_hat

integrated by RK4; after each step p is put back on the sphere and v on its tangent plane. Without
contact the energy is conserved to the integrator's order.

**The contact.** The arm is the chain of capsules between consecutive backbone points (the model's
points and markers, ordered by arc length), of the cone's radius there; the ball meets the capsule it
overlaps most, along the normal n from the closest backbone point Q to the ball's centre, overlap
delta = ``r_arm(Q) + r_ball - |c - Q|``. The force is Hunt and Crossley's with the damping of Lankarani and
Nikravesh (restitution e, approach speed delta_dot_0 at first touch):

    F_n = k delta^(3/2) (1 + 3 (1 - e^2) / 4 * delta_dot / delta_dot_0),  F_n >= 0

with Hertz's stiffness of a rigid ball on an incompressible elastic body of local radius r
(Young's modulus E, Poisson ratio 1/2): k = 4/3 * E / (1 - 1/4) * sqrt(r r_b / (r + r_b)). It pushes
the ball along +n and the arm along -n at Q, where a frictionless force along the normal has no
moment about the backbone. The arm's point is held over a plant step while the ball is sub-stepped
through it (the ball's contact is stiffer than the arm's step); the arm takes the mean force.
"""
from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np
from numba import njit

from soft_arm_control.pendulum_geometry import GRAVITY, PendulumConfig


def hertz_stiffness(youngs_modulus: float, arm_radius: float, ball_radius: float) -> float:
    """k [N/m^1.5] of a rigid ball of radius ``ball_radius`` [m] pressed into an incompressible
    elastic body of radius ``arm_radius`` [m] and Young's modulus [Pa] (scalars)."""
    return _hertz_stiffness(float(youngs_modulus), float(arm_radius), float(ball_radius))


@njit(cache=True, nogil=True)
def _hertz_stiffness(youngs_modulus, arm_radius, ball_radius):
    """:func:`hertz_stiffness`, for the compiled contact."""
    reduced = youngs_modulus / (1.0 - 0.25)
    return 4.0 / 3.0 * reduced * math.sqrt(arm_radius * ball_radius / (arm_radius + ball_radius))


def closest_capsule(points, radii, centre) -> tuple[int, float, np.ndarray, float]:
    """The capsule of the chain through ``points`` (P, 3) [m] with radii (P,) [m] that ``centre``
    [m] is closest to the surface of: (segment index i between points i and i+1, fraction s along
    it, the backbone point Q [m], the gap [m] from Q's surface: ``|c - Q| - r(Q)``; the first
    such capsule where several are as close, the first whose gap is NaN where one is). ValueError
    for a chain of fewer than two points."""
    points = _writable(points)
    if points.ndim != 2 or points.shape[0] < 2 or points.shape[1] != 3:
        raise ValueError(f"a chain of capsules needs (P >= 2, 3) points, got the shape {points.shape}")
    q = np.empty(3)
    i, s, gap = _closest(points, _writable(radii), _writable(centre), q)
    return i, s, q, gap


def _writable(values) -> np.ndarray:
    """``values`` as the compiled contact takes them: float, C-ordered and writable (a read-only
    array would compile the kernels a second time), copied only where it is not."""
    return np.require(values, dtype=float, requirements=["C", "W"])


@njit(cache=True, nogil=True)
def _closest(points, radii, centre, q):
    """:func:`closest_capsule` in one compiled pass: (i, s, gap), Q into ``q`` (3,)."""
    best, best_i, best_s = np.inf, 0, 0.0
    for k in range(points.shape[0] - 1):
        along = 0.0
        length2 = 0.0
        for j in range(3):
            d = points[k + 1, j] - points[k, j]
            along += (centre[j] - points[k, j]) * d
            length2 += d * d
        s = min(max(along / max(length2, 1e-18), 0.0), 1.0)
        distance2 = 0.0
        for j in range(3):
            g = centre[j] - (points[k, j] + s * (points[k + 1, j] - points[k, j]))
            distance2 += g * g
        gap = math.sqrt(distance2) - (radii[k] + s * (radii[k + 1] - radii[k]))
        if gap < best or np.isnan(gap):
            best, best_i, best_s = gap, k, s
            if np.isnan(gap):
                break                   # returned as it is: the contact turns NaN, not a miss
    for j in range(3):
        q[j] = points[best_i, j] + best_s * (points[best_i + 1, j] - points[best_i, j])
    return best_i, best_s, best


@dataclass(frozen=True)
class ArmSurface:
    """The arm at one instant, as the contact sees it: backbone points (P, 3) [m] in arm_base ordered
    by arc length, their velocities (P, 3) [m/s], the cone's radius at each (P,) [m], and the
    world-frame linear Jacobians (P, 3, n) of the points (to turn a force into a generalised one)."""
    points: np.ndarray
    velocities: np.ndarray
    radii: np.ndarray
    jacobians: np.ndarray

    def closest(self, centre) -> tuple[int, float, np.ndarray, float]:
        """:func:`closest_capsule` of this surface."""
        return closest_capsule(self.points, self.radii, centre)

    def generalised_force(self, i: int, s: float, force) -> np.ndarray:
        """The generalised force of ``force`` [N] (arm_base) applied at fraction s of segment i."""
        jac = (1.0 - s) * self.jacobians[i] + s * self.jacobians[i + 1]
        return jac.T @ np.asarray(force, dtype=float)


@dataclass(frozen=True)
class Contact:
    """The contact over one plant step: mean force on the ball [N] (arm_base; the arm takes minus
    it), the segment and fraction where it acts, the deepest overlap [m] and the smallest surface
    gap between arm and ball [m] (negative: overlap)."""
    force: np.ndarray
    segment: int
    fraction: float
    overlap: float
    gap: float


class Pendulum:
    """The ball's state: position p [m], velocity v [m/s] in arm_base, held until :meth:`release`.
    ``youngs_modulus`` [Pa]: the arm's, for the contact stiffness."""

    def __init__(self, config: PendulumConfig, youngs_modulus: float):
        self.config = config
        self.youngs_modulus = float(youngs_modulus)
        self.p = config.held_position.copy()
        self.v = np.zeros(3)
        self.released = False
        self._approach = None               # delta_dot at first touch of the current contact [m/s]
        self._pivot = np.array(config.pivot, dtype=float)       # as the compiled step takes it

    def release(self):
        """Let the ball go (from rest at the held position)."""
        self.released = True

    def energy(self) -> float:
        """Kinetic + gravitational energy [J] (zero height at the pivot)."""
        m = self.config.mass
        return float(0.5 * m * self.v @ self.v - m * GRAVITY @ (self.p - self._pivot))

    def advance(self, dt: float, surface: ArmSurface | None = None, substeps: int = 4) -> Contact | None:
        """Advance the ball by dt [s] (nothing while held), in ``substeps`` RK4 steps, against the
        arm ``surface`` held over the step (None: no arm). Returns the step's :class:`Contact` (None
        without a surface): its force is the RK4-weighted mean of what the ball felt, so that the
        arm takes the impulse the ball got."""
        far = np.inf
        in_reach = False
        if surface is not None:
            # broad phase: a ball farther than it and the arm can close in one step feels nothing
            far = surface.closest(self.p)[3] - self.config.ball_radius
            reach = (np.linalg.norm(self.v) + np.linalg.norm(GRAVITY) * dt
                     + np.abs(surface.velocities).sum(axis=1).max()) * dt
            in_reach = self.released and not far > 2.0 * reach + 1e-4
            if not in_reach:
                self._approach = None
        if not self.released:
            return None if surface is None else Contact(np.zeros(3), 0, 0.0, 0.0, far)
        c = self.config
        points, velocities, radii = (surface.points, surface.velocities, surface.radii) if in_reach \
            else _NO_SURFACE
        impulse = np.zeros(3)
        # new arrays each step, as a reader may keep the last ones
        p, v = np.array(self.p, dtype=float), np.array(self.v, dtype=float)
        approach = np.nan if self._approach is None else self._approach
        segment, fraction, deepest, gap, approach = _swing(
            p, v, self._pivot, float(c.length), float(c.mass), float(c.ball_radius),
            float(c.restitution), self.youngs_modulus, _GRAVITY, float(dt), operator.index(substeps),
            in_reach, _writable(points), _writable(velocities), _writable(radii), float(far),
            float(approach), impulse)
        self.p, self.v = p, v
        self._approach = None if np.isnan(approach) else approach
        if surface is None:
            return None
        return Contact(impulse / dt, segment, fraction, deepest, gap)


_NO_SURFACE = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
_GRAVITY = np.array(GRAVITY, dtype=float)


@njit(cache=True, nogil=True)
def _stage(p, v, pivot, length, mass, ball_radius, restitution, youngs_modulus, gravity, touching,
           points, velocities, radii, approach, acceleration, force, q):
    """One RK4 stage of :meth:`Pendulum.advance` at the ball's (p, v): its acceleration and the
    contact force on it [N] into ``acceleration`` and ``force`` (3,) (``q``: scratch (3,)), and
    (segment, fraction, overlap [m], gap [m], the approach speed): the approach speed is set at
    the first touch of a contact (NaN: none yet) and returned as it is otherwise. Without
    ``touching`` (the surface beyond the step's reach) no contact is evaluated: no force, no
    overlap, an infinite gap."""
    segment, fraction, overlap, gap = 0, 0.0, 0.0, np.inf
    for j in range(3):
        force[j] = 0.0
    if touching:
        segment, fraction, gap = _closest(points, radii, p, q)
        gap -= ball_radius
        if not gap >= 0.0:                              # NaN too: the force says it, not a miss
            distance = _distance(p, q)
            rate = 0.0                                     # d(overlap)/dt along the normal
            for j in range(3):
                arm = (1.0 - fraction) * velocities[segment, j] + fraction * velocities[segment + 1, j]
                rate -= (v[j] - arm) * (p[j] - q[j]) / max(distance, 1e-12)
            if np.isnan(approach):
                approach = max(rate, 1e-3)
            radius = radii[segment] + fraction * (radii[segment + 1] - radii[segment])
            k = _hertz_stiffness(youngs_modulus, radius, ball_radius)
            damping = 0.75 * (1.0 - restitution ** 2) * rate / approach
            magnitude = max(k * (-gap) ** 1.5 * (1.0 + damping), 0.0)
            for j in range(3):
                force[j] = magnitude * (p[j] - q[j]) / max(distance, 1e-12)
            overlap = -gap
    r = _distance(p, pivot)
    along = 0.0
    speed2 = 0.0
    for j in range(3):
        along += (gravity[j] + force[j] / mass) * (p[j] - pivot[j]) / r
        speed2 += v[j] * v[j]
    for j in range(3):
        r_hat = (p[j] - pivot[j]) / r
        acceleration[j] = gravity[j] + force[j] / mass - along * r_hat - speed2 / length * r_hat
    return segment, fraction, overlap, gap, approach


@njit(cache=True, nogil=True)
def _swing(p, v, pivot, length, mass, ball_radius, restitution, youngs_modulus, gravity, dt, substeps,
           touching, points, velocities, radii, far, approach, impulse):
    """:meth:`Pendulum.advance` of a released ball in one compiled call: p and v (3,) [m, m/s]
    advanced in place by ``substeps`` RK4 steps of dt / substeps, each put back on the sphere and
    its tangent plane; the RK4-weighted impulse [N s] into ``impulse``. Returns (segment and
    fraction of the deepest overlap, that overlap [m], the smallest gap seen at a step's start or
    ``far`` [m], the approach speed of the contact under way: NaN when none is)."""
    h = dt / substeps
    stages = np.empty((4, 3, 3))          # per stage: the rate of p (v), of v (a), the force
    p_stage = np.empty(3)
    v_stage = np.empty(3)
    q = np.empty(3)
    deepest, where_segment, where_fraction, gap = 0.0, 0, 0.0, far
    for _ in range(substeps):
        for n in range(4):
            for j in range(3):
                if n == 0:
                    p_stage[j], v_stage[j] = p[j], v[j]
                else:
                    step = h if n == 3 else 0.5 * h
                    p_stage[j] = p[j] + step * stages[n - 1, 0, j]
                    v_stage[j] = v[j] + step * stages[n - 1, 1, j]
                stages[n, 0, j] = v_stage[j]
            segment, fraction, overlap, g, approach = _stage(
                p_stage, v_stage, pivot, length, mass, ball_radius, restitution, youngs_modulus,
                gravity, touching, points, velocities, radii, approach, stages[n, 1], stages[n, 2], q)
            if overlap > deepest:
                deepest, where_segment, where_fraction = overlap, segment, fraction
            if n == 0:
                if overlap == 0.0:
                    approach = np.nan           # out of contact: the next touch starts a new one
                gap = min(gap, g)
        for j in range(3):
            p[j] += h / 6.0 * _rk4_sum(stages, 0, j)
            v[j] += h / 6.0 * _rk4_sum(stages, 1, j)
            impulse[j] += h / 6.0 * _rk4_sum(stages, 2, j)
        r = _distance(p, pivot)
        for j in range(3):
            p[j] = pivot[j] + (p[j] - pivot[j]) * (length / r)
        along = 0.0
        for j in range(3):
            along += v[j] * (p[j] - pivot[j]) / length
        for j in range(3):
            v[j] -= along * (p[j] - pivot[j]) / length
    return where_segment, where_fraction, deepest, gap, approach


@njit(cache=True, nogil=True)
def _distance(a, b):
    """|a - b| of two 3-vectors [m]."""
    return math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)


@njit(cache=True, nogil=True)
def _rk4_sum(stages, m, j):
    """k1 + 2 k2 + 2 k3 + k4 of component j of the stages' rate ``m`` (:func:`_swing`'s)."""
    return stages[0, m, j] + 2.0 * stages[1, m, j] + 2.0 * stages[2, m, j] + stages[3, m, j]
