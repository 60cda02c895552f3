"""Time stepping of the arm: a linearly implicit (IMEX) Euler step, stable at millisecond steps.

The axial and torsional modes of the soft cone are stiff (hundreds of Hz, heavily damped), so the
elastic and damping forces are taken implicitly, linearised about the current state, and the rest
(gravity, Coriolis, tendons) explicitly:

    (M + h D + h^2 K_t) qd+ = M qd + h (F_g - C qd - F_el(q) - A u),    q+ = q + h qd+

This is first-order accurate and unconditionally stable for the linear stiff part.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from . import kernels
from .dynamics import OutOfDomainError
from .model import ArmData, ArmModel


@njit(cache=True)
def _imex_step(model_args, data_args, M, Cqd, Fg, Fel, Kt, Au, D, q, qd, u, h, q_out, qd_out):
    """One IMEX step; M .. Au are the workspace arrays in data_args (Au: A or A0), D the damping."""
    if not kernels.evaluate(*model_args, q, qd, 2, False, *data_args):
        return False
    n = q.shape[0]
    lhs = M + h * D + (h * h) * Kt
    rhs = M @ qd + h * (Fg - Cqd - Fel - Au @ u)
    v = np.linalg.solve(lhs, rhs)
    for a in range(n):
        qd_out[a] = v[a]
        q_out[a] = q[a] + h * v[a]
    return True


class ImexStepper:
    """Advances (q, qd) by fixed steps ``dt`` [s] under tensions u [N]; owns its workspace."""

    def __init__(self, model: ArmModel, dt: float, friction: bool = True):
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        self.model, self.dt, self.friction = model, float(dt), friction
        self.data = d = ArmData(model)
        self._args = (model.kernel_args, d.kernel_args, d.M, d.Cqd, d.Fg, d.Fel, d.Kt,
                      d.A if friction else d.A0, model.D)

    def step(self, q, qd, u):
        """Return (q, qd) one step later (new arrays). Raises OutOfDomainError if the state leaves
        the model's domain."""
        q = np.ascontiguousarray(q, dtype=float)
        qd = np.ascontiguousarray(qd, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        q_out = np.empty_like(q)
        qd_out = np.empty_like(qd)
        if not _imex_step(*self._args, q, qd, u, self.dt, q_out, qd_out):
            raise OutOfDomainError("the state left the model's domain during a step")
        return q_out, qd_out


@dataclass(frozen=True)
class Trajectory:
    """Sampled simulation: times t [s] (N,), coordinates q (N, n), rates qd (N, n), tensions u (N, n_t)."""
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    u: np.ndarray


def simulate(model: ArmModel, q0, qd0, tension, duration: float, dt: float = 1e-3,
             friction: bool = True) -> Trajectory:
    """Simulate ``duration`` [s] with the IMEX step; ``tension(t)`` returns tensions [N] at time t."""
    stepper = ImexStepper(model, dt, friction)
    steps = int(round(duration / dt))
    t = np.arange(steps + 1) * dt
    q = np.zeros((steps + 1, model.n))
    qd = np.zeros((steps + 1, model.n))
    u = np.zeros((steps + 1, model.n_tendons))
    q[0], qd[0] = q0, qd0
    for i in range(steps):
        u[i] = tension(t[i])
        q[i + 1], qd[i + 1] = stepper.step(q[i], qd[i], u[i])
    u[-1] = tension(t[-1])
    return Trajectory(t, q, qd, u)
