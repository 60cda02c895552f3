"""Static equilibrium of the arm under tendon tensions: Newton's method with load continuation.

Solves ``R(q) = F_el(q) - F_g(q) + A(q) u = 0`` (A with the paper's friction weight unless
``friction=False``). Its tangent dR/dq is analytic (``kernels.static_tangent``: the elastic tangent,
the gravity Hessian by one backward pass over the Magnus steps, the tendons' geometric stiffness
and the friction weight's derivative), at the cost of one to two evaluations of the kernel where
forward differences took n + 1; those stay as ``_fd_jacobian_oracle``, for the tests and the bench
only. Each damped Newton solve runs in one compiled call. Load continuation walks the tensions
from ``u_start`` to ``u`` with a tangent predictor and adaptive steps; when it cannot reach the
target it raises :class:`EquilibriumError` instead of returning an unconverged state.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_arm_model import kernels

from .dynamics import OutOfDomainError
from .lie import nonallocating_strict
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


@nonallocating_strict
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


@nonallocating_strict
def residual_jacobian_kernel(model_args, data_args, Fg, Fel, Au, q, u, friction, r0, jac, dA_dmu):
    """Residual at q into r0, its analytic Jacobian dR/dq into jac and dA/d mu into dA_dmu
    (kernels.static_tangent: one evaluation and one backward pass); False outside the domain."""
    if not _residual_kernel(model_args, data_args, Fg, Fel, Au, q, u, r0):
        return False
    kernels.static_tangent(*model_args, q, u, friction, *data_args, jac, dA_dmu)
    return True


@nonallocating_strict
def _fd_jacobian_oracle(model_args, data_args, Fg, Fel, Au, q, u, r0, jac, qp, rp):
    """Test oracle, not used by the solvers: the residual at q into r0 and its forward-difference
    Jacobian into jac (n + 1 evaluations, relative step 1e-7); False outside the domain. ``qp``
    and ``rp`` (n,): scratch for the perturbed state and its residual. The workspace is left at
    the last perturbed state."""
    n = q.shape[0]
    if not _residual_kernel(model_args, data_args, Fg, Fel, Au, q, u, r0):
        return False
    for b in range(n):
        qp[b] = q[b]
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


@nonallocating_strict
def _lu_solve(A, b, x, lu, piv):
    """x = A^-1 b by LU with partial pivoting (LAPACK's dgesv's algorithm, unblocked); False if a
    pivot is exactly zero (A singular), as dgesv reports it. Written out rather than
    np.linalg.solve: nothing allocated per Newton iteration, and its rounding is the same whatever
    kernels the machine's BLAS picks (the equilibria every figure starts from do not move with
    the processor). The loops run over unsigned indices, which numba need not check for negative
    values: the elimination's row update vectorises (element by element, so the rounding is the
    same)."""
    n = np.uint64(b.shape[0])
    one = np.uint64(1)
    for i in range(n):
        for j in range(n):
            lu[i, j] = A[i, j]
        x[i] = b[i]
    for k in range(n):
        pk = k
        big = abs(lu[k, k])
        for i in range(k + one, n):
            if abs(lu[i, k]) > big:
                big = abs(lu[i, k])
                pk = i
        if big == 0.0:
            return False
        piv[k] = pk
        if pk != k:
            for j in range(n):
                tmp = lu[k, j]
                lu[k, j] = lu[pk, j]
                lu[pk, j] = tmp
            tmp = x[k]
            x[k] = x[pk]
            x[pk] = tmp
        inv = 1.0 / lu[k, k]
        for i in range(k + one, n):
            f = lu[i, k] * inv
            if f != 0.0:
                lu[i, k] = f
                for j in range(k + one, n):
                    lu[i, j] -= f * lu[k, j]
                x[i] -= f * x[k]
            else:
                lu[i, k] = 0.0
    for ii in range(n):
        i = n - one - ii
        acc = x[i]
        for j in range(i + one, n):
            acc -= lu[i, j] * x[j]
        x[i] = acc / lu[i, i]
    return True


@nonallocating_strict
def _norm(v):
    acc = 0.0
    for i in range(v.shape[0]):
        acc += v[i] * v[i]
    return np.sqrt(acc)


@nonallocating_strict
def _newton_kernel(model_args, data_args, Fg, Fel, Au, friction, q, u, tol, max_iter, floor,
                   r, jac, dA_dmu, r_new, q_new, dq, lu, piv):
    """Damped Newton from q (overwritten with the solution): the number of iterations, or 0 when
    it fails (a singular tangent, no decrease of |R| down to a step of 1e-3, the domain left, or
    ``max_iter`` reached). r and jac hold the residual and its tangent at the solution. The
    residual of an accepted line-search step leaves the workspace at the new q, so the tangent
    there needs no second evaluation."""
    n = q.shape[0]
    if not residual_jacobian_kernel(model_args, data_args, Fg, Fel, Au, q, u, friction, r, jac, dA_dmu):
        return 0
    for it in range(1, max_iter + 1):
        if not _lu_solve(jac, r, dq, lu, piv):
            return 0
        for a in range(n):
            dq[a] = -dq[a]
        norm0 = _norm(r)
        alpha = 1.0
        while True:
            for a in range(n):
                q_new[a] = q[a] + alpha * dq[a]
            ok = _residual_kernel(model_args, data_args, Fg, Fel, Au, q_new, u, r_new)
            if ok and _norm(r_new) <= (1.0 - 1e-4 * alpha) * norm0 + floor:
                break
            alpha *= 0.5
            if alpha < 1e-3:
                return 0
        step = 0.0
        for a in range(n):
            q[a] = q_new[a]
            r[a] = r_new[a]
            step = max(step, abs(dq[a]))
        kernels.static_tangent(*model_args, q, u, friction, *data_args, jac, dA_dmu)
        if alpha * step < tol:
            return it
    return 0


class _Problem:
    def __init__(self, model: ArmModel, data: ArmData, friction: bool, oracle: bool = False):
        self.model, self.data = model, data
        self.friction = bool(friction)
        self.oracle = oracle     # the finite-difference Jacobian: for the tests and the bench only
        self.Au = data.A if friction else data.A0   # a view into the workspace, refreshed per call
        self.args = (model.kernel_args, data.kernel_args, data.Fg, data.Fel, self.Au)
        self.r = np.zeros(model.n)
        self.jac = np.zeros((model.n, model.n))
        self.dA_dmu = np.zeros((model.n, model.n_tendons))
        n = model.n
        self.newton_work = (np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, n)),
                            np.zeros(n, dtype=np.int64))
        self.oracle_work = (np.zeros(n), np.zeros(n))   # the oracle's perturbed state and residual
        # residual changes below this floor count as no increase in the line search
        self.residual_floor = float(np.abs(model.K).max()) * 1e-12

    def residual(self, q, u):
        ok = _residual_kernel(*self.args, q, u, self.r)
        return self.r.copy() if ok else None

    def linearise(self, q, u):
        if self.oracle:
            ok = _fd_jacobian_oracle(*self.args, q, u, self.r, self.jac, *self.oracle_work)
        else:
            ok = residual_jacobian_kernel(*self.args, q, u, self.friction, self.r, self.jac, self.dA_dmu)
        return (self.r.copy(), self.jac.copy()) if ok else (None, None)

    def actuation(self):
        """A(q) at the last evaluated q (call ``residual`` first)."""
        return self.Au.copy()


def residual_jacobian(model: ArmModel, q, u, friction: bool = True,
                      data: ArmData | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Static residual R = F_el - F_g + A u at (q, u) and its tangent dR/dq at fixed u.

    dR/dq = K_t - dF_g/dq + sum_k u_k dA_k/dq (elastic tangent, gravity and tendon geometric
    stiffness, the friction weight's derivative included), analytic (:func:`static_tangents`).
    Raises :class:`~soft_arm_model.dynamics.OutOfDomainError` outside the model's domain.
    """
    r, jac, _ = static_tangents(model, q, u, friction, data)
    return r, jac


