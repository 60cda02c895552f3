"""Kinematics and dynamics of the arm as free functions of (model, data, q[, qd, u]).

Equation of motion (README, Conventions; tension u >= 0 pulls):

    M(q) qdd + C(q, qd) qd + D qd + F_el(q) = F_g(q) - A(q) u

with F_el(q) = K q for the linear axial law (the neo-Hookean law is stiffer in compression).
Positions and rotations are in ``arm_base``; twists and Jacobians in the body (section) frame,
angular first. Every function that takes ``data`` reuses it as scratch; results returned as arrays
are copies unless the docstring says otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_arm_model import kernels

from .model import XI_STAR, ArmData, ArmModel, _substep

KINEMATICS, STATICS, DYNAMICS, CORIOLIS = 0, 1, 2, 3


class OutOfDomainError(RuntimeError):
    """The configuration leaves the model's domain (axial stretch <= 0 or a degenerate tendon)."""


def evaluate(model: ArmModel, data: ArmData, q, qd=None, level: int = DYNAMICS,
             markers: bool = False) -> ArmData:
    """Fill ``data`` with every term up to ``level`` at (q, qd) and return it.

    KINEMATICS: data.R, data.p, data.J at the points (and data.marker_* if ``markers``);
    STATICS: + data.Fg, data.Fel, data.Kt, data.A, data.A0, data.Lc, data.theta, data.wrap;
    DYNAMICS: + data.eta, data.psi (= Jdot qd), data.M, data.Cqd, kinetic energy;
    CORIOLIS: + data.Jd and the Coriolis matrix data.C.
    """
    q = np.ascontiguousarray(q, dtype=float)
    qd = np.zeros_like(q) if qd is None else np.ascontiguousarray(qd, dtype=float)
    if q.shape != (model.n,) or qd.shape != (model.n,):
        raise ValueError(f"q and qd must have shape ({model.n},), got {q.shape} and {qd.shape}")
    if not kernels.evaluate(*model.kernel_args, q, qd, level, markers, *data.kernel_args):
        raise OutOfDomainError("configuration outside the model's domain (axial stretch <= 0 or "
                               "a degenerate tendon tangent)")
    return data


@dataclass(frozen=True)
class Frame:
    """A section frame: rotation R (columns = section axes in arm_base), position p [m] in arm_base,
    body Jacobian J (6, n), angular rows first, in the section frame."""
    R: np.ndarray
    p: np.ndarray
    J: np.ndarray


def tip_frame(model: ArmModel, q, data: ArmData | None = None) -> Frame:
    """Frame of the tip section (X = L)."""
    data = evaluate(model, data or ArmData(model), q, level=KINEMATICS)
    return Frame(data.R[-1].copy(), data.p[-1].copy(), data.J[-1].copy())


def marker_positions(model: ArmModel, q, data: ArmData | None = None) -> np.ndarray:
    """Positions [m] in arm_base of the configured markers (``markers.positions``), (n_markers, 3)."""
    data = evaluate(model, data or ArmData(model), q, level=KINEMATICS, markers=True)
    return data.marker_p.copy()


def frame_at(model: ArmModel, q, X: float, data: ArmData | None = None) -> Frame:
    """Frame at any arc length X in [0, L] [m]: the model's own kinematics plus one Magnus sub-step."""
    if not 0.0 <= X <= model.length:
        raise ValueError(f"X = {X} m is outside [0, {model.length}] m")
    data = evaluate(model, data or ArmData(model), q, level=KINEMATICS)
    pt = int(np.flatnonzero(model.X <= X)[-1])
    h, B1, B2 = _substep(model.config.discretisation, model.n, float(model.X[pt]), float(X))
    R = np.empty((3, 3))
    p = np.empty(3)
    J = np.empty((6, model.n))
    q = np.ascontiguousarray(q, dtype=float)
    scratch = kernels.new_scratch(model.n)
    kernels._magnus_step(q, q, XI_STAR, h, B1, B2, np.uint64(0), np.uint64(model.n), data.R[pt],
                         data.p[pt], data.J[pt], R, p, J, 0, data.eta[pt], data.psi[pt], data.Jd[pt],
                         data.eta[pt], data.psi[pt], data.Jd[pt], scratch, scratch[0][3], scratch[1][0],
                         scratch[1][1])
    return Frame(R, p, J)


