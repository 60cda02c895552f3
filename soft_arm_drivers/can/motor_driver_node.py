"""``motor_driver`` node: the rig's CAN motors (MIT protocol, torque mode) in the simulator's place.

A thin shell around :class:`~soft_arm_drivers.can.motor_driver.MotorDriver`; a thread of its own
(:class:`~.periodic_thread.PeriodicThread`, apart from the executor, as a ros2_control hardware loop
is) runs one driver cycle at ``rig.motors.rate`` on the monotonic clock, and

- publishes ``tendon/state`` (sensor_msgs/JointState over ``arm.tendons.names``: position =
  shortening [m] from the straight arm, ``rig.motors.zero_shortening`` at the zeroing pose;
  velocity [m/s]; effort = measured tension [N]), stamped with the oldest sensor time stamp of the
  cycle's replies, in every mode, whenever every motor replied;
- publishes ``/diagnostics`` (diagnostic_msgs/DiagnosticArray: one status for the driver with mode,
  fault reason, command counters, its cycle timing over the last 1000 cycles: period p50/p99/max
  and p99 error from 1/rate [ms], deadline misses (cycles later than 1.5 periods), and the
  state-to-command latency over the last 1000 answers (:mod:`.command_latency`: from publishing a
  state to receiving the command stamped like it, p50/p99/max [ms]) and over every answer since the
  node started (``state_to_command_run_p99_ms``, ``_run_max_ms``); one per motor with
  temperature, error code and reply age) every 0.5 s and at once when the mode or the fault changes.

Subscribes ``tendon/command`` (effort = tensions [N]; a command missing a tendon, with NaN or
infinity or a non-finite stamp is counted and dropped: the previous one ages until the watchdog
latches a fault). The watchdog counts a command's age from its receipt on this node's monotonic
clock, whatever its stamp says (:class:`~.motor_driver.MotorDriver`). Commands are taken from one
publisher only, the node ``rig.motors.command_publisher`` names (:mod:`.command_source`): while
another node publishes on ``tendon/command`` (a second computer on the domain, a stray ``ros2 topic
pub``) every command is refused, the publishers are named on ``/diagnostics``, and with the motors
enabled the fault ``foreign publisher`` is latched; activation is refused while one is there.

A managed (lifecycle) node (:mod:`soft_arm_ros.lifecycle`), driven with ``ros2 lifecycle set
/motor_driver <transition>`` or by ``soft-arm-experiment`` and ``rig.launch.py``:

- ``configure`` opens the bus, takes every motor out of motor mode and polls until every motor has
  answered (refused, bus closed again, if one is silent for 1 s or reports an error); from then on the
  cycle timer runs and the state flows (inactive: motors polled with zero torque, out of motor mode);
- ``activate`` enters motor mode and applies the commands (clearing a latched fault, from zero
  tension); a fault while active (watchdog, a silent or failing motor, e-stop) sends zero torque
  at once and deactivates the node itself, the fault latched and reported until the next activate;
- ``deactivate`` sends zero torque and exits motor mode; ``cleanup`` and ``shutdown`` close the bus
  after the same.

Services: ``~/estop`` (std_srvs/Trigger: zero torque and out of motor mode, latched, in any state;
forces an active node inactive; answers failure, naming the motors, when the bus refused its
frames: then, as when a deactivation's or the closing's frames are refused, the node goes on and
its process exits with status 1 when it is stopped, whatever a later stop sends) and ``~/zero``
(std_srvs/Trigger: the current angles become the zero; only when inactive, with the tendons slack).

Parameters: ``rig.motors.*`` of the package's ``config/rig.yaml`` overlaid with the node's own
(``--params-file``, ``-p rig.motors.key:=value``), ``arm.*`` for the tendon names, each declared
read-only with a description and range (:class:`~soft_arm_ros.parameters.NodeParameters`). A bad
value logs the key, the value and the allowed range and exits with status 2. Leaving (Ctrl-C,
SIGTERM, an exception) sends zero torque and exit-motor-mode to every motor.
"""
from __future__ import annotations

