"""How far a task target is from the tension limits on arms that differ from the model.

A target is *robust* when the arms the controller may really meet all hold it at equilibrium with
tensions inside the limits, with a margin. The precomputed CLIK solves the target on the model; the
solution is then followed, target fixed, while the arm is deformed step by step into each variant
(Young's modulus scaled, a point mass added at the tip): the variant's equilibrium at the target on
the branch the model's solution lies on, which is the one the online CLIK walks the real arm to.
The margin of a variant is the smallest distance [N] of its task tendons' tensions from
``[u_min, u_max]`` (negative outside). A target must also be a *stable* equilibrium of every
variant: a curled arm with a load at its tip buckles sideways (two mirror equilibria for the same
tensions, the one between them unstable), and no reference between the branches can be held. The
stability of a variant is the smallest real part of the eigenvalues of its static stiffness under
the inner loop, ``dR/dq + A K_p A0^T`` (the tangent of the static residual at fixed tensions plus
the proportional gain on the task tendons' shortenings); it must be positive. The default variants
are the rule the default targets of ``tasks.yaml`` are chosen by (:data:`STIFFNESS_SCALES` x
:data:`TIP_PAYLOADS`: a margin of at least :data:`MIN_MARGIN` and a positive stability on every one).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from soft_arm_model import ArmConfig, build_model
from soft_arm_model.dynamics import OutOfDomainError
from soft_arm_model.statics import EquilibriumError, solve_equilibrium

from .clik import Clik, ClikPoint, TargetError
from .collocated import full_tensions, held_stiffness, lowest_held_frequency
from .config import ControlConfig, TaskConfig
from .outer_loop import OuterLoop, clik_for, outer_loop_for

STIFFNESS_SCALES = (0.8, 1.0, 1.25)   # Young's modulus of the arm / the model's
# kg, an unmodelled mass at the tip; a heavier load than 2 g belongs in arm.tip_mass (a curled arm
# with 5 g at its tip buckles sideways above z = -0.28 m, whatever the controller knows)
TIP_PAYLOADS = (0.0, 0.002)
MIN_MARGIN = 0.1                      # N, on every variant
SAFE_MARGIN = 0.02                    # Hz above min_frequency the closest safe point is searched at


@dataclass(frozen=True)
class Variant:
    """An arm the controller may meet: its Young's modulus scale and an extra tip mass [kg]."""
    stiffness: float
    payload: float

    def arm(self, arm: ArmConfig) -> ArmConfig:
        material = replace(arm.material, youngs_modulus=arm.material.youngs_modulus * self.stiffness)
        return replace(arm, material=material, tip_mass=arm.tip_mass + self.payload)


@dataclass(frozen=True)
class VariantMargin:
    """A target on one variant: the task tendons' equilibrium tensions [N] and their margin [N]
    from the limits (negative outside them) and its stability (the smallest real part of the
    eigenvalues of the static stiffness under the inner loop [N m], positive when stable), or None
    and the reason when the variant has no equilibrium at the target on the model's branch."""
    variant: Variant
    tensions: np.ndarray | None
    margin: float | None
    stability: float | None = None
    reason: str | None = None

    @property
    def stable(self) -> bool:
        return self.stability is not None and self.stability > 0


def default_variants(stiffness=STIFFNESS_SCALES, payloads=TIP_PAYLOADS) -> list:
    return [Variant(float(s), float(p)) for s in stiffness for p in payloads]


class MarginChecker:
    """Solves targets of one task on each variant; ``steps``: the homotopy steps from the model to a
    variant (the models and CLIKs are built once)."""

    def __init__(self, arm: ArmConfig, control: ControlConfig, task: TaskConfig, variants=None,
                 steps: int = 4):
        self.control, self.task = control, task
        self._kp = np.array([control.proportional[k] for k in task.tendons])
        self.variants = default_variants() if variants is None else list(variants)
        self.nominal = outer_loop_for(build_model(arm), control, task)
        self._paths = [[clik_for(build_model(Variant(1.0 + (v.stiffness - 1.0) * k / steps,
                                                     v.payload * k / steps).arm(arm)), control, task)
                        for k in range(1, steps + 1)] for v in self.variants]

    def stability(self, clik: Clik, q, tensions) -> float:
        """The smallest real part of the eigenvalues of ``dR/dq + A K_p A0^T`` at q under the task
        tendons' ``tensions`` [N] (positive: a stable equilibrium under the inner loop)."""
        return float(np.linalg.eigvals(held_stiffness(clik.cm, q, tensions, self._kp)).real.min())

    def margin(self, tensions) -> float:
        """The distance [N] of ``tensions`` from the limits (negative outside)."""
        u = np.asarray(tensions, dtype=float)
        return float(min((u - self.control.tension_min).min(), (self.control.tension_max - u).min()))

    def check(self, target) -> list:
        """A :class:`VariantMargin` per variant for a target [m] in the task's coordinates; raises
        TargetError when the model itself cannot hold the target within the limits."""
        x_d = np.asarray(target, dtype=float)
        q_model = self.nominal.precompute(x_d).q
        out = []
        for variant, path in zip(self.variants, self._paths):
            q = q_model
            for k, clik in enumerate(path):
                q, _ = clik.solve(x_d, q)
                if q is None:
                    out.append(VariantMargin(variant, None, None,
                                             f"no equilibrium at the target {k + 1}/{len(path)} of the "
                                             f"way to this arm (out of its reach)"))
                    break
            else:
                tensions = path[-1].reference(q).u_ff
                out.append(VariantMargin(variant, tensions, self.margin(tensions),
                                         self.stability(path[-1], q, tensions)))
        return out


