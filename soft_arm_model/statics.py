"""Static equilibrium of the arm under tendon tensions: Newton's method with load continuation.

Solves ``R(q) = F_el(q) - F_g(q) + A(q) u = 0`` (A with the paper's friction weight unless
``friction=False``). The Jacobian is taken by forward differences inside one numba call (n + 1
evaluations). Load continuation walks the tensions from ``u_start`` to ``u`` with a tangent
predictor and adaptive steps; when it cannot reach the target it raises
:class:`EquilibriumError` instead of returning an unconverged state.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from soft_arm_model import kernels

from .dynamics import OutOfDomainError
from .model import ArmData, ArmModel


class EquilibriumError(RuntimeError):
    """No equilibrium was found; ``reached`` is the load fraction in [0, 1) that did converge."""

    def __init__(self, message: str, reached: float, q_reached: np.ndarray | None):
        super().__init__(message)
        self.reached = reached
        self.q_reached = q_reached


@dataclass(frozen=True)
class Equilibrium:
    """A converged equilibrium: coordinates q, tensions u [N], Newton iterations and load steps
    used, final residual norm [generalised force units] and the residual Jacobian dR/dq at q."""
    q: np.ndarray
    u: np.ndarray
    iterations: int
    load_steps: int
    residual: float
    jacobian: np.ndarray


@njit(cache=True, nogil=True)
def _residual_kernel(model_args, data_args, Fg, Fel, Au, q, u, out):
    """out = F_el - F_g + A u at q; Fg, Fel and Au (A or A0) are the workspace arrays in data_args."""
    if not kernels.evaluate(*model_args, q, q, 1, False, *data_args):
        return False
    for a in range(q.shape[0]):
        acc = Fel[a] - Fg[a]
        for k in range(u.shape[0]):
            acc += Au[a, k] * u[k]
        out[a] = acc
    return True


@njit(cache=True, nogil=True)
def _residual_jacobian(model_args, data_args, Fg, Fel, Au, q, u, r0, jac):
    """Residual at q into r0 and its forward-difference Jacobian into jac; False outside the domain.
    The workspace is left at the last perturbed state."""
    n = q.shape[0]
    if not _residual_kernel(model_args, data_args, Fg, Fel, Au, q, u, r0):
        return False
    qp = q.copy()
    rp = np.empty(n)
    for b in range(n):
        step = 1e-7 * max(1.0, abs(q[b]))
        qp[b] = q[b] + step
        if not _residual_kernel(model_args, data_args, Fg, Fel, Au, qp, u, rp):
            qp[b] = q[b] - step
            step = -step
            if not _residual_kernel(model_args, data_args, Fg, Fel, Au, qp, u, rp):
                return False
        for a in range(n):
            jac[a, b] = (rp[a] - r0[a]) / step
        qp[b] = q[b]
    return True


class _Problem:
    def __init__(self, model: ArmModel, data: ArmData, friction: bool):
        self.model, self.data = model, data
        self.Au = data.A if friction else data.A0   # a view into the workspace, refreshed per call
        self.args = (model.kernel_args, data.kernel_args, data.Fg, data.Fel, self.Au)
        self.r = np.zeros(model.n)
        self.jac = np.zeros((model.n, model.n))
        # residual changes below this floor count as no increase in the line search
        self.residual_floor = float(np.abs(model.K).max()) * 1e-12

    def residual(self, q, u):
        ok = _residual_kernel(*self.args, q, u, self.r)
        return self.r.copy() if ok else None

    def linearise(self, q, u):
        ok = _residual_jacobian(*self.args, q, u, self.r, self.jac)
        return (self.r.copy(), self.jac.copy()) if ok else (None, None)

    def actuation(self):
        """A(q) at the last evaluated q (call ``residual`` first)."""
        return self.Au.copy()


def residual_jacobian(model: ArmModel, q, u, friction: bool = True,
                      data: ArmData | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Static residual R = F_el - F_g + A u at (q, u) and its tangent dR/dq at fixed u.

    dR/dq = K_t - dF_g/dq + sum_k u_k dA_k/dq (elastic tangent, gravity and tendon geometric
    stiffness), taken by forward differences of the kernel (n + 1 evaluations, relative step 1e-7).
    Raises :class:`~soft_arm_model.dynamics.OutOfDomainError` outside the model's domain.
    """
    u = np.ascontiguousarray(u, dtype=float)
    q = np.ascontiguousarray(q, dtype=float)
    r, jac = _Problem(model, data or ArmData(model), friction).linearise(q, u)
    if r is None:
        raise OutOfDomainError("configuration outside the model's domain")
    return r, jac


