"""``clik`` node: the underactuated CLIK, precomputed and online, with the paper's switch.

Subscribes ``task/goal`` (soft_arm_interfaces/TaskGoal: the target task coordinates [m] in
``arm_base``, taken by their labels, and the mode: clik (default), replay, precomputed, online, or
track: the trajectory of the goal's phase from the target, see :mod:`soft_arm_control.outer_loop`)
and ``mocap/markers`` (on an estimated feedback, ``control.clik.feedback`` fused or estimate,
also ``fused/tip``, whose covariance, zero where the mocap saw the tip, says how much of the error
the estimate shows an online step may take: :mod:`soft_arm_control.trust_region`; a frame is paired
with the tip of its own stamp, and waits for it if the tip comes after it); publishes
``tendon/reference`` (position: reference shortenings [m] of all tendons; effort: feedforward
tensions [N], the pretension on the tendons the task does not use) and
``arm/configuration_reference`` (soft_arm_interfaces/ConfigurationReference: q_d, the goal it
answers, the goal's target now and the model's task coordinates at q_d [m]). A bad goal (another
frame, coordinates not the task's), an infeasible or a fragile one (one too near a fold of
the model's equilibria to be held, ``control.clik.min_frequency``) is rejected with a logged
reason; the last good reference stays. A target the precomputation does not reach from the
hanging arm starts from the seed equilibria (``control.clik.seed_levels``), solved at start-up so
that such a goal is answered in milliseconds too. Time is the mocap's (frame stamps), so it works
on sim time and on the rig alike; the stamps are checked as they enter
(:class:`~soft_arm_control.loop_clock.LoopClock`): a frame whose stamp is no number is dropped, and
a clock step (a stamp more than ``control.clik.max_time_step`` ahead, or one that goes back)
advances the CLIK's time by one frame period, counted (``clock_steps`` on ``/diagnostics``) and
logged (seen on a frame dropped behind the node's own step, with that step's wall time: the other
cause of such a jump), so that no stamp can hold the CLIK's steps off. Messages are stamped with
the latest frame's own stamp. A frame that arrived while the last one was processed is dropped (a
CLIK step that outlasts the frame period on a loaded computer would otherwise queue the frames, and
the goals and timers behind them, for seconds: :mod:`soft_arm_ros.backlog`); its time is taken, the
count is on ``/diagnostics`` (``frames_dropped``) and in a warning.
"""
from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from sensor_msgs.msg import JointState
from soft_arm_interfaces.msg import ConfigurationReference, TaskGoal

from soft_arm_model import build_model
from soft_arm_ros.backlog import Backlog
from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.conversions import (configuration_reference, goal_of, joint_state, markers_of,
                                      seconds_to_stamp, stamp_to_seconds)
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .clik import TargetError
from .collocated import full_tensions
from .config import control_of, task_of
from .loop_clock import LoopClock
from .outer_loop import outer_loop_for
from .target_margin import fragility_error

TIPS_KEPT = 16                  # fused tips kept by stamp for their frames (some 60 ms at 250 Hz)
REPORT_PERIOD = 1.0     # s: the current goal's report on /diagnostics at least this often

# A goal report's status (soft_arm_control.outer_loop.STATUSES) on /diagnostics: level and message
LEVELS = {"ok": DiagnosticStatus.OK, "constrained": DiagnosticStatus.WARN,
          "saturated": DiagnosticStatus.WARN, "stalled": DiagnosticStatus.WARN,
          "unreached": DiagnosticStatus.WARN, "unseen": DiagnosticStatus.WARN,
          "held": DiagnosticStatus.ERROR, "untrusted": DiagnosticStatus.WARN,
          "uncertain": DiagnosticStatus.WARN}