def check_arm(arm: ArmConfig, control: ControlConfig, task: TaskConfig, targets) -> list:
    """Whether one given arm (e.g. a simulated plant, whose strain basis may differ from the
    model's) holds each target: a :class:`VariantMargin` per target (``variant`` None) from the
    precomputed CLIK solved on that arm itself (from its hanging pose, then its seed equilibria)."""
    checker = MarginChecker(arm, control, task, variants=[])
    out = []
    for target in targets:
        try:
            point = checker.nominal.precompute(np.asarray(target, dtype=float))
        except TargetError as exc:
            out.append(VariantMargin(None, None, None, None, str(exc)))
            continue
        out.append(VariantMargin(None, point.u_ff, checker.margin(point.u_ff),
                                 checker.stability(checker.nominal.clik, point.q, point.u_ff)))
    return out


def worst_margin(results) -> float | None:
    """The smallest margin over the variants (None when a variant has no equilibrium at the target)."""
    margins = [r.margin for r in results]
    return None if any(m is None for m in margins) else min(margins)


def is_robust(results, min_margin: float = MIN_MARGIN) -> bool:
    """The rule: every variant holds the target, stably, with at least ``min_margin`` [N]."""
    worst = worst_margin(results)
    return worst is not None and worst >= min_margin and all(r.stable for r in results)


def target_frequency(outer: OuterLoop, control: ControlConfig, task: TaskConfig, point: ClikPoint) -> float:
    """The lowest natural frequency [Hz] of the model's arm at the reference ``point`` held by the
    inner loop (:func:`~soft_arm_control.collocated.lowest_held_frequency`; negative: unstable)."""
    kp = [control.proportional[k] for k in task.tendons]
    return lowest_held_frequency(outer.clik.cm, point.q, point.u_ff, kp)


def fragility_error(outer: OuterLoop, control: ControlConfig, task: TaskConfig,
                    point: ClikPoint) -> str | None:
    """Why the reference ``point`` is too near a fold of the model's equilibria to be held (its
    lowest frequency under the inner loop below ``control.min_frequency``), or None."""
    if control.min_frequency <= 0:
        return None
    f = target_frequency(outer, control, task, point)
    if f >= control.min_frequency:
        return None
    return (f"its equilibrium on the model is {'unstable' if f < 0 else 'near a fold'} (lowest natural "
            f"frequency held by the inner loop {f:.2f} Hz, below control.clik.min_frequency "
            f"{control.min_frequency:g} Hz): the smallest model error moves the arm far from it")


def safe_point(outer: OuterLoop, control: ControlConfig, task: TaskConfig, point: ClikPoint,
               steps: int = 20, iterations: int = 8) -> ClikPoint | None:
    """The reference nearest to ``point`` on the straight path in the actuated tensions from the
    start-up pose's to ``point``'s (inside the limits all the way) that is not fragile
    (:func:`fragility_error`): the model's equilibria along the path, continued in ``steps`` steps
    from the start-up pose, their task points precomputed as targets are (so that the point offered
    passes :func:`target_point` itself), the last safe one refined by ``iterations`` bisections. What
    ``--accept-closest`` runs for a fragile target. None when the start-up pose itself is fragile."""
    clik = outer.clik
    cm = clik.cm
    u0, u1 = np.asarray(outer.start.u_ff, dtype=float), np.asarray(point.u_ff, dtype=float)

    def at(s, q_start):
        """The reference the run would use for the task point of the path's equilibrium at s
        (precomputed as a target is), or None when it is not safe."""
        try:
            eq = solve_equilibrium(cm.model, full_tensions(cm, u0 + s * (u1 - u0)), q_start=q_start,
                                   friction=cm.friction)
            ref = outer.precompute(clik.reference(eq.q).x)
        except (EquilibriumError, OutOfDomainError, TargetError):
            return None
        return None if fragility_error(outer, control, task, ref) else ref

    best = outer.start if fragility_error(outer, control, task, outer.start) is None else None
    if best is None:
        return None
    lo, hi = 0.0, None
    for s in np.linspace(0.0, 1.0, steps + 1)[1:]:
        ref = at(s, best.q)
        if ref is None:
            hi = s
            break
        lo, best = s, ref
    if hi is None:
        return best
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        ref = at(mid, best.q)
        if ref is None:
            hi = mid
        else:
            lo, best = mid, ref
    return best


