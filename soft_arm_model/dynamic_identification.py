"""Dynamic identification (ROS-free): the viscosity of the body and the rotors' reflected mass,
from the recorded motion between plateaus (tension steps, chirps).

Each :class:`~soft_arm_model.recording.DynamicSegment` is simulated with the project's own
dynamics (:class:`~soft_arm_model.integrators.ImexStepper`, the static parameters already
identified) from the equilibrium under the tensions applied at its start, driven by the applied
tensions as recorded (the motor torque / pulley radius: it moves the rotor and pulls the tendon).
Residuals are *changes* from the segment's start, markers over ``marker_sigma`` and shortenings
over ``shortening_sigma``, so that a static error left by the static fit does not bias the
dynamic one. Parameters: log ratios of the viscosity and of the rotor mass to their starting
values; Levenberg-Marquardt (:func:`levenberg_marquardt`) on forward differences of a fixed step
in the log parameters, stopped when a next step would be below the estimates' resolution. The
segments of an evaluation, and the two perturbed evaluations of a Jacobian together, are simulated
in parallel, one thread per core: the compiled segment loop releases the GIL, so threads share
the compiled kernels that processes would each have to load.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from .config import ArmConfig
from .dynamics import OutOfDomainError
from .identification import Estimate, IdentificationError, Registration
from .integrators import ImexStepper, _imex_advance, _imex_prepare
from .model import build_model
from .recording import SETTLED_LEAD
from .statics import solve_equilibrium

SAMPLE_PERIOD = 0.02        # s between the compared samples of a segment
_LOG_STEP = 1e-3            # forward-difference step of the log parameters (absolute)


@dataclass(frozen=True)
class DynamicFit:
    """Identified viscosity [Pa s] and reflected rotor mass [kg] (one for all tendons), residual
    RMS per marker and per tendon shortening [m] of the changes, per segment its data and the
    changes simulated at the optimum (shortenings, markers), and the evaluations used."""
    viscosity: Estimate
    rotor_mass: Estimate
    marker_rms: np.ndarray
    shortening_rms: np.ndarray
    segments: tuple
    simulated: tuple
    evaluations: int


@dataclass(frozen=True)
class SegmentData:
    """What one simulation needs: input stamps and tensions, and the compared samples' stamps and
    measured changes (markers already in arm_base)."""
    t_input: np.ndarray
    tension: np.ndarray
    t_start: float
    u_start: np.ndarray
    t_s: np.ndarray
    ds: np.ndarray
    t_m: np.ndarray
    dp: np.ndarray


def segment_data(rec, seg, registration: Registration, lead: float) -> SegmentData:
    s, m = rec.window(seg.start, seg.end)
    s0, m0 = rec.window(seg.start, seg.start + lead)
    if s0.sum() < 2 or m0.sum() < 2 or m.sum() < 10:
        raise IdentificationError(f"the dynamic segment {seg.start:.2f}-{seg.end:.2f} s has too few "
                                  "tendon states or mocap frames")
    t0 = seg.start + lead
    u0 = rec.tension[s0].mean(axis=0)
    keep_s = s & (rec.t >= t0)
    t_s = rec.t[keep_s]
    every_s = max(1, int(round(SAMPLE_PERIOD / max(np.median(np.diff(t_s)), 1e-6))))
    markers = registration.to_arm(rec.markers)
    keep_m = m & (rec.t_markers >= t0)
    t_m = rec.t_markers[keep_m]
    every_m = max(1, int(round(SAMPLE_PERIOD / max(np.median(np.diff(t_m)), 1e-6))))
    inputs = np.flatnonzero(s & (rec.t >= t0))
    inputs = inputs[inputs + 1 < len(rec.t)]       # a state reports the tension of the period before it
    ds = rec.shortening[keep_s] - rec.shortening[s0].mean(axis=0)
    dp = markers[keep_m] - markers[m0].mean(axis=0)
    return SegmentData(rec.t[inputs], rec.tension[inputs + 1], t0, u0, t_s[::every_s], ds[::every_s],
                       t_m[::every_m], dp[::every_m])


@njit(cache=True, nogil=True)
def _simulate_segment(prepare_args, advance_args, Lc, marker_p, rest_lengths, q, qd, t_start, h,
                      t_input, tension, t_s, t_m, ds, dp, s_ref, p_ref, no_force):
    """The loop of :func:`simulate_changes`, compiled: from (q, qd) prepared at t_start, sample the
    shortening and marker changes at t_s and t_m into ds and dp, stepping under the tensions held
    from t_input. Returns 0, 1 if a state left the model's domain, 2 if the dynamics diverged (or a
    step's matrix was singular)."""
    model_args, data_args, rotor_mass, adot = prepare_args
    n = q.shape[0]
    q_next = np.empty(n)
    qd_next = np.empty(n)
    i_s = i_m = 0
    n_steps = int(np.ceil((max(t_s[-1], t_m[-1]) - t_start) / h)) + 1
    for k in range(n_steps):
        t = t_start + k * h
        want_m = i_m < t_m.shape[0] and t_m[i_m] <= t + 0.5 * h
        if not _imex_prepare(model_args, data_args, rotor_mass, q, qd, want_m, adot):
            return 1
        while i_s < t_s.shape[0] and t_s[i_s] <= t + 0.5 * h:
            ds[i_s] = (rest_lengths - Lc) - s_ref
            i_s += 1
        while want_m and i_m < t_m.shape[0] and t_m[i_m] <= t + 0.5 * h:
            dp[i_m] = marker_p - p_ref
            i_m += 1
        if i_s >= t_s.shape[0] and i_m >= t_m.shape[0]:
            break
        j = max(0, np.searchsorted(t_input, t, side="right") - 1)
        if not _imex_advance(*advance_args, q, qd, tension[j], no_force, h, q_next, qd_next):
            return 2
        q, q_next = q_next, q
        qd, qd_next = qd_next, qd
        if not np.all(np.isfinite(q)):
            return 2
    return 0


