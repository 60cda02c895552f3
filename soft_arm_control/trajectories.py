"""Time-parameterised task trajectories for tracking (the paper's stated future direction).

A trajectory starts at a point p0 of the task space (a target of ``tasks.yaml``) and moves in the
plane of two task coordinates (``plane``: their indices, e1 and e2 the unit vectors), with size a
[m] and period T [s], omega = 2 pi / T:

- ``line``:     p0 + a sin(omega t) e1 (back and forth through p0);
- ``circle``:   p0 + a ((cos(omega t) - 1) e1 + sin(omega t) e2) (radius a, through p0);
- ``figure8``:  p0 + a (sin(omega t) e1 + sin(2 omega t) / 2 e2) (crossing at p0).

:meth:`Trajectory.at` gives the desired coordinates and their velocity (the CLIK's feedforward),
:meth:`Trajectory.acceleration` their acceleration (the dynamic feedforward of a track goal).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SHAPES = ("line", "circle", "figure8")


@dataclass(frozen=True)
class Trajectory:
    """``shape`` (one of :data:`SHAPES`), size [m], period [s] and the two task coordinates
    (0-based indices) of its plane."""
    shape: str
    size: float
    period: float
    plane: tuple = (0, 1)

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise ValueError(f"trajectory shape {self.shape!r} is not one of {list(SHAPES)}")
        if not (self.size > 0 and self.period > 0) or len(self.plane) != 2 or self.plane[0] == self.plane[1]:
            raise ValueError("a trajectory needs a size > 0 m, a period > 0 s and two distinct plane "
                             f"coordinates, got {self.size}, {self.period}, {self.plane}")

    def offset(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(displacement from p0 [m], velocity [m/s], acceleration [m/s^2]) in the plane's (e1, e2)
        at time t [s]."""
        w = 2 * np.pi / self.period
        a, s, c = self.size, np.sin(w * t), np.cos(w * t)
        if self.shape == "line":
            return a * np.array([s, 0.0]), a * w * np.array([c, 0.0]), -a * w * w * np.array([s, 0.0])
        if self.shape == "circle":
            return a * np.array([c - 1.0, s]), a * w * np.array([-s, c]), -a * w * w * np.array([c, s])
        s2, c2 = np.sin(2 * w * t), np.cos(2 * w * t)
        return a * np.array([s, 0.5 * s2]), a * w * np.array([c, c2]), -a * w * w * np.array([s, 2.0 * s2])

    def acceleration(self, m: int, t: float) -> np.ndarray:
        """x_d's acceleration [m/s^2] at t [s], in a task space of m coordinates."""
        acc = np.zeros(m)
        acc[list(self.plane)] = self.offset(t)[2]
        return acc

    def at(self, p0, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(x_d [m], x_d velocity [m/s]) of the trajectory from ``p0`` (task coordinates) at t [s]."""
        x = np.array(p0, dtype=float)
        v = np.zeros_like(x)
        d, dv, _ = self.offset(t)
        x[list(self.plane)] += d
        v[list(self.plane)] = dv
        return x, v

    def path_speed(self, samples: int = 720) -> float:
        """The mean speed along the path over a period [m/s]."""
        t = np.arange(samples) * self.period / samples
        return float(np.mean([np.linalg.norm(self.offset(s)[1]) for s in t]))