def static_residual(model: ArmModel, q, u, friction: bool = True, data: ArmData | None = None) -> np.ndarray:
    """The static residual R = F_el - F_g + A u at (q, u) [generalised force units] (zero at an
    equilibrium); raises :class:`~soft_arm_model.dynamics.OutOfDomainError` outside the domain."""
    pb = _Problem(model, data or ArmData(model), friction)
    r = pb.residual(np.ascontiguousarray(q, dtype=float), np.ascontiguousarray(u, dtype=float))
    if r is None:
        raise OutOfDomainError("configuration outside the model's domain")
    return r


def _newton(pb: _Problem, q, u, tol, max_iter):
    """Damped Newton from q; returns (q, iterations, |R|, jacobian) or None on failure."""
    r, jac = pb.linearise(q, u)
    if r is None:
        return None
    for it in range(1, max_iter + 1):
        try:
            dq = -np.linalg.solve(jac, r)
        except np.linalg.LinAlgError:
            return None
        norm0 = np.linalg.norm(r)
        alpha = 1.0
        while True:
            q_new = q + alpha * dq
            r_new = pb.residual(q_new, u)
            if r_new is not None and \
                    np.linalg.norm(r_new) <= (1.0 - 1e-4 * alpha) * norm0 + pb.residual_floor:
                break
            alpha *= 0.5
            if alpha < 1e-3:
                return None
        q = q_new
        if alpha * np.max(np.abs(dq)) < tol:
            r, jac = pb.linearise(q, u)
            if r is None:
                return None
            return q, it, float(np.linalg.norm(r)), jac
        r, jac = pb.linearise(q, u)
        if r is None:
            return None
    return None


def solve_equilibrium(model: ArmModel, u, q_start=None, u_start=None, friction: bool = True,
                      tol: float = 1e-10, max_iter: int = 25, min_step: float = 1.0 / 4096,
                      data: ArmData | None = None) -> Equilibrium:
    """Static equilibrium for tensions ``u`` [N] (u >= 0 pulls).

    Starts from ``q_start`` (default: the straight arm) at tensions ``u_start`` (default zero),
    first converging there, then continues the load to ``u``. ``tol`` bounds the last Newton step
    (coordinate units: rad or strain). Raises :class:`EquilibriumError` when no equilibrium is found.
    """
    u = np.asarray(u, dtype=float)
    if u.shape != (model.n_tendons,) or not np.all(np.isfinite(u)):
        raise ValueError(f"u must be {model.n_tendons} finite tensions [N], got {u}")
    u0 = np.zeros_like(u) if u_start is None else np.asarray(u_start, dtype=float)
    q = np.zeros(model.n) if q_start is None else np.array(q_start, dtype=float)
    pb = _Problem(model, data or ArmData(model), friction)
    total_iter = 0
    first = _newton(pb, q, u0, tol, max_iter)
    if first is None:
        raise EquilibriumError("no equilibrium at the starting tensions", 0.0, None)
    q, it, res, jac = first
    total_iter += it
    lam, step, steps = 0.0, 1.0, 0
    du = u - u0
    while lam < 1.0:
        trial = min(1.0, lam + step)
        u_t = u0 + trial * du
        try:  # tangent predictor: dq/dlam = -J^-1 A(q) du (the residual call refreshes A at q)
            pb.residual(q, u_t)
            q_pred = q - (trial - lam) * np.linalg.solve(jac, pb.actuation() @ du)
        except np.linalg.LinAlgError:
            q_pred = q.copy()
        sol = _newton(pb, q_pred, u_t, tol, max_iter)
        if sol is None:
            step *= 0.5
            if step < min_step:
                raise EquilibriumError(
                    f"load continuation stalled at {lam:.4f} of the way to u = {u.tolist()} N "
                    "(no converged equilibrium beyond it)", lam, q)
            continue
        q, it, res, jac = sol
        total_iter += it
        steps += 1
        lam = trial
        step = min(1.0, step * (2.0 if it <= 4 else 1.0))
    return Equilibrium(q=q, u=u.copy(), iterations=total_iter, load_steps=steps, residual=res,
                       jacobian=jac)