def closest_safe_point(outer: OuterLoop, control: ControlConfig, task: TaskConfig, x_d,
                       start: ClikPoint, margin: float = SAFE_MARGIN) -> ClikPoint:
    """The safe reference nearest to x_d [m], searched from the safe reference ``start`` (e.g.
    :func:`safe_point`'s): ``min |x(u) - x_d|`` over the actuated tensions u within the limits,
    subject to the lowest held frequency being at least ``control.min_frequency + margin`` [Hz]
    (SLSQP; x(u) the task coordinates of the model's equilibrium under u, continued from the last
    one, with dx/du from the implicit function theorem; the frequency's gradient by central
    differences). The point found is precomputed as a target is and kept only when it is safe and
    nearer x_d than ``start``; otherwise ``start``."""
    clik = outer.clik
    cm, kp = clik.cm, [control.proportional[k] for k in task.tendons]
    x_d = np.asarray(x_d, dtype=float)
    h = 1e-3 * (control.tension_max - control.tension_min)
    lo, hi = control.tension_min + h, control.tension_max - h       # inside, as a precomputed point
    solve = clik.equilibrium_of_tensions(start.q)

    def equilibrium(u):
        """(q, x, dx/du) under u clipped to the limits (a difference step may leave them)."""
        return solve(np.clip(u, control.tension_min, control.tension_max))

    def frequency(u):
        return lowest_held_frequency(cm, equilibrium(u)[0], u, kp) - control.min_frequency - margin

    def frequency_gradient(u):
        return np.array([(frequency(u + h * e) - frequency(u - h * e)) / (2 * h)
                         for e in np.eye(len(u))])

    def distance(u):
        r = equilibrium(u)[1] - x_d
        return 0.5 * float(r @ r)

    def distance_gradient(u):
        _, x, dxdu = equilibrium(u)
        return dxdu.T @ (x - x_d)

    from scipy.optimize import minimize   # here: at import, 0.1-0.25 s of a CLIK node's start

    try:
        sol = minimize(distance, np.asarray(start.u_ff, dtype=float), jac=distance_gradient,
                       method="SLSQP", bounds=[(lo, hi)] * len(start.u_ff),
                       constraints=[{"type": "ineq", "fun": frequency, "jac": frequency_gradient}],
                       options={"maxiter": 50, "ftol": 1e-12})
        point = outer.precompute(equilibrium(sol.x)[1])
    except (EquilibriumError, OutOfDomainError, TargetError):
        return start
    nearer = np.linalg.norm(point.x - x_d) < np.linalg.norm(start.x - x_d)
    return point if nearer and fragility_error(outer, control, task, point) is None else start


def target_point(outer: OuterLoop, control: ControlConfig, task: TaskConfig, x_d) -> ClikPoint:
    """The precomputed reference of x_d [m] (:meth:`OuterLoop.precompute`), refused with TargetError
    when x_d is unreachable, infeasible, or fragile (too near a fold of the model's equilibria to
    be held: :func:`fragility_error`). The error's ``closest`` is the point to run instead: the
    closest feasible one, or when that is fragile the closest safe one (:func:`closest_safe_point`,
    searched from :func:`safe_point`'s)."""
    def safe_instead(point):
        start = safe_point(outer, control, task, point)
        return None if start is None else closest_safe_point(outer, control, task, x_d, start)

    try:
        point = outer.precompute(x_d)
    except TargetError as exc:
        closest = exc.closest
        if closest is not None and fragility_error(outer, control, task, closest):
            closest = safe_instead(closest)
        raise TargetError(str(exc), closest) from exc
    reason = fragility_error(outer, control, task, point)
    if reason is not None:
        raise TargetError(f"target {np.round(x_d, 4).tolist()} m is fragile: {reason}", safe_instead(point))
    return point
