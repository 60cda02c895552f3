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

from dataclasses import dataclass

import numpy as np

from soft_arm_control.pendulum_geometry import GRAVITY, PendulumConfig


def hertz_stiffness(youngs_modulus: float, arm_radius: float, ball_radius: float) -> float:
    """k [N/m^1.5] of a rigid ball of radius ``ball_radius`` [m] pressed into an incompressible
    elastic body of radius ``arm_radius`` [m] and Young's modulus [Pa]."""
    reduced = youngs_modulus / (1.0 - 0.25)
    return 4.0 / 3.0 * reduced * np.sqrt(arm_radius * ball_radius / (arm_radius + ball_radius))


def closest_capsule(points, radii, centre) -> tuple[int, float, np.ndarray, float]:
    """The capsule of the chain through ``points`` (P, 3) [m] with radii (P,) [m] that ``centre``
    [m] is closest to the surface of: (segment index i between points i and i+1, fraction s along
    it, the backbone point Q [m], the gap [m] from Q's surface: ``|c - Q| - r(Q)``)."""
    a, b = points[:-1], points[1:]
    d = b - a
    s = np.clip(np.einsum("ij,ij->i", centre - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-18),
                0.0, 1.0)
    q = a + s[:, None] * d
    gap = np.linalg.norm(centre - q, axis=1) - (radii[:-1] + s * (radii[1:] - radii[:-1]))
    i = int(np.argmin(gap))
    return i, float(s[i]), q[i], float(gap[i])


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

    def release(self):
        """Let the ball go (from rest at the held position)."""
        self.released = True

    def energy(self) -> float:
        """Kinetic + gravitational energy [J] (zero height at the pivot)."""
        m = self.config.mass
        return float(0.5 * m * self.v @ self.v - m * GRAVITY @ (self.p - self.config.pivot))

    def _contact_force(self, surface: ArmSurface, p, v) -> tuple:
        """(force on the ball [N], segment, fraction, overlap [m], gap [m]) at ball state (p, v)."""
        c = self.config
        i, s, q, gap = surface.closest(p)
        gap -= c.ball_radius
        if gap >= 0.0:
            return np.zeros(3), i, s, 0.0, gap
        normal = (p - q) / max(np.linalg.norm(p - q), 1e-12)
        arm_velocity = (1.0 - s) * surface.velocities[i] + s * surface.velocities[i + 1]
        rate = -float((v - arm_velocity) @ normal)            # d(overlap)/dt
        if self._approach is None:
            self._approach = max(rate, 1e-3)
        radius = surface.radii[i] + s * (surface.radii[i + 1] - surface.radii[i])
        k = hertz_stiffness(self.youngs_modulus, radius, c.ball_radius)
        damping = 0.75 * (1.0 - c.restitution ** 2) * rate / self._approach
        magnitude = max(k * (-gap) ** 1.5 * (1.0 + damping), 0.0)
        return magnitude * normal, i, s, -gap, gap

    def _acceleration(self, p, v, force) -> np.ndarray:
        c = self.config
        r = p - c.pivot
        r_hat = r / np.linalg.norm(r)
        pull = GRAVITY + force / c.mass
        return pull - (pull @ r_hat) * r_hat - (v @ v) / c.length * r_hat

    def advance(self, dt: float, surface: ArmSurface | None = None, substeps: int = 4) -> Contact | None:
        """Advance the ball by dt [s] (nothing while held), in ``substeps`` RK4 steps, against the
        arm ``surface`` held over the step (None: no arm). Returns the step's :class:`Contact` (None
        without a surface): its force is the RK4-weighted mean of what the ball felt, so that the
        arm takes the impulse the ball got."""
        far = np.inf
        if surface is not None:
            # broad phase: a ball farther than it and the arm can close in one step feels nothing
            far = surface.closest(self.p)[3] - self.config.ball_radius
            reach = (np.linalg.norm(self.v) + np.linalg.norm(GRAVITY) * dt
                     + np.abs(surface.velocities).sum(axis=1).max()) * dt
            if not self.released or far > 2.0 * reach + 1e-4:
                self._approach = None
                surface_in_reach = None
            else:
                surface_in_reach = surface
        if not self.released:
            return None if surface is None else Contact(np.zeros(3), 0, 0.0, 0.0, far)
        if surface is None or surface_in_reach is None:
            def evaluate(p, v):
                return np.zeros(3), 0, 0.0, 0.0, np.inf
        else:
            def evaluate(p, v):
                return self._contact_force(surface, p, v)
        h = dt / substeps
        impulse, deepest, gap, where = np.zeros(3), 0.0, far, (0, 0.0)

        def stage(p, v):
            nonlocal deepest, where
            f, i, s, overlap, g = evaluate(p, v)
            if overlap > deepest:
                deepest, where = overlap, (i, s)
            return v, self._acceleration(p, v, f), f, overlap, g

        c = self.config
        for _ in range(substeps):
            p, v = self.p, self.v
            k1 = stage(p, v)
            if k1[3] == 0.0:
                self._approach = None          # out of contact: the next touch starts a new one
            gap = min(gap, k1[4])
            k2 = stage(p + 0.5 * h * k1[0], v + 0.5 * h * k1[1])
            k3 = stage(p + 0.5 * h * k2[0], v + 0.5 * h * k2[1])
            k4 = stage(p + h * k3[0], v + h * k3[1])
            p = p + h / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            v = v + h / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            impulse += h / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
            self.p = c.pivot + (p - c.pivot) * (c.length / np.linalg.norm(p - c.pivot))
            r_hat = (self.p - c.pivot) / c.length
            self.v = v - (v @ r_hat) * r_hat
        if surface is None:
            return None
        return Contact(impulse / dt, where[0], where[1], deepest, gap)