def simulate_changes(arm: ArmConfig, rotor_mass: float, data: SegmentData, timestep: float,
                     q_start: np.ndarray | None = None):
    """The model's changes of shortenings (len(t_s), n_t) and markers (len(t_m), n_m, 3) [m] from
    the equilibrium under ``u_start`` (``q_start`` if given: it depends on neither the viscosity
    nor the rotor mass), driven by the recorded tensions (held between stamps)."""
    model = build_model(arm)
    stepper = ImexStepper(model, timestep, rotor_mass=np.full(model.n_tendons, rotor_mass))
    q = solve_equilibrium(model, data.u_start).q if q_start is None else np.array(q_start, dtype=float)
    qd = np.zeros(model.n)
    stepper.prepare(q, qd, True)
    d = stepper.data
    s_ref, p_ref = (model.rest_tendon_lengths - d.Lc).copy(), d.marker_p.copy()
    ds, dp = np.zeros_like(data.ds), np.zeros_like(data.dp)
    # contiguous, as the compiled loop's one specialisation takes them (a recording's samples are
    # often every k-th one, strided views)
    tension, t_s, t_m = (np.ascontiguousarray(a, dtype=float) for a in (data.tension, data.t_s, data.t_m))
    status = _simulate_segment(*stepper.compiled_args, d.Lc, d.marker_p, model.rest_tendon_lengths,
                               q.copy(), qd, data.t_start, timestep, data.t_input, tension, t_s, t_m, ds,
                               dp, s_ref, p_ref, np.zeros(model.n))
    if status == 1:
        raise OutOfDomainError("the state left the model's domain")
    if status == 2:
        raise IdentificationError("the dynamics diverged in a segment (step too long, or a "
                                  "parameter far off)")
    return ds, dp


class DynamicProblem:
    """The weighted least-squares problem of :func:`identify_dynamics` over p = (log viscosity
    ratio, log rotor-mass ratio): the segments ``data`` (:class:`SegmentData`) simulated on
    ``arm`` with ``rotor_mass`` [kg] scaled, ``timestep`` [s]; ``pool``: where the simulations run
    (None: in the caller's thread)."""

    def __init__(self, arm: ArmConfig, rotor_mass: float, data, marker_sigma: float, shortening_sigma: float,
                 timestep: float, pool: ThreadPoolExecutor | None = None):
        self.arm0, self.m0 = arm, float(rotor_mass)
        self.data = list(data)
        self.marker_sigma, self.shortening_sigma = marker_sigma, shortening_sigma
        self.timestep, self.pool = timestep, pool
        model = build_model(arm)
        self.q_start = [solve_equilibrium(model, d.u_start).q for d in self.data]
        self.evaluations = 0
        self._last = None           # (p, changes, residual) of the last residual: the Jacobian's base

    def arm(self, p) -> ArmConfig:
        return replace(self.arm0, material=replace(self.arm0.material,
                                                   viscosity=self.arm0.material.viscosity * np.exp(p[0])))

    def changes(self, p) -> list:
        """Per segment, the simulated (shortening changes, marker changes) at p."""
        if self._last is not None and np.array_equal(self._last[0], p):
            return self._last[1]
        return self._changes([p])[0]

    def _changes(self, points) -> list:
        """:meth:`changes` at each of ``points``, every segment of every point in one batch."""
        self.evaluations += len(points)
        jobs = [(self.arm(p), self.m0 * np.exp(p[1]), d, self.timestep, q0)
                for p in points for d, q0 in zip(self.data, self.q_start)]
        run = self.pool.map if self.pool is not None else map
        done = list(run(lambda job: simulate_changes(*job), jobs))
        k = len(self.data)
        return [done[i * k:(i + 1) * k] for i in range(len(points))]

    def _weighted(self, changes) -> np.ndarray:
        out = []
        for (ds, dp), d in zip(changes, self.data):
            out += [((dp - d.dp) / self.marker_sigma).ravel(), ((ds - d.ds) / self.shortening_sigma).ravel()]
        return np.concatenate(out)

    def residual(self, p) -> np.ndarray:
        """The weighted residual at p (markers over ``marker_sigma``, shortenings over
        ``shortening_sigma``)."""
        changes = self.changes(p)
        r = self._weighted(changes)
        self._last = (np.array(p, dtype=float), changes, r)
        return r

    def jacobian(self, p) -> np.ndarray:
        """Forward differences of :meth:`residual` with the step ``_LOG_STEP`` in each log
        parameter, both perturbed points simulated in one batch."""
        p = np.array(p, dtype=float)
        r0 = self.residual(p)
        points = [p + _LOG_STEP * e for e in np.eye(p.size)]
        return np.column_stack([(self._weighted(c) - r0) / _LOG_STEP for c in self._changes(points)])