MESSAGES = {"ok": "target feasible",
            "constrained": "target infeasible for the model: moving to the closest feasible point",
            "saturated": "the path is too fast for the tendons: its dynamic feedforward exceeds the "
                         "tension limits and is clipped",
            "stalled": "target not reached: the error does not fall although every step is feasible "
                       "(out of reach, or a load the model lacks)",
            "unreached": "the goal ended away from its target",
            "unseen": "the task's markers are not seen: no correcting step (the reference holds, a "
                      "path's goes on along it)",
            "held": "no feasible step: the last reference is held",
            "untrusted": "the estimate fed back left the trust region: the precomputed reference holds",
            "uncertain": "the estimate's uncertainty explains the error it shows: no correcting "
                         "step (the reference holds, a path's goes on along it)"}


class ClikNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("clik", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        self.control = control_of(params, params.arm)
        self.task = task_of(params, params.arm)
        self.trajectories = {ph.name: ph.trajectory for ph in self.task.phases if ph.trajectory is not None}
        self.model = build_model(params.arm)
        self.outer = outer_loop_for(self.model, self.control, self.task)
        # at start-up, not at the goal that needs them (0.7 s idle, seconds under load; see
        # docs/decisions/0008-clik-node-solves-its-seed-equilibria-at-start-up.md)
        self.outer.seeds()
        self.names = self.model.tendon_names
        self.labels = self.task.space.labels()
        # the CLIK's time [s]: 0 until the first frame, then on by the frames' stamps, clock steps
        # taken out; a goal that comes before any frame (a restarted node takes the latched goal
        # first) starts at 0 and so at the first frame, whatever clock the frames are stamped on
        self.now = 0.0
        self.stamp = 0.0                # the latest frame's stamp [s]: what this node's messages carry
        self.frame_clock = LoopClock(self.control.clik_max_time_step, origin=self.now)
        self.rejected_goals = self.rejected_frames = 0
        self.ref_pub = self.create_publisher(JointState, TOPICS["reference"], QOS["tendon/reference"])
        self.q_pub = self.create_publisher(ConfigurationReference, TOPICS["configuration"],
                                           QOS["arm/configuration_reference"])
        self.create_subscription(TaskGoal, TOPICS["goal"], self.on_goal, QOS["task/goal"])
        self.frames = Backlog()
        self._drop_warned, self._drop_warned_at = 0, -math.inf   # frames dropped, monotonic time [s]
        self._frame_sub = self.create_subscription(PoseArray, TOPICS["markers"], self.on_frame,
                                                   QOS["mocap/markers"])
        # on an estimate fed back: the fused tips' covariances (3, 3) [m^2] by stamp [s], the latest
        # few, and a frame held until its own tip arrives (:meth:`on_tip`): (CLIK time [s], task
        # coordinates [m], stamp [s])
        self.tips: dict = {}
        self.waiting = None
        if self.outer.trust is not None:     # an estimate fed back: its uncertainty with it
            # the fused tip's: none where the mocap saw the tip, the estimate's elsewhere
            self.create_subscription(PoseWithCovarianceStamped, TOPICS["fused_tip"], self.on_tip,
                                     QOS["fused/tip"])
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._reported = None                 # (goal index, status) last published
        self._reported_stamp = -math.inf      # frame time [s] of the current goal's last report
        self._reported_wall = -math.inf       # monotonic time [s] of it
        self.create_timer(REPORT_PERIOD, self._heartbeat)
        self.get_logger().info(f"clik ready for task {self.task.name} "
                               f"({', '.join(self.labels)})")

    def publish(self, ref):
        self.ref_pub.publish(joint_state(self.names, self.stamp, position=ref.shortening,
                                         velocity=self.outer.reference_rate,
                                         effort=full_tensions(self.outer.clik.cm, ref.u_ff)))
        x_d, _ = self.outer.target_at(self.now)
        goal = self.outer.reports[-1]
        self.q_pub.publish(configuration_reference(self.stamp, len(self.outer.reports) - 1, goal.mode, ref.q,
                                                   self.labels, x_d, ref.x))

    def on_goal(self, msg: TaskGoal):
        try:
            x_d, mode, phase = goal_of(msg, self.labels)
            trajectory = None
            if mode == TaskGoal.MODE_TRACK:
                trajectory = self.trajectories.get(phase)
                if trajectory is None:
                    raise ValueError(f"a track goal names a phase of task {self.task.name} with a "
                                     f"trajectory ({', '.join(sorted(self.trajectories))}), got {phase!r}")
            point = None
            if mode in ("clik", "precomputed") and x_d.shape == (self.task.space.m,):
                point = self.outer.precompute(x_d)
                reason = fragility_error(self.outer, self.control, self.task, point)
                if reason is not None:
                    raise TargetError(f"target {x_d.round(4).tolist()} m is fragile: {reason}")
            ref = self.outer.goal(self.now, x_d, mode, point=point, trajectory=trajectory)
        except (TargetError, ValueError) as exc:
            self.rejected_goals += 1
            self.get_logger().error(f"goal rejected: {exc}; keeping the last reference")
            return
        self.publish(ref)
        if len(self.outer.reports) > 1:
            self.publish_diagnostics(len(self.outer.reports) - 2)     # the closed one, final

    def on_frame(self, msg: PoseArray):
        """A mocap frame: processed (:meth:`on_markers`); then the frames that arrived meanwhile
        are dropped, their time taken (module docstring)."""
        started = time.monotonic()
        self.on_markers(msg)
        self.frames.processed_one()
        late = self.frames.drain(self._take_frame)
        ended = time.monotonic()
        if late is not None:
            self._take_time(late, ended - started)
        if self.frames.dropped > self._drop_warned and ended >= self._drop_warned_at + 5.0:
            # throttled here: rclpy's throttle inspects the caller's frame on every call
            self._drop_warned, self._drop_warned_at = self.frames.dropped, ended
            self.get_logger().warning(
                f"the CLIK falls behind the mocap frames: {self.frames.dropped} of "
                f"{self.frames.dropped + self.frames.processed} dropped so far")

    def _take_frame(self) -> PoseArray | None:
        """The next frame the subscription holds, taken past the executor (None: it holds none)."""
        sub = self._frame_sub
        try:
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:             # the node is being destroyed: nothing more to take
            return None
        return None if taken is None else taken[0]

    def _take_time(self, msg: PoseArray, step_wall: float | None = None) -> bool:
        """The frame's stamp into the CLIK's time (:attr:`now`); False, the frame dropped, when the
        stamp is no number. ``step_wall`` [s]: for a frame that arrived during this node's own
        step, how long that step took on the wall clock (a clock step seen on it may be the node's
        own lateness, and its warning says so)."""
        stamp, steps = stamp_to_seconds(msg.header.stamp), self.frame_clock.steps
        try:
            self.now = self.frame_clock.advance(stamp)
        except ValueError as exc:
            self.rejected_frames += 1
            self.get_logger().warning(f"mocap frame dropped: {exc}", throttle_duration_sec=1.0)
            return False
        self.stamp = stamp
        if self.frame_clock.steps != steps:
            lateness = ""
            if step_wall is not None and self.frame_clock.last_step[0] == "forward":
                lateness = (f"; seen on a frame that arrived during this node's own step of "
                            f"{step_wall:.3g} s (wall): if the mocap's clock did not step, the CLIK "
                            "fell that far behind its frames")
            self.get_logger().warning(f"the mocap frames' clock stepped, the CLIK goes on: "
                                      f"{self.frame_clock.describe()}{lateness}")
        return True

    def on_markers(self, msg: PoseArray):
        if not self._take_time(msg):
            return
        markers = markers_of(msg)
        if markers.shape[0] != self.model.marker_X.size:
            self.get_logger().warning(f"mocap frame with {markers.shape[0]} markers, expected "
                                      f"{self.model.marker_X.size}", throttle_duration_sec=1.0)
            return
        x = self.task.space.from_markers(markers)
        if self.outer.trust is None:
            self._step(self.now, x, None)
            return
        # on an estimate: the step weighs this frame's own tip uncertainty, published beside it
        # on fused/tip and perhaps not here yet; a frame still waiting for its tip when the next
        # comes goes without (no step on it: its uncertainty is unknown)
        if self.waiting is not None:
            waiting, self.waiting = self.waiting, None
            self._step(waiting[0], waiting[1], None)
        covariance = self.tips.get(self.stamp)
        if covariance is None:
            self.waiting = (self.now, x, self.stamp)
            return
        self._step(self.now, x, self.task.space.tip_sigma(covariance))

    def _step(self, t: float, x, sigma):
        """The CLIK's step on the frame of CLIK time ``t`` [s] with task coordinates ``x`` [m] and
        their standard deviations ``sigma`` [m] (None: measured, or on an estimate unknown)."""
        ref = self.outer.frame(t, x, sigma)
        if ref is not None:
            self.publish(ref)
        if self.outer.reports and ((len(self.outer.reports), self.outer.reports[-1].status) != self._reported
                                   or self.now >= self._reported_stamp + REPORT_PERIOD):
            self.publish_diagnostics()        # at once when a goal turns infeasible; once a second

    def on_tip(self, msg: PoseWithCovarianceStamped):
        """A fused tip: its covariance kept by its stamp, for the frame of the same stamp (the
        shape estimator stamps both with the state they come from); the frame waiting for it
        steps now, or without it if this tip is newer (its own was lost)."""
        stamp = stamp_to_seconds(msg.header.stamp)
        self.tips[stamp] = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3]
        while len(self.tips) > TIPS_KEPT:
            del self.tips[next(iter(self.tips))]
        if self.waiting is not None and stamp >= self.waiting[2]:
            (t, x, frame), self.waiting = self.waiting, None
            self._step(t, x, self.task.space.tip_sigma(self.tips[stamp]) if stamp == frame else None)

    def _heartbeat(self):
        """The current goal's report when the frames have not given one for a second of wall time
        (no mocap: a report, unchanged, that says the node is alive)."""
        if time.monotonic() >= self._reported_wall + REPORT_PERIOD:
            self.publish_diagnostics()

    def publish_diagnostics(self, index: int | None = None):
        """A goal's feasibility on ``/diagnostics`` (the current one on every change and once a
        second of frame time, or of wall time without frames, so that a simulation in lockstep,
        whose timers do not run, reports the goal as it goes too; ``index``: another, e.g. the one
        a new goal closed, with its final counts):
        OK; WARN while its online steps are projected onto the tension limits (the target is
        infeasible for the model: the reference moves to the closest feasible point), while a
        track goal's path needs tensions outside the limits (saturated) and while it is stalled
        (feasible steps, but the error does not fall); ERROR when a step found no feasible
        reference and the last one was held. The values are those of the goal's report (JSON), with
        ``goal``, its index since start-up."""
        if not self.outer.reports:
            return
        index = len(self.outer.reports) - 1 if index is None else index
        report = self.outer.reports[index]
        level, message = LEVELS[report.status], MESSAGES[report.status]
        if report.status == "untrusted":           # say why: the trust region's reason
            message = f"{message} ({report.distrust})"
        status = DiagnosticStatus(level=level, name="clik", hardware_id="soft_arm", message=message)
        d = {"goal": index, **report.as_dict(), "frames_dropped": self.frames.dropped,
             "frames_rejected": self.rejected_frames, "clock_steps": self.frame_clock.steps}
        status.values = [KeyValue(key=k, value=v if k == "status" else json.dumps(v)) for k, v in d.items()]
        msg = DiagnosticArray(status=[status])
        seconds_to_stamp(msg.header.stamp, self.stamp)
        self.diagnostics_pub.publish(msg)
        if index == len(self.outer.reports) - 1:
            self._reported = (len(self.outer.reports), report.status)
            self._reported_stamp, self._reported_wall = self.now, time.monotonic()


def main(args=None) -> int:
    return run_node(ClikNode, "clik", args)


if __name__ == "__main__":
    sys.exit(main())
