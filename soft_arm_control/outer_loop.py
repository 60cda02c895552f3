"""The CLIK layer as the paper runs it, ROS-free: goals in, configuration references out.

A goal is a target in task coordinates with a mode:

- ``clik``: the precomputed reference at once (the paper's fast step), then online refinement from
  the mocap ``switch_delay`` seconds later; the reached reference is stored for the target when the
  next goal arrives;
- ``replay``: the reference stored for this target, straight to the inner loop (no CLIK);
- ``precomputed``: the precomputed reference only (the pendulum strike); with a planned move
  (:class:`~soft_arm_control.strike_planner.StrikeProfile`) the inner loop follows the plan's
  shortenings, their rates and its tensions as feedforward, sampled at the mocap frames, until the
  move's duration has passed, then holds the precomputed reference;
- ``online``: online refinement from the current reference, no precomputed step (sugar task);
- ``track``: online CLIK along a trajectory (:class:`~soft_arm_control.trajectories.Trajectory`)
  from the target, x_d(t) with its velocity as feedforward, from the goal's time on; with
  ``track_dynamics`` the inner loop gets the dynamic reference of the CLIK's
  (:meth:`~soft_arm_control.clik.Clik.dynamic_reference`: the path's inertial and damping forces
  balanced), while the CLIK integrates the quasi-static one. With a ``track_learning`` gain the
  path itself is corrected period by period from the measured error
  (:class:`~soft_arm_control.track_learning.HarmonicLearner`): the CLIK tracks x_d + c(t).

The reference step of a goal whose mode is among ``shaped_modes`` is given in fractions by a
:class:`~soft_arm_control.input_shaping.StepShaper` (zero-vibration input shaping for the arm's
slowest-decaying mode), the later fractions at the mocap frames after their delays; online
refinement starts when the last fraction is given, at the earliest.

``command`` is the reference last handed to the inner loop (``reference`` is the CLIK's own, which
differs in a track goal with ``track_dynamics`` and during a planned move). ``reference_rate`` is
the command's rate of shortening [m/s] (all tendons): an online step's change over the CLIK period
in a goal whose mode is among ``rate_modes``, the plan's during a planned move, zero otherwise (and
for a precomputed, replayed or shaped reference); the inner loop damps the arm's motion about it
(:class:`~soft_arm_control.inner_loop.TendonController`).

Times are the caller's [s] (simulated or wall). An unreachable or infeasible goal raises
:class:`~soft_arm_control.clik.TargetError` and leaves the current reference untouched.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from soft_arm_model import solve_equilibrium

from .clik import Clik, ClikGains, ClikPoint, ClikStep, TargetError, equilibrium_seeds
from .collocated import build_collocated
from .input_shaping import ShapedStep, StepShaper
from .strike_planner import StrikeProfile
from .track_learning import HarmonicLearner
from .trajectories import Trajectory
from .trust_region import TrustRegion

MODES = ("clik", "replay", "precomputed", "online", "track")
STATUSES = ("ok", "constrained", "saturated", "stalled", "unreached", "unseen", "held",   # GoalReport.status
            "untrusted", "uncertain")


@dataclass
class GoalReport:
    """What the online CLIK did for one goal: ``target`` [m], ``mode``, its online steps, those that
    had to be projected onto the tension limits (``infeasible_steps``: the target is infeasible for
    the model from there), those with no feasible step at all (``held_steps``: the reference
    stayed), the smallest and the last measured task error norms [m] (None before the first
    online step), ``stalled_steps``: online steps since the error last fell by a tenth while it
    is above ``reach_tolerance`` [m], and ``shaped_mode``: the frequency [Hz] and damping ratio of
    the mode its reference step was shaped for (None: an unshaped step, or none). A goal whose
    error stays above the tolerance without falling for ``stall_steps`` steps is *stalled*: the
    arm does not go where the model says it should (a target out of the arm's reach, an
    unmodelled load) although every step was feasible. A goal ``closed`` (the next one arrived, or
    the experiment ended) with its last error above the tolerance and nothing else to report is
    *unreached*. ``saturated_steps``: steps of a track goal whose dynamic reference needed
    feedforward tensions outside the limits (the path asks more force than the tendons give: the
    inner loop clips it, and the arm falls behind). ``learner``: a track goal's
    :class:`~soft_arm_control.track_learning.HarmonicLearner` (None: not learned), whose counts the
    report gives: ``learned_periods``, ``backed_off_periods`` (the CLIK could not follow, or the
    error grew) and ``frozen_periods`` (the dynamic reference was clipped). ``unseen_frames``: frames
    on which an online step was due but the task's markers were not all seen (no step: the reference
    holds; a track goal's goes on along its path on the feedforward); ``unseen_time`` [s]: how
    long the current such stretch has lasted (0 once a step is taken). A goal is *unseen* while
    that stretch is longer than one online period. On an estimated feedback
    (:class:`~soft_arm_control.trust_region.TrustRegion`): ``distrusts``, the times the
    trust region refused the estimate and the reference returned to the goal's precomputed one (its
    reason in ``distrust``, the frame time [s] of the last in ``distrust_time``), and
    ``untrusted_frames``, the frames on which an online step was due but not taken for it, and
    ``judged_frames``, those whose drift it judged (the others came too soon after the goal's
    start, a refusal or a jump of the reference); a goal is *untrusted* while it holds the
    precomputed reference so (a track goal's: follows its path's precomputed reference, the model
    closing the CLIK). ``fraction``: the part of the
    estimated error the last online step took (1 on a measurement; less on an estimate whose
    uncertainty explains some of it, :meth:`~soft_arm_control.trust_region.TrustRegion.fraction`),
    ``uncertain_frames``: the frames whose step took less than all of it, or none (no correcting
    step is taken then, and ``error`` is the estimated error); a goal is *uncertain* while its last
    frame took none (the estimate cannot tell the remaining error from its own: the reference holds,
    a track goal's goes on along its path)."""
    target: list
    mode: str
    reach_tolerance: float = 1e-3
    stall_steps: int = 480
    online_steps: int = 0
    infeasible_steps: int = 0
    held_steps: int = 0
    closest_error: float | None = None
    error: float | None = None
    stalled_steps: int = 0
    saturated_steps: int = 0
    closed: bool = False
    shaped_mode: tuple | None = None
    unseen_frames: int = 0
    unseen_time: float = 0.0
    unseen_after: float = 0.0
    untrusted_frames: int = 0
    judged_frames: int = 0
    distrusts: int = 0
    distrust: str | None = None
    distrust_time: float | None = None
    holding: bool = False
    fraction: float = 1.0
    uncertain_frames: int = 0
    learner: HarmonicLearner | None = field(default=None, repr=False, compare=False)
    _progress_level: float = np.inf

    def add(self, step: ClikStep, error=None):
        """Count an online ``step``; ``error`` [m]: the measured task error it was taken on (None:
        the step's own, all of which it took)."""
        self.online_steps += 1
        self.infeasible_steps += step.constrained
        self.held_steps += step.held
        self.error = float(np.linalg.norm(step.error if error is None else error))
        self.closest_error = self.error if self.closest_error is None else min(self.closest_error,
                                                                               self.error)
        if self.error <= self.reach_tolerance or self.error < 0.9 * self._progress_level:
            self._progress_level = self.error
            self.stalled_steps = 0
        else:
            self.stalled_steps += 1

    @property
    def learned_periods(self) -> int:
        return 0 if self.learner is None else self.learner.updates

    @property
    def backed_off_periods(self) -> int:
        return 0 if self.learner is None else self.learner.backed_off

    @property
    def frozen_periods(self) -> int:
        return 0 if self.learner is None else self.learner.frozen

    @property
    def reached(self) -> bool | None:
        """The last measured error is within ``reach_tolerance`` (None without online steps)."""
        return None if self.error is None else self.error <= self.reach_tolerance

    @property
    def status(self) -> str:
        """held (no feasible step: the reference stayed), untrusted (the trust region refused the
        estimate the online steps were taken on: the precomputed reference holds, a track goal's
        follows its path's), uncertain (the estimate's uncertainty explains the error it shows: no
        correcting step), unseen (no frame showed the task's markers for longer than
        ``unseen_after``: no correcting step; the reference holds, a track goal's goes on along its
        path), constrained (the reference keeps moving towards the closest feasible point),
        saturated (a track goal whose path needed tensions outside the limits), stalled (feasible
        steps, but the error stays above the tolerance), unreached (closed away from the target) or
        ok (a track goal, whose error is a tracking error, is never stalled or unreached)."""
        if self.held_steps:
            return "held"
        if self.holding:
            return "untrusted"
        if self.fraction == 0.0:
            return "uncertain"
        if self.unseen_time > self.unseen_after:
            return "unseen"
        if self.infeasible_steps:
            return "constrained"
        if self.saturated_steps:
            return "saturated"
        if self.mode == "track":          # a moving target: its error is the tracking error
            return "ok"
        if self.stalled_steps >= self.stall_steps:
            return "stalled"
        return "unreached" if self.closed and self.reached is False else "ok"

    def as_dict(self) -> dict:
        keys = ("target", "mode", "online_steps", "infeasible_steps", "held_steps", "closest_error",
                "error", "stalled_steps", "saturated_steps", "closed", "shaped_mode", "learned_periods",
                "backed_off_periods", "frozen_periods", "unseen_frames", "unseen_time", "untrusted_frames",
                "judged_frames", "distrusts", "distrust", "distrust_time", "fraction", "uncertain_frames")
        return {**{k: getattr(self, k) for k in keys}, "reached": self.reached, "status": self.status}


class OuterLoop:
    """Reference generator around a :class:`~soft_arm_control.clik.Clik`.

    ``start``: the reference at start-up (the hanging arm); ``switch_delay`` [s]; ``rate`` [Hz] of
    the online steps; ``jacobian_every``: online steps per recomputation of Z (a track goal's path
    turns it at every step: recomputed at every one); ``seed_levels``
    [N]: tensions of the seed equilibria tried when a precomputation from ``start`` fails;
    ``tolerance`` [m]: precomputation tolerance; ``reach_tolerance`` [m] and ``stall_time`` [s]: when
    a goal counts as reached, and as stalled (:class:`GoalReport`); ``shaper`` and ``shaped_modes``:
    the reference steps of goals in those modes are shaped (None: every step is a step);
    ``track_feedforward``: a track goal's trajectory velocity is the CLIK's feedforward;
    ``rate_modes``: the goal modes whose online steps set ``reference_rate``; ``track_dynamics``:
    a track goal's references balance the path's inertial and damping forces, with the rotors'
    reflected mass ``rotor_mass`` [kg] on every tendon; ``trust``: the trust region of an estimated
    feedback (None: the feedback is measured, every frame seen is stepped on). A frame it refuses
    returns the reference to the goal's precomputed one (an online goal's: the reference it started
    from; a track goal's: the model's equilibrium at the path's point, after which the model closes
    the CLIK along the path, without the learned correction), and the online steps resume after
    ``trust.config.recover`` seconds of frames it accepts.
    """

    def __init__(self, clik, start: ClikPoint, switch_delay: float, rate: float,
                 jacobian_every: int = 1, seed_levels=(), tolerance: float = 1e-6,
                 reach_tolerance: float = 1e-3, stall_time: float = 2.0,
                 shaper: StepShaper | None = None, shaped_modes=(), track_feedforward: bool = True,
                 rate_modes=("track",), track_dynamics: bool = False, rotor_mass: float = 0.0,
                 track_learning: float = 0.0, track_harmonics: int = 3, track_settle_time: float = 0.0,
                 trust: TrustRegion | None = None):
        self.clik = clik
        self.start = start
        self.reference = start
        self._hand(start)
        self.switch_delay, self.period = float(switch_delay), 1.0 / float(rate)
        self.jacobian_every = max(1, int(jacobian_every))
        self.seed_levels, self.tolerance = tuple(seed_levels), float(tolerance)
        self.reach_tolerance = float(reach_tolerance)
        self.stall_steps = max(1, int(round(stall_time * float(rate))))
        self.stored: dict = {}
        self.reports: list = []             # a GoalReport per goal, in order
        self.last_step: ClikStep | None = None
        self.shaper, self.shaped_modes = shaper, tuple(shaped_modes)
        self.track_feedforward = bool(track_feedforward)
        self.rate_modes = tuple(rate_modes)
        self.track_dynamics, self.rotor_mass = bool(track_dynamics), float(rotor_mass)
        self.track_learning, self.track_harmonics = float(track_learning), int(track_harmonics)
        self.track_settle_time = float(track_settle_time)
        self.learner: HarmonicLearner | None = None
        self._move: ShapedStep | None = None
        self._fraction = 1.0
        self._planned: StrikeProfile | None = None
        self._planned_from = 0.0
        self._seeds = None
        self._x_d = None
        self._mode = None
        self._trajectory, self._t0 = None, 0.0
        self._online_from = np.inf
        self._next_step = np.inf
        self._unseen_since = None       # frame time [s] since which the task's markers went unseen
        self._steps = 0
        self.trust = trust
        # what a refused estimate returns the reference to (a track goal's: where its path's
        # precomputed reference is solved from)
        self._fallback = start
        self._trusted_since = None       # frame time [s] since which the trust region accepts, holding

    @staticmethod
    def key(x_d) -> tuple:
        """The key a target is stored under (its coordinates rounded to 0.1 mm)."""
        return tuple(np.round(np.asarray(x_d, dtype=float), 4))

    def precompute(self, x_d) -> ClikPoint:
        """The precomputed reference of x_d from the start-up pose, or from the nearest seed
        equilibrium when that fails, or last by the search on the tensions (raises TargetError,
        with the closest point the search found)."""
        try:
            return self.clik.precompute(x_d, self.start.q, tol=self.tolerance, search=not self.seed_levels)
        except TargetError:
            if not self.seed_levels:
                raise
            return self.clik.precompute(x_d, self.start.q, self.seeds(), tol=self.tolerance)

    def seeds(self) -> list:
        """The seed equilibria at ``seed_levels`` (:func:`~soft_arm_control.clik.equilibrium_seeds`),
        solved at the first call and kept: ``levels ** actuated tendons`` equilibria (the triangle's
        81 take 0.7 s; none without levels), so a node that answers goals calls it before the first
        comes."""
        if self._seeds is None:
            self._seeds = equilibrium_seeds(self.clik, self.seed_levels)
        return self._seeds

    def goal(self, t: float, x_d, mode: str, point: ClikPoint | None = None,
             trajectory: Trajectory | None = None, move: StrikeProfile | None = None) -> ClikPoint:
        """Take a new goal at time t [s]; returns the reference to hand the inner loop from now on.

        ``point`` is a reference precomputed beforehand for a clik or precomputed goal (the
        harness solves every target before anything moves); ``trajectory``: a track goal's, from
        x_d at t; ``move``: a precomputed goal's planned move from the hanging arm, started at t.
        """
        if mode not in MODES:
            raise ValueError(f"goal mode {mode!r} is not one of {list(MODES)}")
        if (mode == "track") != (trajectory is not None):
            raise ValueError("a track goal needs a trajectory, and only a track goal takes one")
        if move is not None and mode != "precomputed":
            raise ValueError("only a precomputed goal takes a planned move")
        x_d = np.asarray(x_d, dtype=float)
        space = self.clik.task
        if x_d.shape != (space.m,) or not np.all(np.isfinite(x_d)):
            raise ValueError(f"a goal needs {space.m} finite coordinates "
                             f"({', '.join(space.labels())}), got {x_d.tolist()}")
        if mode == "replay":
            key = self.key(x_d)
            if key not in self.stored and not (self._mode == "clik" and self.key(self._x_d) == key):
                raise TargetError(f"no stored configuration for target {list(key)}: a clik goal "
                                  "must reach it first")
        ref = None
        if mode in ("clik", "precomputed"):
            ref = point if point is not None else self.precompute(x_d)
        self._close_goal()
        current = self.reference                    # where a shaped step starts from
        if self._move is not None:
            current = self._move.at(t)
        elif self._planned is not None:             # a planned move under way: where it is now
            current = self.command
        self._move = None
        if mode == "replay":
            ref = self.stored[self.key(x_d)]
        self._x_d, self._mode = x_d, mode
        self._trajectory, self._t0 = trajectory, t
        self.learner = None
        if trajectory is not None and self.track_learning > 0:
            self.learner = HarmonicLearner(trajectory.period, space.m, self.track_harmonics,
                                           self.track_learning, self.track_settle_time)
        report = GoalReport([float(v) for v in x_d], mode, self.reach_tolerance, self.stall_steps,
                            unseen_after=self.period, learner=self.learner)
        self._unseen_since = None
        self.reports.append(report)
        self._fallback = ref if ref is not None else current
        self._trusted_since = None
        if self.trust is not None:
            self.trust.new_goal(None if trajectory is None else trajectory.period)
        settled = t
        self._planned, self._planned_from = move, t
        if ref is not None and move is None and self.shaper is not None and mode in self.shaped_modes:
            self._move = self.shaper.shape(t, current, ref)
            self._fraction = self._move.fraction(t)
            settled = self._move.end_time
            if self._move.mode is not None:
                report.shaped_mode = (self._move.mode.frequency, self._move.mode.damping)
            ref = self._move.at(t)
        self._online_from = {"clik": max(t + self.switch_delay, settled), "online": t,
                             "track": t}.get(mode, np.inf)
        self._next_step = self._online_from
        if ref is not None:
            self.reference = ref
        command = self.reference
        if trajectory is not None and self.track_dynamics:      # the path starts moving now
            _, velocity, acceleration = self.path_at(t)
            command = self.clik.dynamic_reference(self.reference.q, velocity, acceleration, self.rotor_mass)
        self._hand(command)
        if move is not None:
            self._follow_plan(t)
        return self.command

    def _follow_plan(self, t: float) -> ClikPoint:
        """The planned move's command at time t [s] (its sample half a CLIK period later, so that
        the held sample does not lag the plan), with its rate; the precomputed reference, fixed,
        once the move's duration has passed."""
        tau = t - self._planned_from
        if tau >= self._planned.duration - 1e-9:
            self._planned = None
            return self._hand(self.reference)
        s, s_dot, u = self._planned.reference(tau + 0.5 * self.period)
        command = ClikPoint(self.reference.q, s, u[list(self.clik.cm.active)], self.reference.x)
        return self._hand(command, s_dot)

    def _hand(self, command: ClikPoint, rate=None) -> ClikPoint:
        """Make ``command`` the one handed to the inner loop, with its rate of shortening [m/s] (all
        tendons; None: zero, a held or stepped reference); returns it."""
        self.command = command
        self.reference_rate = np.zeros_like(command.shortening) if rate is None else rate
        return command

    def path_at(self, t: float) -> tuple:
        """The reference path of the current track goal at time t [s]: (coordinates [m], velocity
        [m/s], acceleration [m/s^2]), its trajectory plus the learned correction."""
        x, velocity, acceleration = self._nominal_path(t)
        if self.learner is None:
            return x, velocity, acceleration
        c = self.learner.correction(t - self._t0)
        return x + c[0], velocity + c[1], acceleration + c[2]

    def target_at(self, t: float) -> tuple:
        """(x_d [m], its velocity [m/s] or None) of the current goal at time t [s]: a track goal's
        trajectory (as asked: the learned correction is the CLIK's, :meth:`path_at`), the fixed
        target otherwise."""
        if self._trajectory is None:
            return self._x_d, None
        x_d, velocity = self._trajectory.at(self._x_d, t - self._t0)
        return x_d, velocity if self.track_feedforward else None

    def _close_goal(self):
        """Store the reference of a clik goal (the end of its shaped step if one is under way) and
        close its report."""
        if self._mode == "clik":
            self.stored[self.key(self._x_d)] = self.reference if self._move is None else self._move.end
        if self.reports:
            self.reports[-1].closed = True

    def frame(self, t: float, x_measured, sigma=None) -> ClikPoint | None:
        """A mocap frame delivered at time t [s] with the measured task coordinates [m] (on an
        estimated feedback, ``sigma``: their standard deviations [m], without which no step is
        taken on it); returns the new reference when it changed: a fraction of a shaped step was
        given, or an online step was taken (a track goal's, also one along its path; None
        otherwise)."""
        if self._planned is not None:
            return self._follow_plan(t)
        moved = None
        if self._move is not None:
            fraction = self._move.fraction(t)
            if fraction != self._fraction:
                self._fraction = fraction
                self.reference = moved = self._hand(self._move.at(t))
            if fraction >= 1.0:
                self._move = None
        if t < self._next_step - 1e-9:
            return moved
        report = self.reports[-1]
        if not np.all(np.isfinite(x_measured)):           # a task marker not seen: no step on it
            report.unseen_frames += 1
            if self._unseen_since is None:
                self._unseen_since = t
            report.unseen_time = t - self._unseen_since
            if self._trajectory is None:
                return moved
            self._next_step = max(self._next_step + self.period, t + 0.5 * self.period)
            if report.holding:                          # refused by the trust region: by the model
                return self._along_path(self._nominal_path(t), by_model=True) or moved
            return self._along_path(self.path_at(t)) or moved
        self._unseen_since = None
        report.unseen_time = 0.0
        self._next_step = max(self._next_step + self.period, t + 0.5 * self.period)
        # a frame the mocap measured (zero sigma: the fused tip was seen) needs no trust, and it
        # re-anchors the estimate: the offsets before it are not the ones the estimate goes on to
        # show (it relaxes from the measurement to its own), so the judge starts afresh after it
        measured = sigma is not None and not np.any(np.asarray(sigma, dtype=float))
        if self.trust is not None and measured:
            report.holding, self._trusted_since = False, None     # stepping on a measurement holds nothing
            self.trust.reset()
        elif self.trust is not None:
            allowed, returned = self._trusted(t, x_measured, report)
            if not allowed and self._trajectory is not None:
                return self._along_path(self._nominal_path(t), by_model=True) or (
                    self.command if returned else moved)
            if returned:
                return self.command
            if not allowed:
                return moved
        # a track goal's path turns the Jacobian at every step: a held one's error, summed along the
        # path, is a drift the error term balances with a steady offset (drift / task_gain)
        refresh = self._trajectory is not None or self._steps % self.jacobian_every == 0
        self._steps += 1
        path = None if self._trajectory is None else self.path_at(t)     # x_d + c, its rates
        x_d = self._x_d if path is None else path[0]
        xd_dot = path[1] if path is not None and self.track_feedforward else None
        error = x_d - np.asarray(x_measured, dtype=float)
        x_step = x_measured
        if self.trust is not None:        # the part of the error the estimate's uncertainty leaves
            fraction = report.fraction = self.trust.fraction(error, sigma)
            report.uncertain_frames += fraction < 1.0
            if fraction == 0.0:           # none: no correction (as on an unseen frame)
                report.error = float(np.linalg.norm(error))
                return moved if path is None else self._along_path(path) or moved
            x_step = x_d - fraction * error
        ref, step = self.clik.step(self.reference.q, x_d, self.period, x_step, refresh, xd_dot)
        self.reports[-1].add(step, error)
        self.last_step = step
        if ref is None:
            if self.learner is not None:
                self._learn(t, x_d, x_measured, followed=False)
            return moved
        command, saturated = self._take(ref, path)
        if self.learner is not None:
            self._learn(t, x_d, x_measured, not step.constrained, saturated)
        return command

    def _on_path(self, t: float) -> ClikPoint:
        """A track goal's precomputed reference at t [s]: the model's equilibrium at its path's point
        (:meth:`_nominal_path`), solved from the goal's start (not from the reference the refused
        estimate led, which may be on another branch); the goal's start when none is found (the
        model-closed steps along the path then bring it there)."""
        try:
            return self.clik.precompute(self._nominal_path(t)[0], self._fallback.q, tol=self.tolerance,
                                        search=False)
        except TargetError:
            return self._fallback

    def _nominal_path(self, t: float) -> tuple:
        """:meth:`path_at` without the learned correction (what was learned on an estimate the trust
        region refused is not trusted either)."""
        tau = t - self._t0
        x, velocity = self._trajectory.at(self._x_d, tau)
        return x, velocity, self._trajectory.acceleration(self._x_d.size, tau)

    def _along_path(self, path, by_model: bool = False) -> ClikPoint | None:
        """A track goal's step along ``path`` (:meth:`path_at` at the frame's time) on a frame that
        cannot correct it (its task markers unseen, or an estimate too uncertain): the reference
        goes on along the path on the feedforward alone (no error term, nothing learned). A
        reference held instead would lose the path's motion over the frame for good, an offset the
        error term then has to win back. ``by_model`` (an estimate the trust region refuses): the
        model closes the CLIK's loop instead (its error term is the path less the model's task
        coordinates at the reference), so that the reference returns to the path's precomputed one
        at the task gain and goes on along it. A step projected onto the tension limits, or none
        found, counts in the goal's report as an online one does (without ``track_feedforward`` the
        model's error term alone moves it then). Returns the new command (None: no feasible step,
        or, not ``by_model``, no feedforward to follow: the reference holds)."""
        if not (self.track_feedforward or by_model):
            return None
        velocity = path[1] if self.track_feedforward else None
        measured = None if by_model else path[0]
        ref, step = self.clik.step(self.reference.q, path[0], self.period, measured, True, velocity)
        self.last_step = step
        report = self.reports[-1]
        report.infeasible_steps += step.constrained
        report.held_steps += step.held
        return None if ref is None else self._take(ref, path)[0]

    def _take(self, ref: ClikPoint, path) -> tuple[ClikPoint, bool]:
        """Make the CLIK's new reference ``ref`` the goal's, and hand the inner loop its command:
        on a track goal's ``path`` (x_r, its velocity and acceleration; None: not tracking) with
        ``track_dynamics`` the dynamic reference. Returns (the command, whether its feedforward
        needed tensions outside the limits)."""
        self.reference = ref
        saturated = False
        if path is not None and self.track_dynamics:
            ref = self.clik.dynamic_reference(ref.q, path[1], path[2], self.rotor_mass, refresh=False)
            saturated = self.clik.feasibility_error(ref.u_ff) is not None
            self.reports[-1].saturated_steps += saturated
        rate = None
        if self._mode in self.rate_modes:
            rate = (ref.shortening - self.command.shortening) / self.period
        return self._hand(ref, rate), saturated

    def _trusted(self, t: float, x_estimate, report: GoalReport) -> tuple[bool, bool]:
        """(whether an online step may be taken on the estimate at t [s], whether the reference
        returned now). A step may be taken when the trust region accepts the frame and, after a
        refusal, has accepted every frame for ``recover`` seconds; a refusal returns the reference
        to the goal's fallback and holds it there (a track goal's: to its path's precomputed
        reference, :meth:`_on_path`, which the caller then moves along the path), and sets
        ``report.holding``."""
        judged = self.trust.judged
        reason = self.trust.judge(t, x_estimate, self.reference.x)
        report.judged_frames += self.trust.judged - judged
        if reason is not None:
            report.untrusted_frames += 1
            report.distrust = reason
            self._trusted_since = None
            if report.holding:
                return False, False
            report.holding = True
            report.distrusts += 1
            report.distrust_time = t
            self.reference = self._fallback if self._trajectory is None else self._on_path(t)
            self._hand(self.reference)
            self.trust.reset()
            return False, True
        if not report.holding:
            return True, False
        if self._trusted_since is None:
            self._trusted_since = t
        if t - self._trusted_since < self.trust.config.recover - 1e-9:
            report.untrusted_frames += 1
            return False, False
        report.holding = False
        return True, False

    def _learn(self, t: float, x_r, x_measured, followed: bool, clipped: bool = False):
        """Hand the track goal's learner the frame at t [s] (the reference path x_r, the measured
        coordinates [m]; ``followed``: the CLIK step was neither constrained nor held; ``clipped``:
        the dynamic reference was)."""
        tau = t - self._t0
        learner = self.learner
        lesson = learner.add(tau, self._trajectory.at(self._x_d, tau)[0], x_r, x_measured, followed, clipped)
        mean_moved = np.linalg.norm(np.real(learner.current[0] - learner.previous[0])) if lesson else 0.0
        if self.trust is not None and mean_moved > self.trust.config.drift:
            # a lesson that moves the path's mean by more than the drift moves the reference as a
            # jump does, and the arm follows it late: the judge starts afresh after it
            self.trust.reset()

    def finish(self):
        """Store the reference of the last clik goal and close its report (end of an experiment)."""
        self._close_goal()


def clik_for(model, control, task) -> Clik:
    """The CLIK the configuration describes for ``task`` (a TaskConfig) on ``model``; the task's
    other tendons are held at the pretension."""
    cm = build_collocated(model, list(task.tendons), held_tension=control.tension_min,
                          friction=control.friction)
    return Clik(cm, task.space, ClikGains(control.task_gain, control.equilibrium_gain,
                                          control.singular_threshold),
                (control.tension_min, control.tension_max), control.closest_margin)


def outer_loop_for(model, control, task) -> OuterLoop:
    """The outer loop the configuration describes for ``task`` (a TaskConfig), starting from the
    hanging arm under the pretension; on an estimated feedback (``control.feedback`` fused or
    estimate) with the trust region of ``control.trust``."""
    clik = clik_for(model, control, task)
    start = clik.reference(solve_equilibrium(model, np.full(model.n_tendons, control.tension_min)).q)
    gains = [[getattr(control, name)[k] for k in task.tendons] for name in ("proportional", "derivative")]
    shaper = StepShaper(clik.cm, task.space, control.shaper, *gains, control.shaping_level)
    return OuterLoop(clik, start, control.switch_delay, control.clik_rate,
                     int(round(control.clik_rate / control.jacobian_rate)), control.seed_levels,
                     control.tolerance, control.reach_tolerance, control.stall_time, shaper,
                     control.shaped_modes, control.track_feedforward, control.rate_modes,
                     control.track_dynamics, control.rotor_mass, control.track_learning,
                     control.track_harmonics, control.track_settle_time,
                     TrustRegion(control.trust) if control.feedback != "mocap" and control.trust.enabled
                     else None)