import os
import sys
import time
import traceback

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from soft_arm_model.parameters import ConfigError
from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.conversions import joint_state, ordered, stamp_to_seconds
from soft_arm_ros.hardware_lock import LockTimeout
from soft_arm_ros.lifecycle import SUCCESS, ManagedHardwareNode, transition
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .command_latency import CommandLatency
from .command_source import CommandSource
from .driver_config import NAMESPACE, SCHEMA, bus_load, parse_driver_config
from .motor_driver import Diagnostics, MotorDriver
from .periodic_thread import PeriodicThread

DIAGNOSTICS_PERIOD = 0.5        # s between /diagnostics messages when nothing changes
CONFIGURE_TIMEOUT = 1.0         # s configure waits for every motor's first answer


class MotorDriverNode(ManagedHardwareNode):
    """``defaults``: ``rig.motors`` values (dotted, relative to it) laid over rig.yaml beneath the
    node's own parameters (the emulated rig's motors). Created unconfigured: the bus opens at
    ``configure``."""

    def __init__(self, config_dir: str | None = None, defaults: dict | None = None, **node_options):
        super().__init__("motor_driver", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        self.names = tuple(t.name for t in params.arm.tendons)
        values = params.section(NAMESPACE, SCHEMA, "rig.yaml", defaults)
        try:
            self.config = c = parse_driver_config(values, len(self.names))
        except ConfigError as exc:
            raise ConfigError(f"{os.path.join(params.config_dir, 'rig.yaml')}: {exc}") from None
        self.check_config(c)
        self.driver: MotorDriver | None = None
        self._cycle: PeriodicThread | None = None
        self.failure: BaseException | None = None     # the cycle's end, or stop frames refused
        self.done = False                             # run_node ends the spin when set
        self.incomplete_cycles = self.malformed_commands = 0
        self.latency = CommandLatency()
        self.activated_at = self.first_command_after = None    # monotonic [s]; activate -> command [s]
        self._status, self._last_diagnostics = None, -float("inf")
        self._publish_time = 0.0        # [s] the previous tick's publishing, for the driver's watchdog
        self._lock_holder = ""          # what held the hardware lock while the cycle waited for it
        self._wait_said = False         # the cycle's present wait for the lock logged
        self._release_pending = False   # a release that found the cycle stuck, for the cycle to do
        self.lock_waits = 0             # waits of the cycle for the lock past watchdog_timeout
        self.lock_dropped_commands = 0  # commands whose callback found the lock held past its bound
        self.state_pub = self.create_publisher(JointState, TOPICS["state"], QOS["tendon/state"])
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.command_sub = self.create_subscription(JointState, TOPICS["command"], self.on_command,
                                                    QOS["tendon/command"])
        self.source = CommandSource(c.command_publisher, self._command_publishers)
        self.create_service(Trigger, "~/estop", self.on_estop)
        self.create_service(Trigger, "~/zero", self.on_zero)
        load, worst = bus_load(c)
        if worst > 0.8:
            self.get_logger().warning(f"the motors take {load:.0%} of the bus ({worst:.0%} with worst-case "
                                      f"bit stuffing) at {c.rate:g} Hz: lower rig.motors.rate")
        self.get_logger().info(f"motor driver unconfigured: {len(c.motors)} motors on {c.interface} "
                               f"{c.channel} at {c.rate:g} Hz (configure opens the bus)")

    def check_config(self, config):
        """Further checks of the validated configuration before the bus is opened (ConfigError)."""

    # -- lifecycle -------------------------------------------------------------------------------
    @transition
    def on_configure(self, state):
        c = self.config
        try:
            driver = MotorDriver(c)
        except (can.CanError, OSError) as exc:
            return self.refuse("configure", f"cannot open {c.interface} channel {c.channel!r}: {exc}")
        silent = self._check_motors(driver)
        if silent:
            driver.close()
            return self.refuse("configure", f"motors {silent} did not answer within "
                                            f"{CONFIGURE_TIMEOUT:g} s on {c.interface} {c.channel}")
        if driver.fault is not None:
            driver.close()
            return self.refuse("configure", driver.fault)
        self.driver = driver
        self._lock_holder, self._wait_said, self._release_pending = "", False, False
        self._cycle = PeriodicThread(1.0 / c.rate, self.tick, lock=self.hardware_lock,
                                     on_wait=self._waiting_for_lock,
                                     on_error=self._cycle_failed, name="motor_driver cycle").start()
        self.get_logger().info(f"motor driver configured: {len(c.motors)} motors answer on "
                               f"{c.interface} {c.channel}, out of motor mode (activate to drive them)")
        return SUCCESS

    def _check_motors(self, driver: MotorDriver) -> list:
        """Probe ``driver``'s motors at its rate until every one has answered, for at most
        CONFIGURE_TIMEOUT; the CAN ids of those that did not."""
        period = 1.0 / self.config.rate
        deadline = time.monotonic() + CONFIGURE_TIMEOUT
        answered = np.zeros(len(self.config.motors), dtype=bool)
        while not answered.all() and time.monotonic() < deadline:
            answered |= driver.probe()
            time.sleep(period)
        return [m.can_id for m, ok in zip(self.config.motors, answered) if not ok]

    @transition
    def on_activate(self, state):
        verdict = self.source.update(self.command_sub.get_publisher_count(), time.monotonic(), fresh=True)
        if verdict.status == "foreign":
            return self.refuse("activate", f"{verdict.describe(self.source.expected)}: only "
                                           f"{self.source.expected} may command the motors")
        was = self.driver.fault
        self.driver.enable()
        self.activated_at, self.first_command_after = time.monotonic(), None
        self.get_logger().info("activated: motors in motor mode"
                               + (f" (cleared fault: {was})" if was else ""))
        self._report(self.driver.diagnostics(), force=True)
        return SUCCESS

    @transition
    def on_deactivate(self, state):
        unsent = self.driver.disable()
        self.activated_at = None
        fault = self.driver.fault
        if unsent:
            self._unsent("deactivate", unsent)
        else:
            self.get_logger().info("deactivated: zero torque, motors out of motor mode"
                                   + (f" (fault still latched: {fault})" if fault else ""))
        self._report(self.driver.diagnostics(), force=True)
        return SUCCESS

    def release(self):
        """Stop cycling; zero torque and exit motor mode on every motor; close the bus. A cycle
        stuck holding the hardware lock does that itself if it comes back (:meth:`tick`); meanwhile
        enabled motors hold their last torque until their own CAN timeout, and the node has failed
        (:meth:`_not_done`)."""
        try:
            with self.hardware_lock.held_by("the node's release"):   # the cycle thread is between cycles
                self._release()
        except LockTimeout as exc:
            self._release_pending = True
            self._not_done("the release", exc)

    def _release(self):
        cycle, self._cycle = self._cycle, None
        driver, self.driver = self.driver, None
        try:
            if cycle is not None:
                cycle.stop()
        finally:
            if driver is not None:
                unsent = driver.close()
                if unsent:
                    self._unsent("closing the bus", unsent)

    def _not_done(self, what: str, exc: LockTimeout):
        """``what`` could not take the hardware lock from a stuck cycle: with the motors enabled its
        zero torque was not sent (:meth:`_unsent`); otherwise their firmware holds no torque and it
        is said only."""
        if self.driver is not None and self.driver.mode == "enabled":
            self._unsent(what, [str(exc)])
        else:
            self.get_logger().error(f"{what} not done, the motors out of motor mode: {exc}")

    def _unsent(self, what: str, unsent: list):
        """Say that the zero-torque or exit-motor-mode frames of ``what`` did not all leave, or
        were not sent at all (``unsent``: the frames the bus refused, or why none was sent): the
        motors those frames were for hold their last torque until their own CAN timeout. The node
        has failed its one safety duty whatever a later stop sends: its process exits with status 1
        when it is stopped (:attr:`failure`), so that a run it served is no result."""
        self.failure = self.failure or RuntimeError(f"{what}: zero torque not sent: {'; '.join(unsent)}")
        self.get_logger().fatal(f"{what}: zero torque not sent ({'; '.join(unsent)}): those motors may "
                                "hold their last torque until their own CAN timeout; cut their power "
                                "if they do")

    def _cycle_failed(self, exc: BaseException):
        """The cycle thread raised: zero torque, out of motor mode, the node's process ends (status 1)."""
        self.failure, self.done = exc, True
        self.get_logger().fatal("the driver's cycle failed, motors at zero torque, the node ends: "
                                + "".join(traceback.format_exception(exc)))
        try:
            with self.hardware_lock.held_by("the e-stop after the cycle failed"):
                unsent = self.driver.estop() if self.driver is not None else []
        except LockTimeout as exc:
            unsent = [str(exc)]
        if unsent:
            self._unsent("e-stop after the cycle failed", unsent)

    def on_command(self, msg: JointState):
        received = time.monotonic()
        try:
            with self.hardware_lock.held_by("a command's callback"):
                self._on_command(msg, received)
        except LockTimeout as exc:                 # the cycle's watchdog faults on the gap meanwhile
            self.lock_dropped_commands += 1
            self.get_logger().error(f"command dropped: {exc}", throttle_duration_sec=1.0)

    def _on_command(self, msg: JointState, received: float):
        if self.driver is None:
            return
        stamp = stamp_to_seconds(msg.header.stamp)
        verdict = self.source.update(self.command_sub.get_publisher_count(), received)
        if not verdict.accepts:
            self.source.refused += 1
            if verdict.status == "foreign" and self.driver.mode == "enabled":
                self.driver.trip(f"foreign publisher: {verdict.describe(self.source.expected)}")
            self.get_logger().warning(f"command refused: {verdict.describe(self.source.expected)}",
                                      throttle_duration_sec=1.0)
            return
        self.latency.answered(stamp, received)
        if self.activated_at is not None and self.first_command_after is None:
            self.first_command_after = received - self.activated_at
        try:
            tensions = ordered(msg, "effort", self.names)
        except ValueError as exc:
            self.malformed_commands += 1
            self.get_logger().warning(f"command ignored: {exc}", throttle_duration_sec=1.0)
            return
        try:
            self.driver.command(tensions, stamp)
        except ValueError as exc:
            self.get_logger().warning(f"command rejected: {exc}", throttle_duration_sec=1.0)

    def _command_publishers(self) -> list:
        """(namespace, node name) of every publisher the graph lists on ``tendon/command``."""
        return [(info.node_namespace, info.node_name)
                for info in self.get_publishers_info_by_topic(self.command_sub.topic_name)]

    def tick(self, now: float):
        """One driver cycle, from the cycle thread at ``now`` [s, monotonic], holding the hardware
        lock; the driver reads its own clock (the same monotonic clock). What follows the cycle
        (publishing, logging, a deactivation) is timed for the next cycle's watchdog to name."""
        if self._release_pending:              # a release that found the cycle stuck: done here
            self._release()
            return
        wait = self._cycle.lock_wait
        if wait >= self.config.watchdog_timeout and not self._wait_said:
            self._say_wait(wait)                   # it passed the bound within the last slice
        holder = self._lock_holder
        self._lock_holder, self._wait_said = "", False
        state, diagnostics = self.driver.cycle((
            (self._publish_time, "in the node's publishing after the previous cycle"),
            (wait, f"waiting for the hardware lock, held by {holder or 'a holder not seen'}")))
        published = time.monotonic()
        if state.complete:
            self.state_pub.publish(joint_state(self.names, state.stamp, position=state.shortening,
                                               velocity=state.rate, effort=state.tension))
            self.latency.published(state.stamp, time.monotonic())
        else:
            self.incomplete_cycles += 1
        self._report(diagnostics)
        if diagnostics.fault is not None and self.lifecycle_state == "active":
            self.trigger_deactivate()          # zero torque already; the node says it drives nothing
        self._publish_time = time.monotonic() - published

    def _waiting_for_lock(self, waited: float):
        """From the cycle thread, after each period it waited in vain for the hardware lock
        (``waited`` [s] so far): the holder is kept for the watchdog's fault, and a wait past
        ``watchdog_timeout`` is logged at once (the motors are unwatched until the lock is free,
        their firmware's CAN timeout the guard meanwhile), not only when the cycle runs again."""
        holder = self.hardware_lock.holder()
        if holder is not None and not self._wait_said:    # the holder at the bound is the one named
            self._lock_holder = f"{holder[0]} (for {time.monotonic() - holder[1]:.3f} s)"
        if waited >= self.config.watchdog_timeout and not self._wait_said:
            self._say_wait(waited)

    def _say_wait(self, waited: float):
        """Log and count the cycle's wait for the lock past ``watchdog_timeout``, once per wait."""
        self._wait_said = True
        self.lock_waits += 1
        self.get_logger().error(
            f"the driver's cycle has waited {waited:.3f} s for the hardware lock, held by "
            f"{self._lock_holder or 'a holder not seen'}: the motors are unwatched until it is free "
            "(their firmware's CAN timeout is the guard)")

    def _report(self, diagnostics: Diagnostics, force: bool = False):
        """Publish /diagnostics if forced, on a change of mode or fault, or every DIAGNOSTICS_PERIOD."""
        status, now = (diagnostics.mode, diagnostics.fault), time.monotonic()
        if status != self._status and diagnostics.fault is not None:
            self.get_logger().error(f"fault, all motors at zero torque: {diagnostics.fault}")
        if force or status != self._status or now - self._last_diagnostics >= DIAGNOSTICS_PERIOD:
            self._status, self._last_diagnostics = status, now
            self.diagnostics_pub.publish(self.diagnostic_array(diagnostics))

    def diagnostic_array(self, diag: Diagnostics) -> DiagnosticArray:
        out = DiagnosticArray()
        out.header.stamp = self.get_clock().now().to_msg()
        bus = f"{self.config.interface}:{self.config.channel}"
        driver = DiagnosticStatus(name="motor_driver", hardware_id=bus)
        driver.level = DiagnosticStatus.ERROR if diag.fault else DiagnosticStatus.OK
        driver.message = f"fault: {diag.fault}" if diag.fault else diag.mode
        if not diag.fault and diag.clipped_commands:      # the controller pulls past the driver's clip
            driver.level = DiagnosticStatus.WARN
            driver.message += (f": {diag.clipped_commands} commands above rig.motors.max_tension "
                               f"{self.config.max_tension:g} N clipped to it (control.tension_max above it?)")
        driver.values = _values(mode=diag.mode, fault=diag.fault or "", command_age=diag.command_age,
                                stale_commands=diag.stale_commands, rejected_commands=diag.rejected_commands,
                                malformed_commands=self.malformed_commands,
                                foreign_frames=diag.foreign_frames, error_frames=diag.error_frames,
                                unstamped_frames=diag.unstamped_frames,
                                clipped_commands=diag.clipped_commands,
                                late_cycles=diag.late_cycles, incomplete_cycles=self.incomplete_cycles,
                                lock_waits=self.lock_waits, lock_dropped_commands=self.lock_dropped_commands,
                                cycles=diag.cycles, zeroed=diag.zeroed, lifecycle_state=self.lifecycle_state,
                                command_source=self.source.verdict.status,
                                command_publishers=" ".join(self.source.verdict.publishers),
                                refused_commands=self.source.refused,
                                activate_to_first_command_ms="" if self.first_command_after is None
                                else self.first_command_after * 1e3)
        timing = self.driver.cycle_statistics()
        driver.values += _values(period_p50_ms=timing.period_p50 * 1e3, period_p99_ms=timing.period_p99 * 1e3,
                                 period_max_ms=timing.period_max * 1e3,
                                 period_error_p99_ms=timing.period_error_p99 * 1e3,
                                 deadline_misses=timing.deadline_misses, timed_cycles=timing.cycles)
        latency = self.latency.statistics()
        driver.values += _values(state_to_command_p50_ms=latency.p50 * 1e3,
                                 state_to_command_p99_ms=latency.p99 * 1e3,
                                 state_to_command_max_ms=latency.max * 1e3, answered_states=latency.answers,
                                 unmatched_commands=latency.unmatched,
                                 state_to_command_run_p99_ms=latency.run_p99 * 1e3,
                                 state_to_command_run_max_ms=latency.run_max * 1e3,
                                 answered_states_run=latency.run_answers)
        out.status.append(driver)
        for name, motor, m in zip(self.names, self.config.motors, diag.motors):
            s = DiagnosticStatus(name=f"motor_driver: {name}", hardware_id=f"{bus}:{m.can_id}")
            problem = m.reply_age > self.config.reply_timeout or bool(m.error) or (
                m.temperature is not None and m.temperature > self.config.max_temperature)
            s.level = DiagnosticStatus.ERROR if problem else DiagnosticStatus.OK
            s.message = m.error_text if m.error else (
                f"silent for {m.reply_age:.3f} s" if m.reply_age > self.config.reply_timeout else "ok")
            s.values = _values(can_id=m.can_id, temperature="" if m.temperature is None else m.temperature,
                               error="" if m.error is None else m.error, error_text=m.error_text or "",
                               reply_age=m.reply_age, replies=m.replies, model=motor.model,
                               velocity_ratio=m.velocity_ratio)
            out.status.append(s)
        return out

    def on_estop(self, request, response):
        try:
            with self.hardware_lock.held_by("the estop service"):
                return self._estop(response)
        except LockTimeout as exc:      # the stuck cycle, once back, trips its watchdog (at most 1 s,
            #                             rig.yaml's bound, not above HOLD_WAIT): zero torque then
            response.success = False
            response.message = (f"e-stop not sent: {exc}; enabled motors hold their last torque until "
                                "their own CAN timeout: cut their power if they pull")
            self._not_done("e-stop", exc)
            return response

    def _estop(self, response):
        response.success = True
        if self.driver is None:
            response.message = f"e-stop: nothing to stop, the node is {self.lifecycle_state} (no bus open)"
            self.get_logger().warning(response.message)
            return response
        was = self.driver.fault
        unsent = self.driver.estop()
        if unsent:
            response.success = False
            response.message = (f"e-stop latched, but frames did not leave the bus ({'; '.join(unsent)}): "
                                "those motors may hold their last torque; cut their power")
            self._unsent("e-stop", unsent)
        else:
            response.message = "e-stop: zero torque, motors out of motor mode; activate to resume" + (
                f" (already in fault: {was})" if was else "")
            self.get_logger().warning(response.message)
        self._report(self.driver.diagnostics(), force=True)
        if self.lifecycle_state == "active":
            self.trigger_deactivate()
        return response

    def on_zero(self, request, response):
        try:
            with self.hardware_lock.held_by("the zero service"):
                return self._zero(response)
        except LockTimeout as exc:
            response.success, response.message = False, f"zero not set: {exc}"
            self.get_logger().error(response.message)
            return response

    def _zero(self, response):
        state = self.lifecycle_state
        if state != "inactive":
            response.success = False
            response.message = (f"zeroing needs the motors configured and slack: the node is {state} "
                                f"({'deactivate' if state == 'active' else 'configure'} first)")
            return response
        unsent = self.driver.zero()
        if unsent:
            response.success = False
            response.message = (f"zero not set: the frames to {', '.join(unsent)} did not leave; those "
                                "motors keep their old zero (call zero again once the bus is back)")
            self.get_logger().error(response.message)
            return response
        response.success, response.message = True, "zero set on every motor at the current angle"
        self.get_logger().info(response.message)
        return response


def _values(**items) -> list:
    return [KeyValue(key=k, value=f"{v:.6g}" if isinstance(v, float) else str(v)) for k, v in items.items()]


def main(args=None) -> int:
    return run_node(MotorDriverNode, "motor_driver", args)


if __name__ == "__main__":
    sys.exit(main())
