"""``shape_estimator`` node: the arm's shape from its tendons and the markers the mocap still sees
(:mod:`soft_arm_control.shape_estimation`).

Subscribes ``tendon/state`` (shortenings [m], rates [m/s], applied tensions [N]) and
``mocap/markers`` (unseen markers NaN). Every ``1 / estimator.rate`` of state time it updates the
estimate with the latest state and the latest frame since the last update, and publishes, stamped
with that state's stamp:

- ``estimate/markers`` (PoseArray, the layout of ``mocap/markers``): the estimate of every marker
  the estimator stands by, the others invalid (NaN: the estimate is lost, or the marker's standard
  deviation exceeds ``estimator.max_sigma``; :meth:`~.shape_estimation.ShapeEstimate.defended`);
- ``fused/markers`` (the same layout): the frame's markers where the mocap saw them, the estimate's
  elsewhere (the estimate's alone when no frame came since the last update);
- ``estimate/tip`` (PoseWithCovarianceStamped): the estimate's tip and its position covariance
  [m^2], whether the estimator stands by it or not (a consumer of positions takes
  ``estimate/markers``, whose tip is invalid where it does not);
- ``fused/tip`` (the same): the mocap's tip where it saw it, with a zero covariance (a
  measurement), the estimate's tip and covariance elsewhere: the uncertainty the online CLIK on
  ``fused/markers`` reads (:mod:`soft_arm_control.trust_region`). Where the estimator does not stand
  by its estimate, ``fused/markers``' unseen tip is invalid and this one is the estimate's;
- ``estimate/shape`` (MarkerArray): the estimated backbone, for RViz;
- once a second of wall time ``/diagnostics`` (status ``shape_estimator``, from the first update):
  markers used and gated, the
  innovations' mean normalised squares, divergences, updates left out of the model's domain,
  restarts, samples at which the filter could not start (``start_failures``), the updates whose
  markers went out invalid (``undefended``, with the last reason), the estimated stiffness scale
  and friction coefficients, the tip's standard deviation, the time since the last update.
  WARN when a marker diverged, an update was left out, the estimate restarted, could not start or
  was not stood by since the last report, or no update came for a report period.

The online CLIK closes its loop on either topic by remapping its ``mocap/markers`` (``soft-arm-
experiment --feedback fused|estimate``). A state whose stamp is no number, or any field no number,
is counted and left out. The estimate keeps its time from the states' stamps
(:class:`~soft_arm_control.loop_clock.LoopClock`): a stamp more than ``estimator.max_time_step``
ahead, or one that goes back, is a clock step, counted (``clock_steps`` on ``/diagnostics``) and
taken as one period, so that a stepped clock neither stops the updates nor inflates the estimate's
uncertainty. The messages keep the states' own stamps.
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseArray, PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker, MarkerArray

from soft_arm_model import build_model
from soft_arm_ros.contract import FRAME, QOS, TOPICS
from soft_arm_ros.conversions import markers_of, ordered, pose_array, seconds_to_stamp, stamp_to_seconds
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .config import control_of
from .estimators import shape_estimator
from .loop_clock import LoopClock
from .shape_estimation import ESTIMATOR_SCHEMA, EstimatorConfig, fused_markers, fused_tip

REPORT_PERIOD = 1.0          # s of wall time between diagnostics


class ShapeEstimatorNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("shape_estimator", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        self.config = EstimatorConfig.of(params.section("estimator", ESTIMATOR_SCHEMA))
        self.model = build_model(params.arm)
        self.core = shape_estimator(self.model, self.config, control_of(params, params.arm).rotor_mass)
        self.names = self.model.tendon_names
        self.period = 1.0 / self.config.rate
        self.clock = LoopClock(self.config.max_time_step)   # the estimate's time, from the states' stamps
        self.next_update = -math.inf     # in that time [s]
        self.frame = None                # (stamp [s], markers) of the latest frame since the last update
        self.rejected = self.stale_frames = 0
        self._reported_stale = 0
        self.nis, self.used, self.gated = [], 0, 0
        self.undefended, self.distrust = 0, None      # updates with invalid markers, the last reason
        self._reported_counts = dict(self.core.counts)
        self._reported_at = -math.inf
        self.estimate_pub = self.create_publisher(PoseArray, TOPICS["estimate"], QOS["estimate/markers"])
        self.fused_pub = self.create_publisher(PoseArray, TOPICS["fused"], QOS["fused/markers"])
        self.tip_pub = self.create_publisher(PoseWithCovarianceStamped, TOPICS["estimate_tip"],
                                             QOS["estimate/tip"])
        self.fused_tip_pub = self.create_publisher(PoseWithCovarianceStamped, TOPICS["fused_tip"],
                                                   QOS["fused/tip"])
        self.shape_pub = self.create_publisher(MarkerArray, TOPICS["estimate_shape"], QOS["estimate/shape"])
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(PoseArray, TOPICS["markers"], self.on_markers, QOS["mocap/markers"])
        self.create_subscription(JointState, TOPICS["state"], self.on_state, QOS["tendon/state"])
        self.create_timer(REPORT_PERIOD, self._heartbeat)
        self._last = None                # (stamp [s], estimate) of the last update
        self._updated_at = None          # monotonic time [s] of the last update
        self.get_logger().info(f"shape estimator ready: {self.config.rate:g} Hz on tendon/state")

    def on_markers(self, msg: PoseArray):
        markers = markers_of(msg)
        if markers.shape != (self.model.marker_X.size, 3):
            self.rejected += 1
            self.get_logger().warning(f"mocap frame with {markers.shape[0]} markers, expected "
                                      f"{self.model.marker_X.size}", throttle_duration_sec=1.0)
            return
        self.frame = stamp_to_seconds(msg.header.stamp), markers

    def _fresh_frame(self, t: float):
        """The markers of the latest frame if it is stamped within ``max_frame_age`` of the state's
        stamp ``t`` [s] (both on the rig's wall clock, or on /clock); None otherwise (counted)."""
        if self.frame is None:
            return None
        stamp, markers = self.frame
        if abs(t - stamp) <= self.config.max_frame_age:
            return markers
        self.stale_frames += 1
        self.get_logger().warning(
            f"mocap frame left out: stamped {t - stamp:+.3f} s from the state it would be weighed "
            f"with (estimator.max_frame_age {self.config.max_frame_age:g} s)", throttle_duration_sec=1.0)
        return None

    def on_state(self, msg: JointState):
        t = stamp_to_seconds(msg.header.stamp)
        try:
            advance = self.clock.check(t)
            s, sd, u = (ordered(msg, field, self.names) for field in ("position", "velocity", "effort"))
            if not (np.all(np.isfinite(s)) and np.all(np.isfinite(sd)) and np.all(np.isfinite(u))):
                raise ValueError("a value that is no number")
        except ValueError as exc:
            self.rejected += 1
            self.get_logger().warning(f"state left out: {exc}", throttle_duration_sec=1.0)
            return
        now = self.clock.commit(t, advance)
        if advance.step is not None:
            self.get_logger().warning(f"the states' clock stepped, the estimate goes on: "
                                      f"{self.clock.describe()}", throttle_duration_sec=1.0)
        if now < self.next_update - 1e-9:
            return                              # between updates
        self.next_update = now + self.period
        frame = self._fresh_frame(t)
        report = self.core.update(now, s, sd, u, frame)
        estimate = self.core.estimate()
        if report.marker_nis is not None:
            self.nis += [v for v in report.marker_nis if np.isfinite(v)]
        self.used += len(report.used)
        self.gated += len(report.gated)
        defended = estimate.defended(self.config.max_sigma)
        if not np.all(np.isfinite(defended)):
            self.undefended += 1
            self.distrust = (estimate.distrust
                             or f"a marker's standard deviation above {self.config.max_sigma} m")
        self.estimate_pub.publish(pose_array(defended, t))
        self.fused_pub.publish(pose_array(fused_markers(frame, defended), t))
        self.tip_pub.publish(tip_message(estimate.markers[-1], estimate.marker_covariance[-1], t))
        self.fused_tip_pub.publish(tip_message(*fused_tip(frame, estimate), t))
        self.shape_pub.publish(self._shape(t))
        self.frame = None
        self._last, self._updated_at = (t, estimate), time.monotonic()
        if time.monotonic() >= self._reported_at + REPORT_PERIOD:
            self.publish_diagnostics(t, estimate)

    def _heartbeat(self):
        """The diagnostics when the states have not given them for a second of wall time."""
        if self._last is not None and time.monotonic() >= self._reported_at + REPORT_PERIOD:
            self.publish_diagnostics(*self._last)

    def _shape(self, t: float) -> MarkerArray:
        m = Marker()
        m.header.frame_id = FRAME
        seconds_to_stamp(m.header.stamp, t)
        m.ns, m.id, m.type, m.action = "estimate", 0, Marker.LINE_STRIP, Marker.ADD
        m.scale.x = 0.008
        m.color.r, m.color.g, m.color.b, m.color.a = 0.1, 0.6, 0.9, 1.0
        m.pose.orientation.w = 1.0
        m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in self.core.data.p]
        out = MarkerArray()
        out.markers.append(m)
        return out

    def publish_diagnostics(self, stamp: float, estimate):
        counts = self.core.counts
        new = {k: counts[k] - self._reported_counts[k]
               for k in ("diverged", "out_of_domain", "restarts", "start_failures")}
        stiffness, friction = self.core.parameters
        stale = self.stale_frames - self._reported_stale
        silent = time.monotonic() - self._updated_at if self._updated_at is not None else 0.0
        warn = any(new.values()) or self.undefended or stale or silent > REPORT_PERIOD
        level = DiagnosticStatus.WARN if warn else DiagnosticStatus.OK
        message = "estimating" if not warn else (
            f"no update for {silent:.1f} s (no tendon/state?): the estimate is that of then; "
            if silent > REPORT_PERIOD else "") + (
            f"{new['diverged']} marker divergences, {new['out_of_domain']} updates left out of the "
            f"model's domain, {new['restarts']} restarts (the estimate was lost), "
            f"{new['start_failures']} samples with no start (no equilibrium at their tensions), "
            f"{self.undefended} "
            "updates with markers not stood by"
            + (f" (last: {self.distrust})" if self.distrust else "")
            + f", {stale} mocap frames left out as stamped too far from the states since the last report")
        values = {"updates": counts["updates"], "markers_used": self.used, "markers_gated": self.gated,
                  "marker_nis_mean": float(np.mean(self.nis)) if self.nis else "",
                  "diverged": counts["diverged"], "out_of_domain": counts["out_of_domain"],
                  "restarts": counts["restarts"], "start_failures": counts["start_failures"],
                  "since_update_s": round(silent, 3),
                  "undefended": self.undefended,
                  "distrust": self.distrust or "",
                  "rejected": self.rejected, "stale_frames": self.stale_frames,
                  "clock_steps": self.clock.steps,
                  "stiffness_scale": round(stiffness, 4),
                  "friction": [round(float(f), 4) for f in friction],
                  "tip_sigma_mm": round(1e3 * float(estimate.marker_sigma[-1]), 3)}
        if hasattr(self.core, "settling_time"):
            # the dynamic filter's: how long the latest rest must last before the tendons teach
            # the stiffness and friction (inf: no rest yet, or one whose balance the model does not hold)
            values["rest_settling_time_s"] = round(float(self.core.settling_time), 2)
        status = DiagnosticStatus(level=level, name="shape_estimator", hardware_id="soft_arm",
                                  message=message,
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        seconds_to_stamp(msg.header.stamp, stamp)
        self.diagnostics_pub.publish(msg)
        self.nis, self.used, self.gated = [], 0, 0
        self.undefended, self.distrust = 0, None
        self._reported_stale = self.stale_frames
        self._reported_counts = dict(counts)
        self._reported_at = time.monotonic()


def tip_message(position, covariance, t: float) -> PoseWithCovarianceStamped:
    """A tip position [m] in arm_base with its covariance (3, 3) [m^2], stamped t [s]; the
    orientation is not estimated (identity, variance 1e6)."""
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = FRAME
    seconds_to_stamp(msg.header.stamp, t)
    point = msg.pose.pose.position
    point.x, point.y, point.z = (float(v) for v in position)
    msg.pose.pose.orientation.w = 1.0
    full = np.zeros((6, 6))
    full[:3, :3] = covariance
    full[3:, 3:] = np.eye(3) * 1e6
    msg.pose.covariance = full.ravel().tolist()
    return msg


def main(args=None) -> int:
    return run_node(ShapeEstimatorNode, "shape_estimator", args)


if __name__ == "__main__":
    sys.exit(main())
