"""The motor_driver node on real rclpy: in-process with the CAN emulator (and the arm behind it) on a
python-can ``virtual`` bus served in real time; its lifecycle transitions, services, topics and
diagnostics; rig.yaml through ROS's own parameter parser; a bad parameter; SIGTERM takes the motors
out of motor mode."""
import itertools
import os
import re
import signal
import subprocess
import sys
import threading
import time

import can
import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from lifecycle_msgs.srv import ChangeState
from std_srvs.srv import Trigger

from conftest import change_state, killed_on_exit, spin_until, stop
from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_drivers.can.motor_driver_node import MotorDriverNode, main
from soft_arm_drivers.sim.can_emulator import CanMotorEmulator, EmulatorThread
from soft_arm_model.parameters import ConfigError, default_config_dir
from soft_arm_ros import hardware_lock
from soft_arm_ros.contract import QOS
from soft_arm_ros.conversions import joint_state, ordered, stamp_to_seconds

NAMES = ["tendon_1", "tendon_2", "tendon_3", "tendon_4"]
RIG_YAML = os.path.join(default_config_dir(), "rig.yaml")
_CHANNELS = itertools.count()


def channel():
    return f"motor_driver_node_{os.getpid()}_{next(_CHANNELS)}"


def rig_parameters(name, **values):
    """Node parameters: the virtual bus ``name``, relaxed timeouts for a loaded test machine, the
    harness as the node that commands the motors."""
    values = {"interface": "virtual", "channel": name, "watchdog_timeout": 0.2, "reply_timeout": 0.2,
              "command_publisher": "/harness", **values}
    return [Parameter(f"rig.motors.{k}", value=v) for k, v in values.items()]


class Harness:
    """The other side of the node: answers every tendon/state with a command (like the inner loop)
    while ``tension`` is set, records states and diagnostics, calls the services of the driver
    node ``driver``."""

    def __init__(self, context, driver="motor_driver"):
        self.node = rclpy.create_node("harness", context=context)
        self.states, self.diagnostics, self.tension = [], [], None
        self.pub = self.node.create_publisher(JointState, "tendon/command", QOS["tendon/command"])
        self.node.create_subscription(JointState, "tendon/state", self.on_state, QOS["tendon/state"])
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.clients = {"change_state": self.node.create_client(ChangeState, f"/{driver}/change_state"),
                        "estop": self.node.create_client(Trigger, f"/{driver}/estop"),
                        "zero": self.node.create_client(Trigger, f"/{driver}/zero")}

    def on_state(self, msg):
        self.states.append(msg)
        if self.tension is not None:
            self.pub.publish(joint_state(NAMES, stamp_to_seconds(msg.header.stamp), effort=self.tension))

    def latest(self, field):
        return ordered(self.states[-1], field, NAMES)

    def driver_status(self):
        return self.diagnostics[-1].status[0] if self.diagnostics else None


def values(harness):
    """The driver status's values of the latest /diagnostics, by key."""
    return {v.key: v.value for v in harness.driver_status().values}


def change(executor, harness, label) -> bool:
    """The driver's lifecycle transition ``label``; whether it succeeded."""
    return change_state(executor, harness.clients["change_state"], label)


def call(executor, harness, service, **fields):
    client = harness.clients[service]
    spin_until(executor, client.service_is_ready)
    request = client.srv_type.Request(**fields)
    future = client.call_async(request)
    spin_until(executor, future.done)
    return future.result()


class SpringTendons:
    """A stand-in for the arm behind the emulated motors: each tendon a mass on a spring (the
    plant interface of :class:`~soft_arm_drivers.sim.simulated_rig.Plant`, in plain Python). The
    node's tests run the emulator in a thread of their own process, in real time: the arm's model
    there, which releases the interpreter lock at every kernel call, fell 0.2-0.8 s behind the clock
    beside the executor's thread (0.8 ms of CPU per 1 ms step, 0.2 ms alone) and stopped answering
    frames. The arm behind real motors is tested across processes (test_emulated_hardware)."""

    def __init__(self, n=4, mass=0.6, stiffness=100.0, damping=20.0, dt=1e-3):
        self.m, self.k, self.c, self.dt = mass, stiffness, damping, dt
        self.s, self.sd = np.zeros(n), np.zeros(n)
        self.stepper = type("Stepper", (), {"dt": dt})()
        self.peak = 0.0           # N: the largest tension any step applied since the last reset

    def reset_peak(self):
        self.peak = 0.0

    @property
    def q(self):
        return self.s.copy()

    def sense(self):
        pass

    def step(self, tensions):
        """Semi-implicit Euler: tension [N] shortens the tendon against the spring [m]."""
        self.peak = max(self.peak, float(np.max(tensions)))
        self.sd += self.dt * (np.asarray(tensions) - self.k * self.s - self.c * self.sd) / self.m
        self.s += self.dt * self.sd

    def tendons(self):
        return self.s.copy(), self.sd.copy()


