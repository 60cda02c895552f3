"""Playing an experiment of ``tasks.yaml`` against a stream of mocap frames, ROS-free.

The schedule starts at the first frame and runs on the frames' times on the runner's own clock
(the node's :class:`~soft_arm_control.loop_clock.LoopClock` over their stamps), so that a step of
the stamps' clock neither skips windows nor holds them; at each window start the runner issues the
goal (target coordinates and the phase's mode). It keeps the measured task coordinates and tip positions of
every frame and, at the end, computes the paper's metrics (the peak tip speed from differences of
the measured tip positions over at least 10 ms, as on the rig) and what became of each goal: the
closest and the last measured task error, with the clik node's report of it (infeasible and held
steps, status) when one arrived. A task with a pendulum starts with the strike: the first goal and
the ball's release are timed by the strike's plan (:mod:`.strike`), and the ball's frames give what
the motion capture saw of the strike.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from soft_arm_control.config import TaskConfig

from .metrics import measured_speed, summarise, tracking_metrics, transition_metrics
from .strike import measured_strike


class Goal(NamedTuple):
    """A window's goal: ``target`` task coordinates [m], the clik ``mode`` of its ``phase`` and
    ``window`` [s], how long it stands."""
    target: np.ndarray
    mode: str
    phase: str
    window: float


RELEASE_LEAD = 0.1       # s from the first frame to the start of a task with a pendulum


class TaskRunner:
    """Runs one task; ``tip_marker``: index of the tip among the markers. With a pendulum
    (``plan``, a :class:`~.strike.StrikePlan`, and the ``arm`` whose markers the frames carry), the
    first window's goal goes out ``plan.send_delay`` after its start, the ball is released
    ``plan.release_delay`` after it (:attr:`release_at`), and the ball's frames (:meth:`ball`)
    give the strike's metrics (:meth:`strike`). With a pendulum the task starts
    :data:`RELEASE_LEAD` after the first frame, so that the release, sent at that frame, reaches
    the ball before its time even when the plan releases it at the start."""

    def __init__(self, task: TaskConfig, tip_marker: int, plan=None, arm=None):
        if (task.pendulum is None) != (plan is None):
            raise ValueError("a task with a pendulum needs a strike plan, and only such a task")
        self.task, self.plan, self.arm = task, plan, arm
        self._deferred = None          # the first window's goal, until plan.send_delay
        self.arm_frames, self.ball_frames = {}, {}      # exposure time: markers / ball centre
        self.windows = [(ph.name, ph.mode, k, ph.window) for ph in task.phases for k in ph.sequence]
        self.phases = {ph.name: ph for ph in task.phases}
        self.tip = tip_marker
        self.tip_axes = [a for k, a in zip(task.space.markers, task.space.axes) if k == tip_marker] \
            or [0, 1, 2]
        self.t0 = None             # the schedule's start [s]: on the frames' stamps, on the runner's clock
        self._loop0 = None
        self.index = -1
        self.starts = np.cumsum([0.0] + [w[3] for w in self.windows])
        self.samples = []          # (t, window, x, x_d, tip, tip position)
        self.clik_reports = {}     # goal index: the clik node's last report of it

    @property
    def duration(self) -> float:
        return float(self.starts[-1])

    @property
    def done(self) -> bool:
        return self.t0 is not None and self.index >= len(self.windows)

    def frame(self, t: float, markers, loop_t: float | None = None) -> Goal | None:
        """A mocap frame stamped t [s] (markers (n, 3) [m]), at ``loop_t`` [s] on the runner's own
        clock (None: t); returns the :class:`Goal` when a new window starts with this frame, else
        None. The windows and the metrics' times run on ``loop_t``; the release and the strike's
        frames on the stamps, which the simulator and the ball's frames share."""
        loop_t = t if loop_t is None else float(loop_t)
        if self.t0 is None:
            lead = RELEASE_LEAD if self.plan is not None else 0.0
            self.t0, self._loop0 = t + lead, loop_t + lead
        goal = None
        rel = loop_t - self._loop0
        while self.index < len(self.windows) and rel >= self.starts[self.index + 1] - 1e-9:
            self.index += 1
            self._deferred = None
            if self.index < len(self.windows):
                phase, mode, k, window = self.windows[self.index]
                goal = Goal(np.array(self.task.targets[k]), mode, phase, window)
                if self.index == 0 and self.plan is not None and self.plan.send_delay > 0:
                    self._deferred, goal = goal, None
        if self._deferred is not None and rel >= self.plan.send_delay - 1e-9:
            goal, self._deferred = self._deferred, None
        if self.release_at is not None and t >= self.release_at - 1e-9:
            self.arm_frames[t] = np.asarray(markers, dtype=float).copy()
        if 0 <= self.index < len(self.windows):
            markers = np.asarray(markers, dtype=float)
            self.samples.append((rel, self.index, self.task.space.from_markers(markers),
                                 self.target_at(self.index, rel), markers[self.tip, self.tip_axes],
                                 markers[self.tip].copy()))
        return goal

    def target_at(self, window: int, rel: float) -> np.ndarray:
        """The target [m] of ``window`` at ``rel`` [s] after the start: a track window's trajectory
        from its target, the target itself otherwise."""
        phase, _, k, _ = self.windows[window]
        return self.phases[phase].target_at(self.task.targets[k], rel - self.starts[window])

    @property
    def release_at(self) -> float | None:
        """When the ball is to be released [s, frame time] (None before the first frame or
        without a pendulum)."""
        if self.plan is None or self.t0 is None:
            return None
        return self.t0 + self.plan.release_delay

    def ball(self, t: float, centre):
        """A frame of the ball's marker at exposure time t [s] (centre (3,) [m])."""
        if self.release_at is not None and t >= self.release_at - 1e-9:
            self.ball_frames[t] = np.asarray(centre, dtype=float).copy()

    def strike(self) -> dict | None:
        """The strike's ``plan`` and what the motion capture ``measured``
        (:func:`~.strike.measured_strike` over the frames with both the arm and the ball); None
        without a pendulum."""
        if self.plan is None:
            return None
        stamps = sorted(set(self.arm_frames) & set(self.ball_frames))
        measured = {"struck": False}
        if stamps and self.release_at is not None:
            measured = measured_strike(self.task.pendulum, self.release_at, np.array(stamps),
                                       np.array([self.ball_frames[t] for t in stamps]),
                                       np.array([self.arm_frames[t] for t in stamps]), self.arm)
        return {"plan": self.plan.as_dict(), "measured": measured}

    def metrics(self):
        """(per-transition metrics, summary) of the windows played so far, track windows aside
        (:meth:`tracking`)."""
        rows = []
        for w, (phase, mode, k, window) in enumerate(self.windows):
            s = [x for x in self.samples if x[1] == w and _seen(x)]
            if len(s) < 3 or mode == "track":
                continue                      # a window the mocap did not see has no figures
            t = np.array([x[0] for x in s])
            tip3 = np.array([x[5] for x in s])
            speed = measured_speed(t, tip3)
            rows.append(transition_metrics(phase, k + 1, t, np.array([x[3] - x[2] for x in s]),
                                           np.array([x[4] for x in s]), speed,
                                           self.task.steady_time, window))
        return rows, (summarise(rows) if rows else None)

    def tracking(self) -> list:
        """:class:`~.metrics.TrackingMetrics` of the track windows played so far."""
        rows = []
        for w, (phase, mode, k, window) in enumerate(self.windows):
            s = [x for x in self.samples if x[1] == w]
            if mode != "track" or len(s) < 3:
                continue
            rows.append(tracking_metrics(phase, k + 1, self.phases[phase].trajectory,
                                         np.array([x[0] for x in s]) - self.starts[w],
                                         np.array([x[3] - x[2] for x in s]),
                                         min(self.task.steady_time, 0.5 * window)))
        return rows

    def clik_report(self, t: float, values: dict):
        """The clik node's report of one goal at time t [s] (its ``/diagnostics`` values: ``goal``,
        the goal's index since start-up, ``target`` and the counts of
        :class:`~soft_arm_control.outer_loop.GoalReport`); the last one of each goal is kept."""
        self.clik_reports[int(values["goal"])] = {**values, "as_of": None if self.t0 is None else t - self.t0}

    def goals(self) -> list:
        """Per window: target (1-based), mode, the closest and the last measured task error norms
        [m], and ``clik``, the clik node's last report of that goal (None if none arrived or it was
        of another target: a goal the node rejected shifts the count)."""
        out = []
        for w, (phase, mode, k, _) in enumerate(self.windows):
            errors = [float(np.linalg.norm(x[3] - x[2])) for x in self.samples if x[1] == w and _seen(x)]
            report = self.clik_reports.get(w)
            if report is not None and not np.allclose(report["target"], self.task.targets[k]):
                report = None
            out.append({"phase": phase, "mode": mode, "target": k + 1,
                        "closest_error": min(errors) if errors else None,
                        "error": errors[-1] if errors else None, "clik": report})
        return out


def _seen(sample) -> bool:
    """A sample whose task and tip markers the mocap saw (no NaN)."""
    return bool(np.all(np.isfinite(sample[2])) and np.all(np.isfinite(sample[4])))