def elastic_force(model: ArmModel, q, data: ArmData | None = None) -> np.ndarray:
    """Generalised elastic force F_el(q) (= K q for the linear axial law)."""
    return evaluate(model, data or ArmData(model), q, level=STATICS).Fel.copy()


def gravity_force(model: ArmModel, q, data: ArmData | None = None) -> np.ndarray:
    """Generalised gravity force F_g(q) = -dU_g/dq (right-hand side)."""
    return evaluate(model, data or ArmData(model), q, level=STATICS).Fg.copy()


def actuation_matrix(model: ArmModel, q, friction: bool = True, data: ArmData | None = None):
    """A(q) (n, n_tendons): with the paper's friction weight, or the frictionless dL_c/dq."""
    data = evaluate(model, data or ArmData(model), q, level=STATICS)
    return (data.A if friction else data.A0).copy()


def tendon_lengths(model: ArmModel, q, data: ArmData | None = None) -> np.ndarray:
    """Tendon lengths L_c(q) [m] inside the body (base to tendon end)."""
    return evaluate(model, data or ArmData(model), q, level=STATICS).Lc.copy()


def actuation_coordinates(model: ArmModel, q, friction: bool = True,
                          data: ArmData | None = None) -> np.ndarray:
    """Tendon shortenings theta_a(q) [m] relative to the straight arm (q = 0).

    Without friction theta_a = L_c(0) - L_c(q). With friction, the paper's
    ``int t^T exp(-mu_S) [xi^ d + d']_3 dX`` replaces L_c (same sign convention).
    """
    cur = evaluate(model, data or ArmData(model), q, level=STATICS)
    if friction:
        return model.rest_theta - cur.theta
    return model.rest_tendon_lengths - cur.Lc


def potential_energies(model: ArmModel, q, data: ArmData | None = None) -> tuple[float, float]:
    """(elastic, gravitational) potential energies [J]; U_g = -int rho A g . p dX."""
    data = evaluate(model, data or ArmData(model), q, level=STATICS)
    return float(data.energies[1]), float(data.energies[2])


def mass_matrix(model: ArmModel, q, data: ArmData | None = None) -> np.ndarray:
    """Generalised mass matrix M(q), symmetric positive definite."""
    return evaluate(model, data or ArmData(model), q, level=DYNAMICS).M.copy()


def coriolis_matrix(model: ArmModel, q, qd, data: ArmData | None = None) -> np.ndarray:
    """Coriolis matrix C(q, qd) with Mdot = C + C^T; C qd is the Coriolis/centrifugal force."""
    return evaluate(model, data or ArmData(model), q, qd, level=CORIOLIS).C.copy()


def total_energy(model: ArmModel, q, qd, data: ArmData | None = None) -> float:
    """Kinetic + elastic + gravitational energy [J]."""
    return float(evaluate(model, data or ArmData(model), q, qd, level=DYNAMICS).energies.sum())


def forward_dynamics(model: ArmModel, q, qd, u, friction: bool = True,
                     data: ArmData | None = None) -> np.ndarray:
    """Generalised acceleration qdd for tendon tensions u [N] (u >= 0 pulls)."""
    data = evaluate(model, data or ArmData(model), q, qd, level=DYNAMICS)
    A = data.A if friction else data.A0
    rhs = data.Fg - data.Cqd - model.D @ qd - data.Fel - A @ np.asarray(u, dtype=float)
    return np.linalg.solve(data.M, rhs)
