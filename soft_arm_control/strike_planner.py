"""The strike planned on the model: a tension profile that brings the task point to the strike
target at a chosen time, as fast as the tendons allow, ROS-free.

The paper sends the precomputed reference as one step and lets the inner loop carry the arm there;
the arm arrives when its dynamics let it. The planner shapes the tensions in time instead: ``pieces``
constant levels per tendon over equal parts of the move's duration T [s], each change passed
through the inner loop's tension rate limit (``control.inner_loop.tension_rate_limit``, when on),
then the target's equilibrium tensions from T on (the inner loop holds the precomputed reference
after the strike). It is found by single shooting: the controller's model (its arm, its rotors'
``control.rotor_mass`` on every tendon, the IMEX integrator) is simulated from the hanging arm under
the profile, and ``scipy.optimize.least_squares`` fits the levels, bounded by the tension limits,
so that the task coordinates are at the target at T. The arm passes through the target moving (the
strike): an underactuated arm cannot also be brought to rest there by a few levels.

:func:`plan_strike_move` searches the shortest T: bisection between ``min_duration`` and
``max_duration`` for the shortest T whose fitted miss is within ``tolerance`` [m]. The result,
:class:`StrikeProfile`, carries the planned tendon shortenings and rates beside the tensions, so
that the inner loop follows the planned motion with the planned tensions as its feedforward
(:meth:`StrikeProfile.reference`).

Frames and units: task coordinates in ``arm_base`` [m]; tensions of all tendons [N]; times from the
start of the move [s].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_arm_model import ImexStepper, OutOfDomainError, solve_equilibrium

FIT_STEP = 2e-3           # s, the fit's time step
PLAN_STEP = 1e-3          # s, the recorded plan's (the strike rehearsal's step)
# a fit stops within this fraction of the plan's tolerance (the margin for the recorded plan, at
# its finer step)
ENOUGH = 0.25


@dataclass(frozen=True)
class StrikeProfile:
    """A planned move of ``duration`` [s]: the tensions [N] of every tendon at ``sample_times``
    [s] (the planning simulation's steps, from 0 to the duration), with the planned ``shortening``
    [m] and ``shortening_rate`` [m/s] of every tendon at each; ``levels`` [N] (pieces, the task's
    tendons): the fitted levels before the rate limit; ``hold`` [N] (the task's tendons): the
    tensions from the duration on;
    ``miss`` [m]: the task error norm of the plan at the duration; ``arrival_speed`` [m/s]: the
    planned tip speed there."""
    duration: float
    sample_times: np.ndarray
    tensions: np.ndarray
    shortening: np.ndarray
    shortening_rate: np.ndarray
    levels: np.ndarray
    hold: np.ndarray
    miss: float
    arrival_speed: float

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the inner loop follows t [s] after the start: the planned shortenings [m], their
        rates [m/s] and the tensions [N] of all tendons, at the last sample at or before t (the
        first before 0; the last after the duration)."""
        k = int(np.clip(np.searchsorted(self.sample_times, t, side="right") - 1, 0,
                        self.sample_times.size - 1))
        return self.shortening[k].copy(), self.shortening_rate[k].copy(), self.tensions[k].copy()

    def as_dict(self) -> dict:
        """The plan's duration, levels, miss and arrival speed (JSON-ready)."""
        return {"duration": self.duration, "levels": self.levels.tolist(), "hold": self.hold.tolist(),
                "miss": self.miss, "arrival_speed": self.arrival_speed,
                "tension_range": [float(self.tensions.min()), float(self.tensions.max())]}


class StrikeShooter:
    """Simulates ``model`` (ArmModel) from the hanging arm (every tendon at ``pretension`` [N])
    under a profile of levels on the task's ``tendons`` (indices; the others stay at the
    pretension), ``rotor_mass`` [kg] on every tendon, steps of ``timestep`` [s], the tension
    changes limited to ``rate_limit`` [N/s] (0: none); ``space``: the TaskSpace of the target."""

    def __init__(self, model, space, tendons, pretension: float, rotor_mass: float, timestep: float,
                 rate_limit: float = 0.0):
        self.model, self.space = model, space
        self.tendons = list(tendons)
        self.pretension, self.rate_limit = float(pretension), float(rate_limit)
        self.stepper = ImexStepper(model, timestep, rotor_mass=np.full(model.n_tendons, rotor_mass))
        self.timestep = float(timestep)
        self.q0 = solve_equilibrium(model, np.full(model.n_tendons, pretension)).q

    def commands(self, levels: np.ndarray, hold: np.ndarray, duration: float) -> np.ndarray:
        """The tensions [N] of all tendons at each step to the duration (steps + 1, n_tendons):
        ``levels`` (pieces, len(tendons)) over equal parts, ``hold`` (len(tendons)) at the end, every
        change rate-limited from the pretension on."""
        steps = int(round(duration / self.timestep))
        piece = np.minimum((np.arange(steps + 1) * len(levels)) // max(steps, 1), len(levels))
        wanted = np.vstack([levels, hold])[piece]
        out = np.full((steps + 1, self.model.n_tendons), self.pretension)
        active = np.full(len(self.tendons), self.pretension)
        limit = self.rate_limit * self.timestep
        for k in range(steps + 1):
            active = wanted[k] if limit <= 0 else np.clip(wanted[k], active - limit, active + limit)
            out[k, self.tendons] = active
        return out

    def run(self, levels: np.ndarray, hold: np.ndarray, duration: float, record: bool = False):
        """Simulate to the duration: (task coordinates there [m] (nan if the state left the model's
        domain), the tip speed there [m/s], and with ``record`` (times, tensions, shortenings,
        rates) at every step, else None). Without ``record`` (the fit's runs) the steps go in one
        compiled loop and only the end state is read."""
        u = self.commands(levels, hold, duration)
        last = u.shape[0] - 1
        q, qd = np.empty((last + 1, self.model.n)), np.empty((last + 1, self.model.n))
        q[0], qd[0] = self.q0, 0.0
        d = self.stepper.data
        s, sd = [], []
        try:
            if record:
                for k in range(last):
                    self.stepper.prepare(q[k], qd[k])
                    s.append(self.model.rest_tendon_lengths - d.Lc)
                    sd.append(-(d.A0.T @ qd[k]))
                    q[k + 1], qd[k + 1] = self.stepper.advance(u[k])
            elif self.stepper.run(q, qd, u) < last:
                raise OutOfDomainError("the strike's run left the model's domain")
            self.stepper.prepare(q[last], qd[last], markers=True)
        except OutOfDomainError:
            return np.full(self.space.m, np.nan), np.nan, None
        x = self.space.from_markers(d.marker_p)
        speed = float(np.linalg.norm(d.marker_R[-1] @ (d.marker_J[-1][3:] @ qd[last])))
        if not record:
            return x, speed, None
        s.append(self.model.rest_tendon_lengths - d.Lc)
        sd.append(-(d.A0.T @ qd[last]))
        return x, speed, (np.arange(last + 1) * self.timestep, u, np.array(s), np.array(sd))


class _Reached(Exception):
    """Raised out of the fit by the first levels whose miss is small enough."""

    def __init__(self, levels: np.ndarray, miss: float):
        super().__init__()
        self.levels, self.miss = levels, miss


def fit_levels(shooter: StrikeShooter, target, hold, duration: float, guess, bounds,
               max_evaluations: int = 40, enough: float = 0.0) -> tuple[np.ndarray, float]:
    """The levels (pieces, len(tendons)) [N] within ``bounds`` (lower, upper) [N] that bring the
    task coordinates to ``target`` [m] at ``duration`` [s], from ``guess``; (levels, miss [m]).
    The fit ends at the first levels it tries that miss by at most ``enough`` [m] (0: when it
    converges): a plan needs to be within its tolerance, not exact, and each of the fit's
    iterations costs a simulation per level."""
    shape = np.shape(guess)

    def residual(z):
        x, _, _ = shooter.run(z.reshape(shape), hold, duration)
        if not np.all(np.isfinite(x)):
            return np.ones(target.size)
        miss = float(np.linalg.norm(x - target))
        if miss <= enough:
            raise _Reached(z.reshape(shape).copy(), miss)
        return x - target

    import scipy.optimize   # here: at import, 0.1-0.25 s of a CLIK node's start

    try:
        sol = scipy.optimize.least_squares(residual, np.ravel(guess), bounds=bounds, diff_step=1e-3,
                                           max_nfev=max_evaluations)
        return sol.x.reshape(shape), float(np.linalg.norm(residual(sol.x)))
    except _Reached as reached:
        return reached.levels, reached.miss


def plan_strike_move(model, control, space, tendons, goal, target, pieces: int = 3,
                     min_duration: float = 0.1, max_duration: float = 0.5, tolerance: float = 1e-3,
                     timestep: float = PLAN_STEP, bisections: int = 4) -> StrikeProfile:
    """The fastest planned move of ``model`` (the controller's) from the hanging arm to ``target``
    [m] (task coordinates of ``space``) on the task's ``tendons``, with ``control``'s tension
    limits, tension rate limit and rotor mass. ``goal``: the target's precomputed reference (a
    ClikPoint), whose equilibrium tensions start the fit and hold the arm after the move. The
    duration (a whole number of the fit's steps) is bisected ``bisections`` times between
    ``min_duration`` and ``max_duration`` [s]; the fit runs at :data:`FIT_STEP`, then the levels
    of the shortest duration are refined at ``timestep`` [s], at which the plan is recorded. A
    recorded plan that misses by more than ``tolerance`` [m] (the finer step moves the arm's end
    point, and a refinement near the tension limits cannot always bring it back) gives way to the
    next longer duration the bisection found within it. Raises ValueError when even
    ``max_duration`` misses, or when no recorded plan is within ``tolerance``."""
    target = np.asarray(target, dtype=float)
    hold = np.clip(np.asarray(goal.u_ff, dtype=float), control.tension_min, control.tension_max)
    step = max(timestep, FIT_STEP)
    fit = StrikeShooter(model, space, tendons, control.tension_min, control.rotor_mass, step,
                        control.tension_rate_limit)
    bounds = (control.tension_min, control.tension_max)

    def whole(T):                   # a duration both the fit and the record take exactly
        return max(1, round(T / step)) * step
    lo, hi = whole(min_duration), whole(max_duration)
    enough = ENOUGH * tolerance
    best, miss = fit_levels(fit, target, hold, hi, np.tile(hold, (pieces, 1)), bounds, enough=enough)
    if miss > tolerance:
        raise ValueError(f"no tension profile within [{control.tension_min}, {control.tension_max}] N "
                         f"brings the task point to the target in {max_duration} s: the closest "
                         f"misses it by {miss * 1e3:.1f} mm")
    feasible = [(hi, best)]                   # durations within the tolerance, longest first
    for _ in range(bisections):
        T = whole(0.5 * (lo + hi))
        if not lo < T < hi:
            break
        levels, miss_T = fit_levels(fit, target, hold, T, best, bounds, enough=enough)
        if miss_T <= tolerance:
            best, hi = levels, T
            feasible.append((T, levels))
        else:
            lo = T
    record = StrikeShooter(model, space, tendons, control.tension_min, control.rotor_mass, timestep,
                           control.tension_rate_limit)
    misses = []
    for duration, levels in reversed(feasible):
        if timestep != step:
            levels, _ = fit_levels(record, target, hold, duration, levels, bounds, max_evaluations=10,
                                   enough=enough)
        x, speed, samples = record.run(levels, hold, duration, record=True)
        if samples is None:                   # the state left the model's domain
            misses.append(f"out of the model's domain in {duration:.3f} s")
            continue
        miss = float(np.linalg.norm(x - target))
        if miss <= tolerance:
            return StrikeProfile(duration, *samples, levels, hold, miss, speed)
        misses.append(f"{miss * 1e3:.1f} mm in {duration:.3f} s")
    raise ValueError(f"the planned move, recorded at {timestep} s steps, misses the target by more than "
                     f"{tolerance * 1e3:.1f} mm at every duration the fit found: {', '.join(misses)}")


def strike_move_for(model, control, task, goal) -> StrikeProfile | None:
    """The planned move of ``task``'s strike (a TaskConfig with a pendulum) to its precomputed
    ``goal`` (a ClikPoint) on the controller's ``model``, recorded at :data:`PLAN_STEP`; None
    unless the task's strike timing is ``planned`` (soft-arm-harness only: the graph refuses it)."""
    if task.pendulum is None or task.strike_timing != "planned":
        return None
    return plan_strike_move(model, control, task.space, task.tendons, goal, goal.x)