def static_tangents(model: ArmModel, q, u, friction: bool = True,
                    data: ArmData | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static residual R = F_el - F_g + A u at (q, u), its tangent dR/dq (n, n) and the derivative
    of the friction-weighted A with respect to the friction coefficients, dA/d mu (n, n_tendons):
    column k is dA_k/d mubar_k = -int B^T Phi_k exp(-mubar_k S_k) S_k dX (S_k the wrap angle), the
    only column mubar_k moves, so d(A u)/d mu = dA/d mu diag(u); zero with ``friction=False``.
    All analytic: one evaluation of the kernel and one backward pass (``kernels.static_tangent``).
    Raises :class:`~soft_arm_model.dynamics.OutOfDomainError` outside the model's domain.
    """
    u = np.ascontiguousarray(u, dtype=float)
    q = np.ascontiguousarray(q, dtype=float)
    pb = _Problem(model, data or ArmData(model), friction)
    r, jac = pb.linearise(q, u)
    if r is None:
        raise OutOfDomainError("configuration outside the model's domain")
    return r, jac, pb.dA_dmu.copy()


def tangent_at(model: ArmModel, data: ArmData, q, u, friction: bool = True) -> np.ndarray:
    """dR/dq (n, n) at (q, u), from ``data`` as :func:`~soft_arm_model.dynamics.evaluate` left it at
    q (statics level or above; a kinematics-level evaluation at the same q since keeps it): the
    tangent's backward pass alone, for a caller that has just evaluated q. The same numbers as
    :func:`residual_jacobian` at (q, u)."""
    jac = np.empty((model.n, model.n))
    dA_dmu = np.empty((model.n, model.n_tendons))
    kernels.static_tangent(*model.kernel_args, np.ascontiguousarray(q, dtype=float),
                           np.ascontiguousarray(u, dtype=float), friction, *data.kernel_args, jac, dA_dmu)
    return jac


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
    if pb.oracle:
        return _newton_oracle(pb, q, u, tol, max_iter)
    q = np.array(q, dtype=float)
    it = _newton_kernel(*pb.args, pb.friction, q, np.ascontiguousarray(u, dtype=float), float(tol),
                        int(max_iter), pb.residual_floor, pb.r, pb.jac, pb.dA_dmu, *pb.newton_work)
    if it == 0:
        return None
    return q, it, float(np.linalg.norm(pb.r)), pb.jac.copy()


def _newton_oracle(pb: _Problem, q, u, tol, max_iter):
    """The same damped Newton in Python on the finite-difference oracle's Jacobian (the bench's
    reference); returns (q, iterations, |R|, jacobian) or None on failure."""
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
        r, jac = pb.linearise(q, u)
        if r is None:
            return None
        if alpha * np.max(np.abs(dq)) < tol:
            return q, it, float(np.linalg.norm(r)), jac
    return None


def solve_equilibrium(model: ArmModel, u, q_start=None, u_start=None, friction: bool = True,
                      tol: float = 1e-10, max_iter: int = 25, min_step: float = 1.0 / 4096,
                      data: ArmData | None = None) -> Equilibrium:
    """Static equilibrium for tensions ``u`` [N] (u >= 0 pulls).

    Starts from ``q_start`` (default: the straight arm) at tensions ``u_start`` (default zero),
    first converging there, then continues the load to ``u``. ``tol`` bounds the last Newton step
    (coordinate units: rad or strain). Raises :class:`EquilibriumError` when no equilibrium is found.
    """
    return _solve(_Problem(model, data or ArmData(model), friction), u, q_start, u_start, tol,
                  max_iter, min_step)


def _solve(pb: _Problem, u, q_start, u_start, tol, max_iter, min_step) -> Equilibrium:
    """:func:`solve_equilibrium` on the problem ``pb`` (the bench passes the oracle's)."""
    model = pb.model
    u = np.asarray(u, dtype=float)
    if u.shape != (model.n_tendons,) or not np.all(np.isfinite(u)):
        raise ValueError(f"u must be {model.n_tendons} finite tensions [N], got {u}")
    u0 = np.zeros_like(u) if u_start is None else np.asarray(u_start, dtype=float)
    q = np.zeros(model.n) if q_start is None else np.array(q_start, dtype=float)
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