def standard_errors(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Each parameter's standard error at a least-squares solution with Jacobian ``J`` and
    residual ``r`` (weighted), the residuals' variance estimated from ``r`` itself."""
    scale = float(r @ r) / max(1, r.size - J.shape[1])
    return np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)) * scale, 0.0, None))


def levenberg_marquardt(residual, jacobian, x0, max_evaluations: int, resolution: float = 0.05):
    """Minimise the squared norm of ``residual(x)`` from ``x0``: Gauss-Newton steps, damped
    (Levenberg-Marquardt) only after a step that did not lower the cost. Stops before simulating
    a step that would move every parameter by less than ``resolution`` of its standard error
    (:func:`standard_errors` at the current point): the data cannot tell such a step from none,
    and a simulated residual costs seconds. Returns (x, residual, Jacobian at x, converged);
    ``max_evaluations`` bounds the residuals evaluated outside the Jacobians."""
    x = np.array(x0, dtype=float)
    r = residual(x)
    J = jacobian(x)
    cost, damping, evaluations = float(r @ r), 0.0, 1
    while evaluations < max_evaluations:
        A, g = J.T @ J, J.T @ r
        step = np.linalg.solve(A + damping * np.diag(np.diag(A)), -g)
        if np.all(np.abs(step) < resolution * standard_errors(J, r)):
            return x, r, J, True
        r_new = residual(x + step)
        evaluations += 1
        cost_new = float(r_new @ r_new)
        if np.isfinite(cost_new) and cost_new < cost:
            x, r, cost, damping = x + step, r_new, cost_new, damping / 10.0
            J = jacobian(x)
        else:
            damping = max(10.0 * damping, 1e-3)
    return x, r, J, False


def identify_dynamics(arm: ArmConfig, rotor_mass: float, rec, segments, registration: Registration,
                      marker_sigma: float = 2e-4, shortening_sigma: float = 2e-5,
                      timestep: float = 0.002, lead: float = SETTLED_LEAD, workers: int | None = None,
                      max_evaluations: int = 30) -> DynamicFit:
    """Fit the viscosity of ``arm`` (its static parameters identified) and the rotors' reflected
    mass [kg] (``rotor_mass``: the starting guess, e.g. a datasheet's J / r^2) to the ``segments``
    of the recording ``rec`` (markers mapped to arm_base by ``registration``); ``marker_sigma`` and
    ``shortening_sigma`` [m]: the noise of one marker coordinate and one shortening reading;
    ``timestep`` [s]: the simulation's; ``lead`` [s]: the settled start of each segment averaged as
    its reference; ``workers``: threads (default: the cores)."""
    if not segments:
        raise IdentificationError("no dynamic segment (a step or a chirp between two plateaus): "
                                  "the viscosity and the rotor mass cannot be identified")
    data = [segment_data(rec, seg, registration, lead) for seg in segments]
    workers = workers or os.cpu_count() or 1
    pool = ThreadPoolExecutor(workers, thread_name_prefix="dynamic_fit") if workers > 1 else None
    try:
        pb = DynamicProblem(arm, rotor_mass, data, marker_sigma, shortening_sigma, timestep, pool)
        x, r, J, converged = levenberg_marquardt(pb.residual, pb.jacobian, np.zeros(2), max_evaluations)
        if not converged:
            raise IdentificationError(f"the dynamic fit did not converge in {max_evaluations} "
                                      "evaluations (a segment the model cannot follow?)")
        changes = pb.changes(x)
    finally:
        if pool is not None:
            pool.shutdown()
    se = standard_errors(J, r)
    eta = arm.material.viscosity * np.exp(x[0])
    m_r = rotor_mass * np.exp(x[1])
    err_p = np.concatenate([(dp - d.dp) for (_, dp), d in zip(changes, pb.data)])
    err_s = np.concatenate([(ds - d.ds) for (ds, _), d in zip(changes, pb.data)])
    return DynamicFit(Estimate(float(eta), float(eta * se[0]), "Pa s"),
                      Estimate(float(m_r), float(m_r * se[1]), "kg"),
                      np.sqrt(np.mean(np.sum(err_p ** 2, axis=2), axis=0)),
                      np.sqrt(np.mean(err_s ** 2, axis=0)),
                      tuple(pb.data), tuple(changes), pb.evaluations)