@pytest.fixture
def rig(context):
    """Emulator with spring tendons, served in real time; the node and the harness on one executor."""
    yield from _rig(context)


def _rig(context, *parameters):
    """The ``rig`` fixture's (executor, node, harness, emulator), the node with more ``parameters``."""
    name = channel()
    cfg = load_driver_config(overrides={"interface": "virtual", "channel": name})
    bus = can.Bus(interface="virtual", channel=name, preserve_timestamps=True)
    emulator = CanMotorEmulator.for_config(cfg, bus, SpringTendons(), reply_delay=2e-4,
                                           start_time=time.time())
    server = EmulatorThread(emulator).start()
    node = MotorDriverNode(context=context, parameter_overrides=rig_parameters(name) + list(parameters))
    harness = Harness(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(harness.node)
    try:
        yield executor, node, harness, emulator
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        harness.node.destroy_node()
        server.stop()
        bus.shutdown()


def test_the_cycle_keeps_the_steady_clock_when_the_graph_runs_on_simulated_time(context):
    """With ``use_sim_time`` and no /clock (a bag replayed, a simulator stopped), ROS time stands
    still: a cycle timed by it would never run and the motors would go unwatched. The driver's
    cycle follows the steady clock."""
    rig = _rig(context, Parameter("use_sim_time", value=True))
    executor, node, harness, _ = next(rig)
    try:
        assert node.get_clock().ros_time_is_active
        assert change(executor, harness, "configure")
        spin_until(executor, lambda: len(harness.states) >= 50, timeout=5.0)
    finally:
        rig.close()


def test_the_cycle_runs_apart_from_the_executor(rig):
    """The cycle is a thread of the driver's own: the motors are polled, and the watchdog watches,
    while no executor spins the node (a callback that blocks, an executor that posts a timer late)."""
    _, node, _, _ = rig
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    before = node.driver.cycles
    time.sleep(0.3)                                                        # 150 periods at 500 Hz
    assert node.driver.cycles - before > 50
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    deadline = time.monotonic() + 5.0
    while node.lifecycle_state in ("active", "deactivating"):              # nobody commands
        assert time.monotonic() < deadline, "the watchdog did not trip without an executor"
        time.sleep(0.01)
    assert node.driver.fault.startswith("stale command") and node.lifecycle_state == "inactive"


def _bus_down(node, down: bool = True):
    """Every send on the node's bus raises "Network is down" (``down``), or sends again; under the
    hardware lock, which the driver's cycle thread holds for its sends."""
    with node.hardware_lock.held_by("the test"):
        if not down:
            del node.driver.bus.send            # the bus's own method again
            return

        def refused(*args, **kwargs):
            raise can.CanError("Network is down")
        node.driver.bus.send = refused


def test_an_estop_whose_frames_do_not_leave_answers_failure_and_the_node_exits_failed(rig):
    """The bus goes down while the motors are enabled: the cycle's sends fail (a fault), and the
    e-stop service says that its frames did not leave (success false, the motors named) where it
    answered success, and the node has failed from then on (exit status 1)."""
    _, node, _, _ = rig
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    _bus_down(node)
    answer = node.on_estop(Trigger.Request(), Trigger.Response())
    assert not answer.success and "did not leave the bus" in answer.message
    assert "motor 1: Network is down" in answer.message
    # failed by the e-stop, or before it by the deactivation the cycle's failed sends started
    failure = node.failure
    assert isinstance(failure, RuntimeError) and "zero torque not sent" in str(failure), failure
    node.close()
    assert node.failure is failure                                          # the first failure kept


def test_a_zero_whose_frames_do_not_leave_answers_failure_naming_the_motors(rig):
    """The bus refuses the zeroing frames: the zero service answers failure naming the motors that
    keep their old zero (an activate would clear the fault the refusal latched, so a success here
    would leave the arm driven from a stale zero); the bus back, zero succeeds."""
    _, node, _, _ = rig
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    _bus_down(node)
    answer = node.on_zero(Trigger.Request(), Trigger.Response())
    assert not answer.success and answer.message.startswith("zero not set"), answer.message
    assert "motor 1: Network is down" in answer.message and not node.driver.zeroed
    _bus_down(node, down=False)
    answer = node.on_zero(Trigger.Request(), Trigger.Response())
    assert answer.success and node.driver.zeroed, answer.message


def test_a_deactivation_whose_frames_do_not_leave_fails_the_node_though_the_close_succeeds(rig):
    """The bus refuses the deactivation's frames, then comes back: the motors held their torque
    meanwhile (until their own timeout), so the node has failed (exit status 1) though its closing
    frames leave; a clean deactivation leaves it unfailed."""
    _, node, _, _ = rig
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS and node.failure is None
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    with node.hardware_lock.held_by("the test"):          # no cycle between: the lock is re-entrant
        _bus_down(node)
        node.trigger_deactivate()
        _bus_down(node, down=False)
    assert isinstance(node.failure, RuntimeError), node.failure
    assert "deactivate: zero torque not sent" in str(node.failure) and "motor 1" in str(node.failure)
    node.close()
    assert "deactivate: zero torque not sent" in str(node.failure)


def test_node_drives_the_emulated_rig_through_its_lifecycle_topics_and_services(rig):
    executor, node, harness, emulator = rig
    # unconfigured: no bus, no state; what needs a configured driver is refused
    assert node.lifecycle_state == "unconfigured" and node.driver is None
    assert not change(executor, harness, "activate") and node.lifecycle_state == "unconfigured"
    refused = call(executor, harness, "zero")
    assert not refused.success and "configure first" in refused.message
    executor.spin_once(timeout_sec=0.2)
    assert not harness.states

    # configure: the bus opens, every motor answered; inactive: polled, the state flows, stamped
    # with the replies' (wall) time
    assert change(executor, harness, "configure") and node.lifecycle_state == "inactive"
    spin_until(executor, lambda: len(harness.states) >= 20 and harness.driver_status() is not None)
    state = harness.states[-1]
    assert list(state.name) == NAMES
    assert abs(stamp_to_seconds(state.header.stamp) - time.time()) < 0.5
    assert harness.driver_status().message == "disabled"
    assert values(harness)["lifecycle_state"] == "inactive"
    assert not any(m.motor_mode for m in emulator.motors)

    assert call(executor, harness, "zero").success
    # from then on the shortenings count from the zeroing pose's (rig.yaml's zero_shortening)
    spin_until(executor, lambda: np.allclose(harness.latest("position"), node.config.zero_shortening,
                                             atol=1e-5))

    # the harness answers states before the activation, as the inner loop does: the watchdog
    # counts from the activation, and the service's answer can take longer than its timeout
    harness.tension = [2.5, 0.0, 0.0, 0.0]
    assert change(executor, harness, "activate") and node.lifecycle_state == "active"
    start = len(harness.states)
    spin_until(executor, lambda: len(harness.states) > start + 150)          # 0.3 s at 500 Hz
    assert all(m.motor_mode for m in emulator.motors), node.driver.fault
    # the harness answers each state at once: the driver times each answer from its state, and
    # the first command from the activation
    spin_until(executor, lambda: int(values(harness)["answered_states"]) > 100)
    latency = values(harness)
    assert 0.0 < float(latency["state_to_command_p50_ms"]) <= float(latency["state_to_command_p99_ms"]) \
        <= float(latency["state_to_command_max_ms"]) < 200.0
    assert int(latency["answered_states_run"]) >= int(latency["answered_states"])         # since the start
    assert float(latency["state_to_command_p50_ms"]) <= float(latency["state_to_command_run_p99_ms"]) \
        <= float(latency["state_to_command_run_max_ms"]) < 200.0
    assert 0.0 < float(latency["activate_to_first_command_ms"]) < 1000.0
    assert emulator.tensions[0] == pytest.approx(2.5, abs=0.45)             # one torque step: 0.88 N
    assert harness.latest("effort")[0] == pytest.approx(2.5, abs=0.9)
    assert harness.latest("position")[0] > 5e-3                              # tendon 1 shortened
    # sensor stamps, one per cycle: strictly increasing, near the 2 ms period (this process also
    # runs the harness, the emulated motors and rclpy's Python executor: a late tick stretches one
    # period, and the timer's fixed grid shortens the next; on a 2-core machine the median is
    # 2-6 ms: the driver's own timing is measured, alone, by bench_motor_driver)
    periods = np.diff([stamp_to_seconds(m.header.stamp) for m in harness.states[start:]])
    assert np.all(periods > 0) and 0.0015 < np.median(periods) < 0.01

    refused = call(executor, harness, "zero")
    assert not refused.success and "deactivate first" in refused.message

    # e-stop: zero torque, out of motor mode, and the node drops to inactive by itself
    assert call(executor, harness, "estop").success
    assert node.lifecycle_state == "inactive"
    spin_until(executor, lambda: harness.driver_status().level == DiagnosticStatus.ERROR)
    assert harness.driver_status().message == "fault: e-stop"
    spin_until(executor, lambda: not any(m.motor_mode for m in emulator.motors))
    assert all(emulator.torque(i) == 0.0 for i in range(4))
    per_motor = harness.diagnostics[-1].status[1:]
    assert [s.name for s in per_motor] == [f"motor_driver: {n}" for n in NAMES]
    assert {v.key: v.value for v in per_motor[0].values}["temperature"] == "30"

    # activate clears the fault
    assert change(executor, harness, "activate")
    spin_until(executor, lambda: harness.driver_status().message == "enabled")
    spin_until(executor, lambda: emulator.tensions[0] > 2.0)

    # the controller stops: the watchdog latches, zero torque, and the node deactivates itself
    harness.tension = None
    spin_until(executor, lambda: node.lifecycle_state == "inactive")
    spin_until(executor, lambda: harness.driver_status().level == DiagnosticStatus.ERROR)
    assert harness.driver_status().message.startswith("fault: stale command"), harness.driver_status().message
    spin_until(executor, lambda: emulator.tensions.max() < 0.45)          # the next plant step
    spin_until(executor, lambda: not any(m.motor_mode for m in emulator.motors))
    assert not change(executor, harness, "deactivate")                     # it is inactive already

    # cleanup: zero torque, out of motor mode, the bus closed, no more state
    assert change(executor, harness, "cleanup") and node.driver is None
    count = len(harness.states)
    executor.spin_once(timeout_sec=0.1)
    executor.spin_once(timeout_sec=0.1)
    assert len(harness.states) <= count + 1


def test_configure_fails_when_the_motors_do_not_answer(context):
    """Nothing on the bus: configure is refused with the silent motors named, the node stays
    unconfigured, and a configure once the motors are there succeeds."""
    name = channel()
    node = MotorDriverNode(context=context, parameter_overrides=rig_parameters(name))
    try:
        assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert node.lifecycle_state == "unconfigured" and node.driver is None
        cfg = load_driver_config(overrides={"interface": "virtual", "channel": name})
        bus = can.Bus(interface="virtual", channel=name, preserve_timestamps=True)
        emulator = CanMotorEmulator.for_config(cfg, bus, start_time=time.time())
        with EmulatorThread(emulator):
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert node.lifecycle_state == "inactive"
            node.trigger_cleanup()
        bus.shutdown()
    finally:
        node.close()
        node.destroy_node()


def test_commands_above_the_drivers_limit_are_clipped_and_said_on_diagnostics(rig):
    """A command above rig.motors.max_tension (an inner loop whose control.tension_max is set above
    it) is applied clipped, and /diagnostics say so with a warning and the count."""
    _, node, _, _ = rig
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    node.driver.command([node.config.max_tension + 3.0, 0.0, 0.0, 0.0])
    status = node.diagnostic_array(node.driver.diagnostics()).status[0]
    values = {v.key: v.value for v in status.values}
    assert status.level == DiagnosticStatus.WARN and values["clipped_commands"] == "1"
    assert "clipped" in status.message and "rig.motors.max_tension" in status.message, status.message


def test_malformed_commands_are_rejected_by_the_node(rig):
    executor, node, harness, emulator = rig
    assert change(executor, harness, "configure") and change(executor, harness, "activate")
    spin_until(executor, lambda: harness.pub.get_subscription_count() > 0)

    def send_until_counted(msg, count):
        deadline = time.monotonic() + 10.0
        while count() == 0:                          # best effort, depth 1: repeat until one lands
            assert time.monotonic() < deadline, "the command never reached the node"
            harness.pub.publish(msg)
            spin_until(executor, lambda: True)
    send_until_counted(joint_state(["tendon_1"], 0.0, effort=[1.0]), lambda: node.malformed_commands)
    send_until_counted(joint_state(NAMES, 0.0, effort=[1.0, float("nan"), 1.0, 1.0]),
                       lambda: node.driver.rejected_commands)
    spin_until(executor, lambda: harness.driver_status().message.startswith("fault: stale command"))
    values = {v.key: v.value for v in harness.driver_status().values}
    assert int(values["malformed_commands"]) >= 1 and int(values["rejected_commands"]) >= 1
    assert emulator.tensions.max() < 0.45                     # nothing but zero torque was applied


def test_diagnostics_report_a_delayed_cycle_as_a_deadline_miss(rig):
    """One driver cycle held for 25 ms (12 periods at 500 Hz): the driver's /diagnostics count a
    deadline miss and show the long period."""
    executor, node, harness, emulator = rig
    assert change(executor, harness, "configure")

    def values():
        return {v.key: v.value for v in harness.driver_status().values}
    spin_until(executor, lambda: harness.driver_status() is not None and int(values()["timed_cycles"]) > 100)
    before = int(values()["deadline_misses"])
    cycle, held = node.driver.cycle, []

    def held_once(*args):
        if not held:
            held.append(time.monotonic())
            time.sleep(0.025)
        return cycle(*args)
    node.driver.cycle = held_once
    spin_until(executor, lambda: held and int(values()["deadline_misses"]) > before)
    assert float(values()["period_max_ms"]) >= 25.0
    assert 1.5 < float(values()["period_p50_ms"]) < 3.0


def _pulling(rig):
    """The rig's driver configured and activated, its first motor pulling 2 N for 50 states."""
    executor, node, harness, emulator = rig
    assert change(executor, harness, "configure")
    harness.tension = [2.0, 0.0, 0.0, 0.0]
    assert change(executor, harness, "activate") and node.lifecycle_state == "active"
    start = len(harness.states)
    spin_until(executor, lambda: len(harness.states) > start + 50)
    assert node.driver.fault is None
    return rig


def _held_fault(rig, where: str) -> tuple:
    """Wait for the rig's driver to fault and its motors to leave motor mode; the fault must be
    ``cycle held`` with a part ``where`` (a regular expression) named: (the hold, that part) [s]."""
    executor, node, _, emulator = rig
    spin_until(executor, lambda: node.driver.fault is not None)
    fault = re.fullmatch(r"cycle held: ([0-9.]+) s since the previous cycle, the motors unwatched "
                         r"\(watchdog_timeout 0.2 s\); ([0-9.]+) s of it " + where, node.driver.fault)
    assert fault is not None, node.driver.fault
    spin_until(executor, lambda: not any(m.motor_mode for m in emulator.motors))
    return float(fault.group(1)), float(fault.group(2))


def test_a_publish_that_holds_the_cycle_past_the_watchdog_is_named_in_the_fault(rig):
    """The state's publish held for 0.3 s while the motors pull (what the middleware does when it
    opens a new reader's shared-memory port: decision 0005): the next cycle trips the watchdog, and
    the fault says the hold was spent in the node's publishing."""
    _, node, _, _ = _pulling(rig)
    publish, held = node.state_pub.publish, []

    def held_once(msg):
        if not held:
            held.append(time.monotonic())
            time.sleep(0.3)
        publish(msg)
    node.state_pub.publish = held_once
    gap, publishing = _held_fault(rig, "in the node's publishing after the previous cycle")
    assert 0.3 <= publishing <= gap


def test_a_cycle_held_by_another_holder_of_the_hardware_lock_names_it(rig):
    """A service of the node held up for 0.3 s holding the hardware lock while the motors pull: the
    cycle says so while it waits (past watchdog_timeout: ``lock_waits``), and its fault, once it
    runs, says the hold was spent waiting for the lock and names what held it."""
    _, node, _, _ = _pulling(rig)
    assert node.lock_waits == 0
    with node.hardware_lock.held_by("a service held up"):
        time.sleep(0.3)
        deadline = time.monotonic() + 3.0
        while node.lock_waits == 0 and time.monotonic() < deadline:      # a loaded machine's cycle
            time.sleep(0.01)
        assert node.lock_waits == 1                                        # said while it lasts
    gap, waiting = _held_fault(rig, r"waiting for the hardware lock, held by a service held up "
                                    r"\(for [0-9.]+ s\)")
    assert 0.25 <= waiting <= gap
    values = {kv.key: kv.value for kv in node.diagnostic_array(node.driver.diagnostics()).status[0].values}
    assert values["lock_waits"] == "1"


def _stuck(node) -> threading.Event:
    """Make the node's cycle stick in the driver, holding the hardware lock, from its next call on;
    returns the event that lets it go on (set it)."""
    stuck, go = threading.Event(), threading.Event()
    cycle = node.driver.cycle

    def stuck_cycle(*args):
        stuck.set()
        go.wait(30.0)
        return cycle(*args)
    with node.hardware_lock.held_by("the test"):
        node.driver.cycle = stuck_cycle
    assert stuck.wait(5.0)
    return go


# the first wait runs out at the bound; the callbacks after it find the same hold and do not wait
WAITED = r"waited 0.1 s for the hardware lock, held by motor_driver cycle for [0-9.]+ s"
FOUND = (r"found the hardware lock held by motor_driver cycle for [0-9.]+ s, as when a wait for it ran "
         r"out \(not waited again\)")
HELD = f"(?:{WAITED}|{FOUND})"


def test_a_cycle_stuck_in_its_hardware_holds_no_callback_past_its_bound(rig, monkeypatch, capfd):
    """The cycle stuck in the driver holding the hardware lock (a bus call that never returns)
    while the motors pull: each callback waits HOLD_WAIT at most, then says what it could not do,
    naming the cycle, where it held the executor with it: a command dropped and counted, the zero
    refused, a deactivation failed with the node still active, the release failed (the motors are
    left to their own CAN timeout: the node has failed, exit status 1), the e-stop answered
    failure. The cycle, once back, does the release itself: the motors safe, the bus closed."""
    executor, node, harness, emulator = _pulling(rig)
    monkeypatch.setattr(hardware_lock, "HOLD_WAIT", 0.1)
    cycle = node._cycle
    go = _stuck(node)
    try:
        node.on_command(joint_state(node.names, time.time(), effort=[1.0, 0.0, 0.0, 0.0]))
        assert node.lock_dropped_commands == 1
        assert values_of(node)["lock_dropped_commands"] == "1"
        answer = node.on_zero(Trigger.Request(), Trigger.Response())
        assert not answer.success and re.fullmatch("zero not set: the zero service " + FOUND, answer.message)
        assert node.trigger_deactivate() == TransitionCallbackReturn.FAILURE
        assert not change(executor, harness, "deactivate")                  # the service's own wait
        assert node.lifecycle_state == "active" and node.failure is None
        capfd.readouterr()
        node.release()
        assert re.fullmatch("the release: zero torque not sent: the node's release " + HELD,
                            str(node.failure)), node.failure
        logged = capfd.readouterr().err                    # said as what it is: nothing was sent
        assert "the release: zero torque not sent (the node's release" in logged, logged
        failure = node.failure
        answer = node.on_estop(Trigger.Request(), Trigger.Response())
        assert not answer.success and re.match("e-stop not sent: the estop service " + HELD, answer.message)
        assert "cut their power" in answer.message and node.failure is failure      # the first kept
    finally:
        go.set()
    monkeypatch.undo()
    spin_until(executor, lambda: node.driver is None and not cycle.running)   # released by the cycle
    spin_until(executor, lambda: not any(m.motor_mode for m in emulator.motors))


def test_a_stuck_cycle_with_the_motors_out_of_motor_mode_fails_nothing(rig, monkeypatch):
    """The same stuck cycle while the node is inactive (the motors hold no torque): the e-stop says
    it was not done, naming the cycle; a shutdown fails its wait, and since rclpy finalizes the node
    whatever it returns, releases anyway: not done either, left to the cycle, which does it once
    back. The node has not failed."""
    executor, node, harness, _ = rig
    assert change(executor, harness, "configure")
    monkeypatch.setattr(hardware_lock, "HOLD_WAIT", 0.1)
    go = _stuck(node)
    try:
        answer = node.on_estop(Trigger.Request(), Trigger.Response())
        assert not answer.success and re.match("e-stop not sent: the estop service " + HELD, answer.message)
        assert node.trigger_shutdown() == TransitionCallbackReturn.FAILURE
        assert node.lifecycle_state == "finalized" and node.failure is None and node.driver is not None
    finally:
        go.set()
    monkeypatch.undo()
    spin_until(executor, lambda: node.driver is None)
    assert node.failure is None


def values_of(node) -> dict:
    """The driver status's values the node would publish now, by key."""
    return {kv.key: kv.value for kv in node.diagnostic_array(node.driver.diagnostics()).status[0].values}


def test_rig_yaml_parses_with_the_ros_parameter_parser():
    ctx = Context()
    rclpy.init(args=["x", "--ros-args", "--params-file", RIG_YAML], context=ctx)
    try:
        node = rclpy.create_node("motor_driver", context=ctx, allow_undeclared_parameters=True,
                                 automatically_declare_parameters_from_overrides=True)
        params = {k: p.value for k, p in node.get_parameters_by_prefix("rig.motors").items()}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    assert params["interface"] == "socketcan" and params["models"] == ["AK80-9"] * 4
    assert list(params["ids"]) == [1, 2, 3, 4] and params["rate"] == 500.0


def test_a_bad_parameter_raises_config_error_naming_it(context):
    with pytest.raises(ConfigError, match=r"rig.motors.max_tension = -2.0 is not valid: expected a tension "
                                          r"in \(0, 1000\] N"):
        MotorDriverNode(context=context,
                        parameter_overrides=rig_parameters(channel(), max_tension=-2.0))


def test_strings_stay_strings(context):
    """A channel YAML 1.1 would read as a boolean reaches python-can as the string it is."""
    cfg = load_driver_config(overrides={"interface": "virtual", "channel": '"yes"'})
    bus = can.Bus(interface="virtual", channel="yes", preserve_timestamps=True)
    node = MotorDriverNode(context=context, parameter_overrides=rig_parameters("yes"))
    try:
        assert node.config.channel == "yes"
        with EmulatorThread(CanMotorEmulator.for_config(cfg, bus, start_time=time.time())):
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert node.driver.bus.channel_id == "yes"
            node.close()
    finally:
        node.close()
        node.destroy_node()
        bus.shutdown()


def test_a_bad_parameter_exits_with_status_2():
    assert main(["motor_driver", "--ros-args", "--params-file", RIG_YAML,
                 "-p", "rig.motors.interface:=virtual", "-p", "rig.motors.directions:=[1, 2, 1, 1]"]) == 2


DRIVER_SCRIPT = """
import sys, threading, time
import can
from soft_arm_drivers.sim.can_emulator import CanMotorEmulator, EmulatorThread
from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_drivers.can.motor_driver_node import main

name = sys.argv[1]
cfg = load_driver_config(overrides={"interface": "virtual", "channel": name})
bus = can.Bus(interface="virtual", channel=name, preserve_timestamps=True)
emulator = CanMotorEmulator.for_config(cfg, bus, start_time=time.time())
done = threading.Event()
exec(sys.argv[2])

def watch():
    seen = None
    while not done.is_set():
        modes = [m.motor_mode for m in emulator.motors]
        if modes != seen:
            print("motor modes", modes, flush=True)
            seen = modes
        time.sleep(0.002)

watcher = threading.Thread(target=watch, daemon=True)
with EmulatorThread(emulator):
    watcher.start()
    try:
        # a node name of its own: the services of an earlier test's driver may linger in discovery
        status = main(["motor_driver", "--ros-args", "-r", "__node:=" + sys.argv[3],
                       "-p", "rig.motors.interface:=virtual",
                       "-p", "rig.motors.channel:=" + name, "-p", "rig.motors.watchdog_timeout:=1.0",
                       "-p", "rig.motors.reply_timeout:=0.2", "-p", "rig.motors.command_publisher:=/harness"])
    finally:                            # what the motors were left with, however main ended
        time.sleep(0.05)
        done.set()
        watcher.join()
        print("torques", [emulator.torque(i) for i in range(4)], flush=True)
bus.shutdown()
sys.exit(status)
"""


def _activated_driver_process(context, node_name: str, inject: str = "") -> subprocess.Popen:
    """A motor_driver (``node_name``) in a process of its own with emulated motors in it, after
    ``inject`` (Python run before the node starts), configured and activated through its
    change_state service; the process prints the motors' modes as they change and their torques
    at its end."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-c", DRIVER_SCRIPT, channel(), inject, node_name], env=env,
                            text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        harness = Harness(context, node_name)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(harness.node)
        # the process's start-up (imports, the compiled kernels' cache) may take seconds on a busy
        # machine: its services first
        spin_until(executor, harness.clients["change_state"].service_is_ready, timeout=60.0,
                   unless_ended=proc)
        # rclpy's change_state would raise out of the node's executor on a transition the state
        # does not have: the node refuses it and lives on
        assert not change(executor, harness, "activate")
        assert change(executor, harness, "configure") and change(executor, harness, "activate")
        executor.shutdown()
        harness.node.destroy_node()
    except BaseException:
        proc.kill()
        proc.communicate()
        raise
    return proc


def _motors_were_left_safe(out: str):
    # the node's log lines (stderr, merged) may fall inside one of the script's printed lines
    # (the print's space before the list too: "motor modes[INFO] ...\n [True, ...]")
    modes = re.findall(r"motor modes ?(?:\[(?:INFO|WARN|ERROR)\][^\n]*\n)* ?(\[(?:True|False)[^\]]*\])", out)
    assert modes[-2:] == ["[True, True, True, True]", "[False, False, False, False]"], out
    assert "torques [0.0, 0.0, 0.0, 0.0]" in out


def test_sigterm_takes_the_motors_out_of_motor_mode(context):
    proc = _activated_driver_process(context, "sigterm_driver")
    with killed_on_exit(proc):
        time.sleep(0.1)
        out = stop(proc, signal.SIGTERM, 20)
    # Known race in the shared run_node (soft_arm_ros/runtime.py): a signal landing between
    # its rclpy.ok() check and the executor's wait set lets rclpy's RCLError out (status 1) after the
    # node was closed. The motors must be safe either way; the status is 0 otherwise.
    assert proc.returncode == 0 or "the given context is not valid" in out, out
    _motors_were_left_safe(out)


FAILING_CYCLE = """
from soft_arm_drivers.can.motor_driver import MotorDriver
cycle, enabled_at = MotorDriver.cycle, []

def failing(self, *args):
    # raises 0.2 s after the enable, in whatever mode: a fault latched meanwhile (a loaded machine's
    # late reply) must not leave the injection waiting for an enabled cycle that never comes
    if self.mode == "enabled" and not enabled_at:
        enabled_at.append(self.clock())
    if enabled_at and self.clock() - enabled_at[0] > 0.2:
        raise RuntimeError("injected: the bus vanished")
    return cycle(self, *args)
MotorDriver.cycle = failing
"""


def test_a_cycle_that_raises_stops_the_motors_and_ends_the_process_with_status_1(context):
    """An exception in the cycle thread is not lost in the thread: the motors go to zero torque and
    out of motor mode, the reason is logged, and the node's process ends with status 1."""
    proc = _activated_driver_process(context, "failing_driver", FAILING_CYCLE)
    try:
        out, _ = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:           # what it did before it hung: the failure says
        proc.kill()
        raise AssertionError(f"the process did not end within 20 s:\n{proc.communicate()[0]}") from None
    assert proc.returncode == 1, out
    assert "the driver's cycle failed" in out and "injected: the bus vanished" in out
    _motors_were_left_safe(out)


def test_parameters_are_declared_read_only_with_their_ranges(rig):
    """The driver applies its configuration once, at start: every rig.motors value (the node's own
    overrides included) is declared read-only, described, with its schema's range; a set is refused."""
    executor, node, harness, emulator = rig
    watchdog = node.describe_parameter("rig.motors.watchdog_timeout")
    assert watchdog.read_only and watchdog.description == "expected a time in (0, 1] s"
    assert watchdog.floating_point_range[0].to_value == 1.0
    assert node.get_parameter("rig.motors.watchdog_timeout").value == 0.2          # the test's override
    assert node.describe_parameter("rig.motors.rate").floating_point_range[0].to_value == 2000.0
    assert node.describe_parameter("arm.tendons.names").read_only
    result = node.set_parameters([Parameter("rig.motors.watchdog_timeout", value=0.5)])[0]
    assert not result.successful and "read-only" in result.reason
    assert node.config.watchdog_timeout == 0.2


def test_a_stray_publisher_on_tendon_command_is_refused_named_and_latches_a_fault(rig, context):
    """Only the configured node commands the motors: a second node publishing 4.5 N while the
    motors are enabled (a second computer on the domain, a stray ``ros2 topic pub``) latches a
    fault named on /diagnostics, and its tensions never reach the motors."""
    executor, node, harness, emulator = rig
    assert change(executor, harness, "configure")
    harness.tension = [1.0, 1.0, 1.0, 1.0]
    assert change(executor, harness, "activate")
    spin_until(executor, lambda: values(harness)["command_source"] == "ok"
               and emulator.tensions.min() > 0.5)
    stray = rclpy.create_node("stray", context=context)
    publisher = stray.create_publisher(JointState, "tendon/command", QOS["tendon/command"])
    executor.add_node(stray)
    emulator.plant.reset_peak()            # every tension the motors apply, step by step: first
    end = time.monotonic() + 0.3           # the harness's 1 N alone,
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.005)
    alone = emulator.plant.peak
    emulator.plant.reset_peak()            # then with the stray
    try:
        def strayed():
            publisher.publish(joint_state(NAMES, time.time(), effort=[4.5] * 4))
            return node.driver.fault is not None
        spin_until(executor, strayed)
        assert node.driver.fault.startswith("foreign publisher") and "/stray" in node.driver.fault
        # the stray keeps publishing after the fault: none of its messages, those in flight at the
        # fault included, reaches the motors
        spin_until(executor, lambda: node.lifecycle_state == "inactive"
                   and values(harness)["command_source"] == "foreign")
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            publisher.publish(joint_state(NAMES, time.time(), effort=[4.5] * 4))
            executor.spin_once(timeout_sec=0.01)
        assert "/stray" in values(harness)["command_publishers"]
        assert harness.driver_status().level == DiagnosticStatus.ERROR
        assert emulator.plant.peak <= alone + 0.05, (emulator.plant.peak, alone)    # never the stray's 4.5 N
        # the emulated motors take the zero-torque frames from their own thread: within 0.5 s
        spin_until(executor, lambda: emulator.tensions.max() < 0.05, timeout=0.5)
        assert not change(executor, harness, "activate")                     # refused while it is there
    finally:
        executor.remove_node(stray)
        stray.destroy_node()
    # the stray gone, the expected publisher alone again: activation is possible
    count = node.command_sub.get_publisher_count
    spin_until(executor, lambda: node.source.update(count(), time.monotonic(), fresh=True).accepts)
    assert change(executor, harness, "activate") and node.driver.fault is None
