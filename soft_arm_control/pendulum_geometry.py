"""The strike experiment's pendulum as the task describes it (``tasks.<task>.pendulum`` in
tasks.yaml): where it hangs, how it is released, and what its free swing does (where and when the
ball passes its speed peak). The simulated pendulum and its contact with the arm are the simulated
rig's (:mod:`soft_arm_drivers.sim.pendulum`); the strike's timing is the experiment's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GRAVITY = np.array([0.0, 0.0, -9.81])      # m/s^2 in arm_base (z up)


@dataclass(frozen=True)
class PendulumConfig:
    """Pivot [m, arm_base], rod length [m], ball mass [kg] and radius [m], release angle from the
    vertical [rad], the horizontal unit direction of the held ball from below the pivot, and the
    contact's restitution coefficient (0-1)."""
    pivot: np.ndarray
    length: float
    mass: float
    ball_radius: float
    release_angle: float
    direction: np.ndarray
    restitution: float

    @property
    def lowest_point(self) -> np.ndarray:
        """Where the ball's centre passes at its speed peak [m]."""
        return self.pivot + np.array([0.0, 0.0, -self.length])

    @property
    def held_position(self) -> np.ndarray:
        """The ball's centre before the release [m]."""
        a = self.release_angle
        return self.pivot + self.length * (np.sin(a) * self.direction - np.array([0.0, 0.0, np.cos(a)]))

    def time_to_lowest(self) -> float:
        """Time [s] from the release to the lowest point of a free swing: a quarter of the exact
        period, sqrt(L / g) K(sin^2(angle / 2)) (K the complete elliptic integral of the first
        kind), not the small-angle one."""
        import scipy.special        # here: every node imports this module, few swing a pendulum
        m = np.sin(self.release_angle / 2.0) ** 2
        return float(np.sqrt(self.length / np.linalg.norm(GRAVITY)) * scipy.special.ellipk(m))

    def peak_speed(self) -> float:
        """The free swing's speed at the lowest point [m/s]: sqrt(2 g L (1 - cos angle))."""
        return float(np.sqrt(2 * np.linalg.norm(GRAVITY) * self.length * (1 - np.cos(self.release_angle))))
