"""Time stepping of the arm: a linearly implicit (IMEX) Euler step, stable at millisecond steps.

The axial and torsional modes of the soft cone are stiff (hundreds of Hz, heavily damped), so the
elastic and damping forces are taken implicitly, linearised about the current state, and the rest
(gravity, Coriolis, tendons) explicitly:

    (M + h D + h^2 K_t) qd+ = M qd + h (F_g - C qd - F_el(q) - A u),    q+ = q + h qd+

This is first-order accurate and unconditionally stable for the linear stiff part.

Motor rotors on the tendons (direct drive) add their reflected mass m_k = J_k / r_k^2 [kg] to the
tendon coordinate: with an inextensible tendon the rotor turns with the shortening s_k, and the
tension that reaches the body is u_k - m_k s_k'' with s'' = -(A0^T qdd + Adot0^T qd). So u is the
tension the motor applies (torque / radius) and

    (M + A diag(m) A0^T) qdd + ... = ... - A (u + diag(m) Adot0^T qd),

with Adot0^T qd in closed form from the strains and their rates
(:func:`~soft_arm_model.kernels.tendon_rate_bias`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from soft_arm_model import kernels

from .dynamics import OutOfDomainError
from .model import ArmData, ArmModel


@njit(cache=True, nogil=True)
def _imex_prepare(model_args, data_args, rotor_mass, q, qd, markers, adot_qd):
    """Evaluate the workspace at (q, qd) (dynamics level, markers if asked) and, with rotors, the
    tendon acceleration term Adot0^T qd into adot_qd."""
    if not kernels.evaluate(*model_args, q, qd, 2, markers, *data_args):
        return False
    adot_qd[:] = 0.0
    for k in range(rotor_mass.shape[0]):
        if rotor_mass[k] != 0.0:
            kernels.tendon_rate_bias(model_args[0], model_args[1], data_args[0], qd, model_args[12],
                                     model_args[13], model_args[15], adot_qd)
            break
    return True


@njit(cache=True, nogil=True)
def _imex_advance(M, Cqd, Fg, Fel, Kt, Au, A0, D, rotor_mass, adot_qd, q, qd, u, f_ext, h, q_out,
                  qd_out):
    """The IMEX update from the prepared workspace (M .. A0 at (q, qd); Au: A or A0); f_ext: an
    external generalised force, taken explicitly."""
    n = q.shape[0]
    n_t = u.shape[0]
    lhs = M + h * D + (h * h) * Kt
    rhs = M @ qd
    force = u + rotor_mass * adot_qd
    s_rate = A0.T @ qd
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for k in range(n_t):
                acc += Au[a, k] * rotor_mass[k] * A0[b, k]
            lhs[a, b] += acc
        acc = 0.0
        for k in range(n_t):
            acc += Au[a, k] * rotor_mass[k] * s_rate[k]
        rhs[a] += acc
    rhs += h * (Fg - Cqd - Fel - Au @ force + f_ext)
    v = np.linalg.solve(lhs, rhs)
    for a in range(n):
        qd_out[a] = v[a]
        q_out[a] = q[a] + h * v[a]


class ImexStepper:
    """Advances (q, qd) by fixed steps ``dt`` [s] under tendon tensions u [N]; owns its workspace.

    ``rotor_mass``: reflected rotor mass [kg] per tendon (rotor inertia / pulley radius^2), or None.
    ``step`` does both halves; ``prepare`` then ``advance`` split them, so that a caller can read the
    workspace ``data`` at the current state (tendon lengths, markers: the sensors) before choosing u.
    """

    def __init__(self, model: ArmModel, dt: float, friction: bool = True, rotor_mass=None):
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        rotor = np.zeros(model.n_tendons) if rotor_mass is None else \
            np.array(rotor_mass, dtype=float).reshape(-1)
        if rotor.shape != (model.n_tendons,) or not np.all(np.isfinite(rotor)) or np.any(rotor < 0):
            raise ValueError(f"rotor_mass must be {model.n_tendons} masses >= 0 kg, got {rotor_mass}")
        self.model, self.dt, self.friction = model, float(dt), friction
        self.data = d = ArmData(model)
        self._adot = np.zeros(model.n_tendons)
        self._no_force = np.zeros(model.n)
        self._prepare_args = (model.kernel_args, d.kernel_args, rotor)
        self._advance_args = (d.M, d.Cqd, d.Fg, d.Fel, d.Kt, d.A if friction else d.A0, d.A0,
                              model.D, rotor, self._adot)
        self._state = None

    def prepare(self, q, qd, markers: bool = False):
        """Evaluate ``data`` at (q, qd) (dynamics terms, markers if asked). Raises OutOfDomainError
        if the state is outside the model's domain."""
        q = np.ascontiguousarray(q, dtype=float)
        qd = np.ascontiguousarray(qd, dtype=float)
        if not _imex_prepare(*self._prepare_args, q, qd, markers, self._adot):
            raise OutOfDomainError("the state left the model's domain")
        self._state = (q, qd)

    def advance(self, u, f_ext=None):
        """(q, qd) one step after the prepared state under tensions u [N] and an optional external
        generalised force ``f_ext`` (e.g. a payload's weight through a Jacobian) (new arrays)."""
        if self._state is None:
            raise RuntimeError("advance() needs a prepare() first")
        q, qd = self._state
        q_out = np.empty_like(q)
        qd_out = np.empty_like(qd)
        f_ext = self._no_force if f_ext is None else np.ascontiguousarray(f_ext, dtype=float)
        _imex_advance(*self._advance_args, q, qd, np.ascontiguousarray(u, dtype=float), f_ext,
                      self.dt, q_out, qd_out)
        self._state = None
        return q_out, qd_out

    def step(self, q, qd, u):
        """Return (q, qd) one step later (new arrays). Raises OutOfDomainError if the state leaves
        the model's domain."""
        self.prepare(q, qd)
        return self.advance(u)


@dataclass(frozen=True)
class Trajectory:
    """Sampled simulation: times t [s] (N,), coordinates q (N, n), rates qd (N, n), tensions u (N, n_t)."""
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    u: np.ndarray


def simulate(model: ArmModel, q0, qd0, tension, duration: float, dt: float = 1e-3,
             friction: bool = True, rotor_mass=None) -> Trajectory:
    """Simulate ``duration`` [s] with the IMEX step; ``tension(t)`` returns tensions [N] at time t
    (``rotor_mass``: see :class:`ImexStepper`)."""
    stepper = ImexStepper(model, dt, friction, rotor_mass)
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
