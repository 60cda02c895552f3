"""Closed-loop inverse kinematics for underactuated systems (paper eq. CLIK).

With task x = h_g(q) of dimension m = n_a, the stacked Jacobian ``Z = [J_x; dG_theta_u/dq]`` is square
and the law

    qdot = Z^-1 [xdot_d + Gamma_Z (x_d - x); -Gamma_eps G_theta_u]

makes the task error and the equilibrium residual decay independently: e' = -Gamma_Z e and
G_theta_u' = -Gamma_eps G_theta_u. In collocated coordinates this is the paper's
``thetadot = Pbar_eps Gamma_Z e - Pbar_Z Gamma_eps G_theta_u`` with ``[Pbar_eps, Pbar_Z] = J_h Z^-1``
and ``qdot = J_h^-1 thetadot`` (:func:`projectors`). Near a singular Z the solve is damped (rows
scaled to unit norm, damped least squares below a relative singular value threshold).

Two variants: precomputed (x from the model; :meth:`Clik.precompute` solves for the end point
offline, a damped Newton iteration on the same equations, i.e. the CLIK flow with unit gain-step) and
online (x measured at the mocap rate; :meth:`Clik.step`). Targets are checked before anything moves:
:class:`TargetError` says why a target cannot be reached or needs tensions outside the limits.

Feasibility. An online step whose end point would need equilibrium tensions outside [u_min, u_max]
is not dropped: it is replaced by the bounded least-squares step. On the equilibrium set the tension
rate is linear in the task velocity v, ``udot = P v + c`` (``P = dG_theta_a/dq Z^-1[:, :m]``, c from
the equilibrium term), so the step solves ``min |v - Gamma_Z e|`` subject to the tensions of its end
point staying within the limits (exactly, on the tension rate: :mod:`.box_least_squares`). Its
fixed point is where the task error is orthogonal to every direction the free tensions can still
move the task: the closest feasible point, to first order. Such steps are reported
(``ClikStep.constrained``).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from soft_arm_model import (DYNAMICS, STATICS, ArmData, EquilibriumError, OutOfDomainError, evaluate,
                            solve_equilibrium)

from .box_least_squares import box_least_squares
from .collocated import (CollocatedData, CollocatedModel, collocated_jacobian, evaluate_collocated,
                         full_tensions)
from .task_space import TaskSpace


_LIMIT_MARGIN = 1e-3   # a bounded step aims this fraction of the tension range inside the limits


class TargetError(ValueError):
    """A target is unreachable (no equilibrium reaches it) or infeasible (tensions out of limits);
    ``closest``: the model equilibrium closest to it within the limits (a ClikPoint), when the
    search of :meth:`Clik.closest_feasible` ran and found one."""

    def __init__(self, message: str, closest=None):
        super().__init__(message)
        self.closest = closest


@dataclass(frozen=True)
class ClikGains:
    """Gamma_Z and Gamma_eps [1/s] (scalar times identity); ``singular_threshold``: relative singular
    value of the row-normalised Z below which the solve is damped."""
    task: float
    equilibrium: float
    singular_threshold: float = 1e-4

    def __post_init__(self):
        if not (self.task > 0 and self.equilibrium > 0):
            raise ValueError(f"CLIK gains must be > 0 1/s, got {self.task}, {self.equilibrium}")
        if not 0 < self.singular_threshold < 1:
            raise ValueError(f"singular_threshold must be in (0, 1), got {self.singular_threshold}")


@dataclass(frozen=True)
class ClikPoint:
    """A reference configuration q_d with its tendon references: shortenings s_d [m] (all tendons),
    feedforward u_ff = G_theta_a(q_d) [N] (active tendons) and model task coordinates x [m]."""
    q: np.ndarray
    shortening: np.ndarray
    u_ff: np.ndarray
    x: np.ndarray


@dataclass(frozen=True)
class ClikStep:
    """Diagnostics of one CLIK evaluation: qdot, the task error e [m], G_theta_u, cond(Z) of the
    row-normalised Z and whether the solve was damped."""
    qdot: np.ndarray
    error: np.ndarray
    G_theta_u: np.ndarray
    condition: float
    damped: bool
    constrained: bool = False
    held: bool = False


class Clik:
    """Underactuated CLIK for one task and one collocated model (m must equal n_a).

    ``closest_margin`` [N]: the margin from the tension limits of the closest feasible point
    :meth:`precompute` offers for a target it cannot reach (None: a thousandth of the range)."""

    def __init__(self, cm: CollocatedModel, task: TaskSpace, gains: ClikGains,
                 tension_limits: tuple[float, float], closest_margin: float | None = None):
        task.check(cm.model)
        if task.m != cm.n_a:
            raise ValueError(f"the task has {task.m} coordinates but {cm.n_a} tendons are actuated "
                             "(the underactuated CLIK needs m = n_a)")
        self.cm, self.task, self.gains = cm, task, gains
        self.u_min, self.u_max = map(float, tension_limits)
        self.closest_margin = closest_margin
        self.cd = CollocatedData(cm)
        self._at = None          # q of the last evaluation held in cd, _x, _Jx
        self._x = self._Jx = None
        self._Z = self._factor = None
        self._Ga = None          # dG_theta_a/dq with the current Z: the tension rate per qdot

    # -- evaluation -------------------------------------------------------------------------------
    def _evaluate(self, q):
        """Collocated terms and task coordinates at q, skipped when q is the last point evaluated."""
        q = np.asarray(q, dtype=float)
        if self._at is None or not np.array_equal(q, self._at):
            self._at = None
            evaluate_collocated(self.cm, self.cd, q, markers=True)
            self._x, self._Jx = self.task.read(self.cm.model, self.cd.arm)
            self._at = q.copy()
        return self._x

    def _stack(self, q, refresh: bool = True):
        """Model task coordinates and Z at q. With ``refresh`` False the last Z is reused (the
        residuals are always fresh, so the fixed point is unchanged: a chord iteration)."""
        x = self._evaluate(q)
        if refresh or self._Z is None:
            dG = collocated_jacobian(self.cm, self.cd)
            self._Z, self._Ga = np.vstack([self._Jx, dG[self.cm.n_a:]]), dG[:self.cm.n_a]
            self._factor = None
        return x, self._Z

    def _solve(self, Z, rhs):
        """Z^-1 rhs (a vector or the columns of a matrix) with unit-norm rows; damped least squares
        below the singular threshold. The singular values alone decide (the full decomposition
        only where they call for damping: an inverse costs half of it); the inverse of the current
        Z is kept for the chord steps that reuse it."""
        if self._factor is None or self._factor[0] is not Z:
            w = 1.0 / np.sqrt(np.einsum("ij,ij->i", Z, Z))
            Zw = Z * w[:, None]
            sig = np.linalg.svd(Zw, compute_uv=False)
            damped = sig[-1] < self.gains.singular_threshold * sig[0]
            cond = sig[0] / sig[-1] if sig[-1] > 0 else np.inf
            if damped:
                U, sig, Vt = np.linalg.svd(Zw)
                lam = self.gains.singular_threshold * sig[0]
                inverse = Vt.T @ ((sig / (sig ** 2 + lam ** 2))[:, None] * U.T)
            else:
                inverse = np.linalg.inv(Zw)
            self._factor = (Z, w, inverse, float(cond), bool(damped))
        _, w, inverse, cond, damped = self._factor
        if rhs.ndim == 2:
            return inverse @ (w[:, None] * rhs), cond, damped
        return inverse @ (w * rhs), cond, damped

    def velocity(self, q, x_d, x=None, xd_dot=None, refresh: bool = True) -> ClikStep:
        """qdot of the CLIK law at q [generalised coordinates] for target x_d [m].

        x: measured task coordinates [m] (online variant); default the model's x(q) (precomputed).
        xd_dot: target velocity [m/s] (default zero: regulation). refresh: recompute Z (False
        reuses the last one; the residuals G_theta_u and e are always evaluated at q).
        """
        x_model, Z = self._stack(q, refresh)
        x = x_model if x is None else np.asarray(x, dtype=float)
        e = np.asarray(x_d, dtype=float) - x
        rhs = np.concatenate([(0.0 if xd_dot is None else np.asarray(xd_dot, dtype=float))
                              + self.gains.task * e, -self.gains.equilibrium * self.cd.G_theta_u])
        qdot, cond, damped = self._solve(Z, rhs)
        return ClikStep(qdot, e, self.cd.G_theta_u.copy(), cond, damped)

    def projectors(self, q) -> tuple[np.ndarray, np.ndarray]:
        """The paper's (Pbar_eps (n, m), Pbar_Z (n, n - n_a)): the column blocks of J_h Z^-1 at q."""
        _, Z = self._stack(q)
        P = self.cd.J_h @ np.linalg.inv(Z)
        return P[:, :self.task.m], P[:, self.task.m:]

    def reference(self, q) -> ClikPoint:
        """Tendon references of configuration q (shortenings, feedforward, model task coordinates)."""
        x = self._evaluate(q)
        return ClikPoint(np.array(q, dtype=float), self.cd.shortening.copy(), self.cd.u_eq.copy(),
                         x.copy())

    def feasibility_error(self, u_ff) -> str | None:
        """Why the feedforward tensions [N] violate [u_min, u_max], or None if they do not."""
        for k, u in zip(self.cm.active, u_ff):
            if not self.u_min <= u <= self.u_max:
                return (f"{self.cm.model.tendon_names[k]} would need {u:.3f} N at equilibrium, outside "
                        f"[{self.u_min}, {self.u_max}] N")
        return None

    # -- online variant ---------------------------------------------------------------------------
    def step(self, q, x_d, dt: float, x=None, refresh: bool = True,
             xd_dot=None) -> tuple[ClikPoint | None, ClikStep]:
        """One explicit Euler step of length dt [s] from q_d = q; x: measured task coordinates [m]
        (online) or None (model); refresh: see :meth:`velocity`; xd_dot: the target's velocity
        [m/s] (a tracked trajectory's feedforward; default zero). Returns (the new reference,
        diagnostics). When the step would need tensions outside the limits, the bounded
        least-squares step is taken instead (``constrained``); the reference is None (``held``: keep
        the last one) only when no step within the limits and the model's domain is found."""
        info = self.velocity(q, x_d, x, xd_dot, refresh=refresh)
        u0 = self.cd.u_eq.copy()             # the tensions at q, before the trial moves cd
        q = np.asarray(q, dtype=float)
        ref = self._feasible_reference(q + dt * info.qdot)
        if ref is not None:
            return ref, info
        qdot = self._bounded_velocity(u0, dt, info, xd_dot)
        for scale in (1.0, 0.5, 0.25, 0.125):
            ref = self._feasible_reference(q + scale * dt * qdot)
            if ref is not None:
                return ref, ClikStep(scale * qdot, info.error, info.G_theta_u, info.condition,
                                     info.damped, constrained=True)
        return None, ClikStep(info.qdot, info.error, info.G_theta_u, info.condition, info.damped,
                              constrained=True, held=True)

    def dynamic_reference(self, q, xd_dot, xd_ddot, rotor_mass: float = 0.0,
                          refresh: bool = True) -> ClikPoint:
        """The reference that keeps the arm on a moving task path through the equilibrium q, to first
        order in the path's inertial and damping forces (a track goal's dynamic feedforward).

        Along the path the equilibria move with qdot = Z^-1 [xd_dot; 0] and qddot = Z^-1 [xd_ddot; 0]
        (xd_dot [m/s], xd_ddot [m/s^2]; the Zdot qdot term is neglected), which takes the forces
        f = (M + m_r A A0^T) qddot + D qdot (the arm's mass matrix, the rotors' reflected mass
        ``rotor_mass`` [kg] on every tendon, the body's damping). The quasi-static reference q
        leaves them to the arm: it swings off the path. The returned reference q + dq balances them
        where the inner loop cannot act, with the task point unchanged: Z dq = [0; -(J_h^-T f)_u];
        its feedforward adds the actuated part, u_ff = G_theta_a(q + dq) + (J_h^-T f)_a. With
        friction off, f uses the frictionless A. A first-order correction: right below the held
        arm's lowest mode, wrong above it. The quasi-static reference itself if q + dq leaves the
        model's domain. ``refresh``: see :meth:`velocity`."""
        m = self.task.m
        _, Z = self._stack(q, refresh)
        arm = evaluate(self.cm.model, self.cd.arm, np.asarray(q, dtype=float), level=DYNAMICS)
        zeros = np.zeros(Z.shape[0] - m)
        qdot = self._solve(Z, np.concatenate([np.asarray(xd_dot, dtype=float), zeros]))[0]
        qddot = self._solve(Z, np.concatenate([np.asarray(xd_ddot, dtype=float), zeros]))[0]
        A = arm.A if self.cm.friction else arm.A0
        f = arm.M @ qddot + rotor_mass * (A @ (arm.A0.T @ qddot)) + self.cm.model.D @ qdot
        forces = self.cd.solve_transposed(f)
        dq = self._solve(Z, np.concatenate([np.zeros(m), -forces[m:]]))[0]
        try:
            point = self.reference(np.asarray(q, dtype=float) + dq)
        except (OutOfDomainError, ValueError):
            return self.reference(q)
        return ClikPoint(point.q, point.shortening, point.u_ff + forces[:m], point.x)

    def _feasible_reference(self, q) -> ClikPoint | None:
        """The reference of q if q is in the model's domain and its tensions within the limits."""
        try:
            ref = self.reference(q)
        except (OutOfDomainError, ValueError):
            return None
        return ref if self.feasibility_error(ref.u_ff) is None else None

    def _bounded_velocity(self, u0, dt: float, info: ClikStep, xd_dot=None) -> np.ndarray:
        """qdot of the bounded least-squares step from the configuration of ``info`` with
        equilibrium tensions u0 [N] (see the module's docstring): the task velocity closest to
        xd_dot + Gamma_Z e whose tension rate keeps u0 + dt udot within the limits, the
        equilibrium term unchanged."""
        m = self.task.m
        Z, Ga = self._Z, self._Ga            # as used by velocity() for this step
        task_columns = self._solve(Z, np.eye(Z.shape[0])[:, :m])[0]
        w = -self.gains.equilibrium * info.G_theta_u
        qdot_eq = self._solve(Z, np.concatenate([np.zeros(m), w]))[0]
        P = Ga @ task_columns                # tension rate per task velocity
        c = Ga @ qdot_eq                     # tension rate of the equilibrium term
        A = np.linalg.pinv(P)                # task velocity per tension rate
        margin = _LIMIT_MARGIN * (self.u_max - self.u_min)      # room for the step's curvature
        lo = (self.u_min + margin - u0) / dt
        hi = (self.u_max - margin - u0) / dt
        wanted = self.gains.task * info.error + (0.0 if xd_dot is None else np.asarray(xd_dot, dtype=float))
        udot = box_least_squares(A, wanted + A @ c, lo, hi)
        return task_columns @ (A @ (udot - c)) + qdot_eq

    def equilibrium_of_tensions(self, q_start):
        """A function of the actuated tensions u [N] (the other tendons held): (q, x, dx/du) of
        the model's equilibrium under u, its task coordinates x [m] and dx/du = -J_x (dR/dq)^-1 A_a
        from the implicit function theorem. Each solve starts from the last one's equilibrium
        (the first from ``q_start``); the same u again returns the last result."""
        cm = self.cm
        model, active = cm.model, list(cm.active)
        data = ArmData(model)
        last = {"u": None, "q": np.asarray(q_start, dtype=float), "value": None}

        def equilibrium(u):
            u = np.asarray(u, dtype=float)
            if last["u"] is None or not np.array_equal(u, last["u"]):
                u_start = None if last["u"] is None else full_tensions(cm, last["u"])
                eq = solve_equilibrium(model, full_tensions(cm, u), q_start=last["q"], u_start=u_start,
                                       friction=cm.friction, data=data)
                evaluate(model, data, eq.q, level=STATICS)
                A = (data.A if cm.friction else data.A0)[:, active]     # a copy (fancy index)
                x, Jx = self.task.evaluate(model, eq.q, data)
                last.update(u=u.copy(), q=eq.q, value=(eq.q, x, -Jx @ np.linalg.solve(eq.jacobian, A)))
            return last["value"]
        return equilibrium

    def closest_feasible(self, x_d, starts, margin: float | None = None) -> ClikPoint:
        """The model equilibrium closest to x_d [m] whose actuated tensions lie in
        [u_min + margin, u_max - margin] [N] (default margin: a thousandth of the range): bounded
        least squares on the tensions, ``min |x(u) - x_d|`` with x(u) the task coordinates of the
        equilibrium under u (the other tendons held) and dx/du = -J_x (dR/dq)^-1 A_a from the
        implicit function theorem. Local: the best over ``starts`` (configurations; their
        equilibrium tensions, clipped into the box, start the search). x_d itself when it is
        feasible and reachable from a start."""
        from scipy.optimize import least_squares   # here: at import, 0.1-0.25 s of a CLIK node's start

        margin = _LIMIT_MARGIN * (self.u_max - self.u_min) if margin is None else float(margin)
        lo, hi = self.u_min + margin, self.u_max - margin
        x_d = np.asarray(x_d, dtype=float)
        best = None
        for q in starts:
            u0 = np.clip(self.reference(q).u_ff, lo, hi)
            equilibrium = self.equilibrium_of_tensions(q)
            try:
                sol = least_squares(lambda u: equilibrium(u)[1] - x_d, u0, jac=lambda u: equilibrium(u)[2],
                                    bounds=(lo, hi), x_scale=hi - lo, xtol=1e-10, ftol=1e-10, gtol=1e-10)
            except (EquilibriumError, OutOfDomainError):
                continue
            if best is None or sol.cost < best[0]:
                best = (sol.cost, equilibrium(sol.x)[0])
        if best is None:
            raise TargetError("no equilibrium within the tension limits found near "
                              f"{x_d.round(4).tolist()} m")
        return self.reference(best[1])

    # -- precomputed variant ----------------------------------------------------------------------
    def _newton(self, q, x_d, tol: float, max_iter: int):
        """Damped Newton on [x(q) - x_d; G_theta_u(q)] = 0 from q; returns (q, iterations) or None."""
        def merit(qq):
            try:
                x, Z = self._stack(qq)
            except (OutOfDomainError, ValueError):
                return None
            # residuals over the row norms of Z (the scaling of _solve, so that its step descends):
            # each is the coordinate change that would cancel it
            norms = np.linalg.norm(Z, axis=1)
            r = np.concatenate([x - x_d, self.cd.G_theta_u]) / norms
            return x, Z, float(r @ r), self.cd.G_theta_u.copy(), norms[self.task.m:]

        state = merit(q)
        if state is None:
            return None
        for it in range(1, max_iter + 1):
            x, Z, phi, G_u, scale = state
            if np.max(np.abs(x - x_d)) < tol and np.max(np.abs(G_u) / scale) < tol:
                return q, it - 1
            dq, _, _ = self._solve(Z, np.concatenate([x_d - x, -G_u]))
            alpha = 1.0
            while True:
                trial = merit(q + alpha * dq)
                if trial is not None and trial[2] < (1.0 - 1e-4 * alpha) * phi:
                    break
                alpha *= 0.5
                if alpha < 1.0 / 64:
                    return None
            q, state = q + alpha * dq, trial
        return None

    def solve(self, x_d, q_start, tol: float = 1e-6, max_iter: int = 40, max_splits: int = 6):
        """The model equilibrium whose task coordinates are x_d [m], whatever its tensions: Newton
        from q_start along the straight task path to x_d in halved sub-steps. Returns (q, 1.0), or
        (None, the fraction of the path reached)."""
        q = np.array(q_start, dtype=float)
        x0 = self._evaluate(q).copy()
        lam, step = 0.0, 1.0
        while lam < 1.0:
            trial = min(1.0, lam + step)
            sol = self._newton(q, x0 + trial * (x_d - x0), tol if trial == 1.0 else 1e-4, max_iter)
            if sol is None:
                step *= 0.5
                if step < 0.5 ** max_splits:
                    return None, lam
                continue
            q, lam = sol[0], trial
            step = min(1.0, 2.0 * step)
        return q, 1.0

    def precompute(self, x_d, q_start, seeds=(), tol: float = 1e-6, max_iter: int = 40,
                   max_splits: int = 6, max_seeds: int = 8, search: bool = True) -> ClikPoint:
        """The equilibrium reference q_d whose model task coordinates are x_d [m].

        Newton from q_start, continued along the straight task path in halved sub-steps when a full
        step fails. A task point can have several equilibria (and the straight path can leave the
        workspace), so when q_start gives none within the tension limits, the ``seeds`` (pairs of
        task coordinates and configurations, e.g. from :func:`equilibrium_seeds`) nearest to x_d are
        tried in turn, and last (with ``search``) a search over the tensions within the limits from
        q_start and the 3 nearest seeds (:meth:`closest_feasible`), which goes round where the
        straight path leaves the workspace. Raises TargetError when no equilibrium reaches x_d or
        none is within the limits; after a search, its ``closest`` is the closest point found
        ``closest_margin`` inside the limits.
        """
        x_d = np.asarray(x_d, dtype=float)
        if x_d.shape != (self.task.m,) or not np.all(np.isfinite(x_d)):
            raise TargetError(f"a target needs {self.task.m} finite coordinates "
                              f"({', '.join(self.task.labels())}), got {x_d.tolist()}")
        starts = [np.asarray(q_start, dtype=float)] + [
            q for x, q in sorted(seeds, key=lambda s: float(np.linalg.norm(s[0] - x_d)))[:max_seeds]]
        reasons = []
        for q0 in starts:
            q, reached = self.solve(x_d, q0, tol, max_iter, max_splits)
            if q is None:
                reasons.append(f"unreachable (stalled at {reached:.0%} of the way)")
                continue
            ref = self.reference(q)
            reason = self.feasibility_error(ref.u_ff)
            if reason is None:
                return ref
            reasons.append(f"infeasible ({reason})")
        closest = None
        if search:            # on the tensions, round where the straight task path leaves the workspace
            try:
                closest = self.closest_feasible(x_d, starts[:4], self.closest_margin)
            except TargetError:
                pass
            if closest is not None and np.max(np.abs(closest.x - x_d)) < tol:
                return closest
        kind = "infeasible" if any(r.startswith("infeasible") for r in reasons) else "unreachable"
        raise TargetError(f"target {x_d.round(4).tolist()} m ({', '.join(self.task.labels())}) is "
                          f"{kind}: from {len(starts)} starting configuration(s): " + "; ".join(reasons),
                          closest)


def equilibrium_seeds(clik: Clik, levels) -> list:
    """(task coordinates, q) of the model's equilibria for every combination of ``levels`` [N] on the
    actuated tendons (the others held), for :meth:`Clik.precompute`; non-converging ones are skipped."""
    cm = clik.cm
    out = []
    for u in itertools.product([float(v) for v in levels], repeat=cm.n_a):
        try:
            q = solve_equilibrium(cm.model, full_tensions(cm, u)).q
        except EquilibriumError:
            continue
        out.append((clik.task.evaluate(cm.model, q)[0], q))
    return out
