"""Hardware in the loop, emulated: the rig's graph (motor_driver on a CAN bus with the motor
emulator behind it, mocap_bridge reading the NatNet server emulator over UDP on 127.0.0.1,
inner_loop, clik, task_runner, recorder, each its own process) closes the loop like the
simulator-only graph; and the emulated rig's configuration."""
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
import rclpy
import yaml
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor

from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_experiments import realtime
from soft_arm_experiments.experiment import _ros_arguments, main, run_composed
from soft_arm_experiments.figures import read_series
from soft_arm_experiments.identify_cli import write_identified_arm
from soft_arm_experiments.orchestration import BRINGUP_TIMEOUT, GRAPH_SETTLE
from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_drivers.sim.emulated_rig import load_emulator_config, read_emulated_motors
from soft_arm_model import build_model, load_arm_config, marker_positions, solve_equilibrium, tendon_lengths
from soft_arm_ros.conversions import markers_of
from soft_arm_model.parameters import ConfigError, default_config_dir

from conftest import killed_on_exit, spin_until, stop, wait_for_output

WINDOW = 8.0                    # s, the one target's window
ONE_TARGET = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[1]",
              f"tasks.coiling.phase.upward.window={WINDOW}"]
# These tests check what the graph does, not how punctually the machine schedules it: the
# emulated rig is some ten processes in real time on two cores, and with the rig's own figures
# (500 Hz motors and inner loop, 240 Hz mocap and online CLIK, emulator.yaml's 50 ms watchdog) it
# needs about 1.7 cores of a two-core development machine and more than two of one half as fast
# (CI's may be either): there the real-time nodes take every core, the others starve (the recorder
# keeps a tenth of the states, the test's own DDS discovery takes more than 10 s) and one run in
# three or four ends on a 50 ms hiccup (a stale command, a silent motor); without real-time
# scheduling the emulated motors fall silent for 250 ms. Here the motors and the inner
# loop run at RATE [Hz], the mocap and the online CLIK at MOCAP_RATE [Hz], and the driver's watchdog
# and reply timeout are TIMEOUT [s]; bench/bench_emulated_rig.py measures the real-time figures
# with the rig's own.
RATE = 250.0
MOCAP_RATE = 120.0
TIMEOUT = 0.25
FIRMWARE_TIMEOUT = 0.4          # s, the emulated motors' CAN timeout: longer than the watchdog


@pytest.fixture(scope="module")
def config_dir(tmp_path_factory) -> str:
    """The package's parameter files, with the rates and timeouts above."""
    d = tmp_path_factory.mktemp("config")
    shutil.copytree(default_config_dir(), d, dirs_exist_ok=True)
    for name, path, values in (
            ("emulator.yaml", ("rig", "motors"),
             {"rate": RATE, "watchdog_timeout": TIMEOUT, "reply_timeout": TIMEOUT}),
            ("emulator.yaml", ("rig", "emulator"), {"command_timeout": FIRMWARE_TIMEOUT}),
            ("control.yaml", ("control", "inner_loop"), {"rate": RATE}),
            ("control.yaml", ("control", "clik"), {"rate": MOCAP_RATE}),
            ("plant.yaml", ("plant", "mocap"), {"rate": MOCAP_RATE})):
        tree = yaml.safe_load((d / name).read_text())
        section = tree["/**"]["ros__parameters"]
        for key in path:
            section = section[key]
        section.update(values)
        (d / name).write_text(yaml.safe_dump(tree))
    return str(d)


def test_the_motors_zero_shortening_is_the_models_slack_hanging_pose():
    """rig.yaml's zero_shortening is what the controller's model predicts for the pose the motors
    are zeroed in (hanging, tendons slack), to 0.01 mm."""
    model = build_model(load_arm_config())
    hanging = solve_equilibrium(model, np.zeros(model.n_tendons)).q
    predicted = model.rest_tendon_lengths - tendon_lengths(model, hanging)
    np.testing.assert_allclose(load_driver_config().zero_shortening, predicted, atol=1e-5)


def test_emulator_config_is_validated_and_laid_over_the_rig():
    values = load_emulator_config()
    assert values["reply_delay"] == 3e-4 and values["natnet_version"] == "4.1"
    assert load_emulator_config(overrides={"natnet_version": '"3.1"'})["natnet_version"] == "3.1"
    motors = read_emulated_motors()
    driver = load_driver_config(overrides=motors)
    # the emulated motors and arm in a process of their own, on the cross-process bus
    assert driver.interface == "soft_arm_loopback" and all(m.limits.t_max == 0.5 for m in driver.motors)
    with pytest.raises(ConfigError, match=r"rig\.emulator\.reply_delay = 0\.5 .*\[0, 0\.01\] s"):
        load_emulator_config(overrides={"reply_delay": 0.5})
    with pytest.raises(ConfigError, match=r"rig\.emulator\.natnet_version .*among"):
        load_emulator_config(overrides={"natnet_version": '"2.9"'})
    with pytest.raises(ConfigError, match="did you mean"):
        load_emulator_config(overrides={"reply_dealy": 0.001})


# Loaded by every Python process of a run through PYTHONPATH: once a process has frozen its set-up
# (run_node, the emulated hardware), a module imported by a thread other than the main one (a
# driver's cycle, the mocap's receive thread, the motors' loop) is written down. Such an import
# holds the interpreter for all of it (numpy.ma: 7 ms on an idle machine), longer than a cycle.
_LATE_IMPORT_PROBE = """
import gc, os, sys, threading
_freeze, _frozen = gc.freeze, []


def _freeze_marked():
    _frozen.append(True)
    _freeze()


def _audit(event, args):
    if event == "import" and _frozen and threading.current_thread() is not threading.main_thread():
        name = next((a for a in sys.orig_argv if a.startswith("soft_arm_")), " ".join(sys.orig_argv[1:3]))
        with open(os.path.join(os.environ["SOFT_ARM_LATE_IMPORTS"], str(os.getpid())), "a") as fh:
            fh.write(f"{name} [{threading.current_thread().name}]: {args[0]}\\n")


gc.freeze = _freeze_marked
sys.addaudithook(_audit)
"""


def test_closed_loop_through_the_emulated_hardware_reaches_the_target_like_the_simulator(
        tmp_path, config_dir, monkeypatch):
    """The one target through the emulated hardware as on the simulator; no process of the run
    imports a module from a thread other than its main one once running (:data:`_LATE_IMPORT_PROBE`)."""
    probe, late = tmp_path / "probe", tmp_path / "late_imports"
    probe.mkdir()
    late.mkdir()
    (probe / "sitecustomize.py").write_text(_LATE_IMPORT_PROBE, encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(probe),
                                                                   os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("SOFT_ARM_LATE_IMPORTS", str(late))
    sets = [a for s in ONE_TARGET for a in ("--set", s)]
    for attempt in ("hil", "hil_rerun"):
        out = tmp_path / attempt
        before = time.time()
        status = main(["coiling", "--emulated-hardware", "--quiet", "--config", config_dir,
                       "--output", str(out)] + sets)
        after = time.time()
        with open(out / "metrics.json", encoding="utf-8") as fh:
            hil = json.load(fh)
        # (a run whose bring-up failed has no faults: its failure says why)
        if not _rerun_after_a_hiccup(attempt, _hiccup("\n".join(
                [f["message"] for f in hil["run"].get("driver_faults", [])] + [hil.get("failure") or ""]))):
            break
    assert status == 0, hil
    assert hil["run"]["emulated_hardware"] and hil["run"]["driver_faults"] == []
    assert set(hil["run"]["node_exits"].values()) == {0}, hil["run"]["node_exits"]   # stopped cleanly
    assert not list(late.iterdir()), "".join(p.read_text() for p in late.iterdir())
    # the enable follows the run's own nodes' last change by the settle (the nodes' start-up is the
    # machine's: seconds more under load)
    assert hil["run"]["motors_enabled_s"] - hil["run"]["graph_quiet_s"] <= GRAPH_SETTLE + 5.0, hil["run"]

    sim_dir = tmp_path / "sim"
    sim_dir.mkdir()
    run_composed(_ros_arguments("coiling", ONE_TARGET, config_dir),
                 {"bag": str(sim_dir / "bag"), "metrics": str(sim_dir / "metrics.json")},
                 config_dir=config_dir)
    with open(sim_dir / "metrics.json", encoding="utf-8") as fh:
        sim = json.load(fh)

    h, s = hil["transitions"][0], sim["transitions"][0]
    # the same move (from the hanging arm to target 1), into the mm band, ending as close; the
    # window starts at the goal, which on the rig comes while the arm still settles from the
    # motors' enabling (0 to the pretension), some tenths of a second earlier: 3 mm apart on a slow
    # machine, under 3 mm on a fast one
    assert h["displacement"] == pytest.approx(s["displacement"], abs=5e-3)
    assert h["time_mm"] is not None and h["time_mm"] < 6.0
    assert h["final_error"] < 2e-3 and s["final_error"] < 2e-3
    assert h["rms_steady"] < 2e-3
    assert h["peak_speed"] < 1.5 * s["peak_speed"]    # measured, not a frame-timing artefact

    # what the drivers published, on the system clock: the motors' state at about 500 Hz (the
    # replies' stamps), the mocap at about 240 Hz (mid-exposure stamps), the controller answering
    series = read_series(str(out / "bag"))
    state = np.array([t for t, _ in series["tendon/state"]])
    markers = np.array([t for t, _ in series["mocap/markers"]])
    assert 0.75 / RATE < np.median(np.diff(state)) < 1.5 / RATE and np.all(np.diff(state) > 0)
    assert 0.85 / MOCAP_RATE < np.median(np.diff(markers)) < 1.2 / MOCAP_RATE
    assert len(series["tendon/command"]) > 0.8 * len(state)
    assert before < state[0] and state[-1] < after and before < markers[0] and markers[-1] < after


# Another process on the domain that every 0.5 s creates a node subscribed to tendon/state and
# destroys the one before (a `ros2 topic echo` started and stopped, RViz restarting), for at most
# argv[1] seconds
CHURN = """
import sys, time
import rclpy
from sensor_msgs.msg import JointState
rclpy.init()
end, k, last = time.monotonic() + float(sys.argv[1]), 0, None
while time.monotonic() < end:
    node = rclpy.create_node(f"visitor_{k}")
    node.create_subscription(JointState, "/tendon/state", lambda msg: None, 10)
    if last is not None:
        last.destroy_node()
    last, k = node, k + 1
    time.sleep(0.5)
rclpy.shutdown()
"""


def test_the_rig_comes_up_on_a_domain_where_other_nodes_come_and_go(tmp_path, config_dir):
    """The bring-up waits for the run's own nodes to settle, not the domain's: with another process
    creating and destroying a node every 0.5 s, the motors are enabled within the settle time + 5 s
    of the run's own endpoints' last change (when its nodes were up: their start-up is the
    machine's)."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    churn = subprocess.Popen([sys.executable, "-c", CHURN, str(2 * BRINGUP_TIMEOUT)], env=env)
    try:
        out = tmp_path / "run"
        sets = [a for s in ONE_TARGET for a in ("--set", s)]
        assert main(["coiling", "--emulated-hardware", "--quiet", "--config", config_dir, "--output",
                     str(out)] + sets) == 0
        assert churn.poll() is None                 # it churned the whole bring-up
    finally:
        churn.terminate()
        churn.wait(timeout=30)
    with open(out / "metrics.json", encoding="utf-8") as fh:
        run = json.load(fh)["run"]
    assert run["driver_faults"] == [], run
    assert run["motors_enabled_s"] - run["graph_quiet_s"] <= GRAPH_SETTLE + 5.0, run
    assert run["graph_settled_s"] - run["graph_quiet_s"] >= GRAPH_SETTLE - 0.01, run   # it did settle


def _experiment(config_dir, out, *options) -> subprocess.Popen:
    """``soft-arm-experiment coiling --emulated-hardware`` on one target as its own process (output
    to a pipe), with the parameter files of ``config_dir``, its results in ``out``."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    sets = [a for s in ONE_TARGET for a in ("--set", s)]
    return subprocess.Popen([sys.executable, "-m", "soft_arm_experiments.experiment", "coiling",
                             "--emulated-hardware", "--config", config_dir, *options, "--output", str(out)]
                            + sets,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory, config_dir):
    """A run with an identified arm file whose mocap calibration is 30 mm higher than mocap.yaml's,
    interrupted by a Ctrl-C 2 s after the motors were activated: (the process, its output, the run
    directory). A run the machine's fault ended before the Ctrl-C runs once more
    (:func:`_rerun_after_a_hiccup`)."""
    tmp = tmp_path_factory.mktemp("interrupted")
    calibration = load_mocap_config().calibration
    shifted = (calibration.rotation, calibration.translation + np.array([0.0, 0.0, 0.03]))
    arm_file = tmp / "identified_arm.yaml"
    write_identified_arm(str(arm_file), load_arm_config(), shifted)
    for attempt in ("run", "rerun"):
        out = tmp / attempt
        proc = _experiment(config_dir, out, "--arm-file", str(arm_file))
        with killed_on_exit(proc):
            seen = _until_activated(proc, attempt)
            if seen is None:
                continue
            time.sleep(2.0)
            output = seen + stop(proc, signal.SIGINT, 60)
        return proc, output, out
    raise AssertionError("unreachable: the rerun returns or raises")


def test_ctrl_c_disables_the_emulated_motors_then_stops_every_node(interrupted):
    """A Ctrl-C reaches the experiment only (each node runs in a process group of its own, setsid):
    it disables the motors, stops the nodes, keeps the bag and exits with 130; no node is left
    running."""
    proc, output, out = interrupted
    assert proc.returncode == 130, output
    assert "[motor_driver]: deactivated" in output
    assert_bag_holds_the_run(read_series(str(out / "bag"))["tendon/state"], 1.0)
    left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout
    assert left == "", left


def assert_bag_holds_the_run(state: list, driven: float):
    """The recorded motor states (time [s], message) cover at least ``driven`` [s] of the run (the
    motors were driven 2 s). Counted loosely: the recorder, at the normal policy
    beside the real-time nodes, keeps what it can on a slow machine (here as few as a tenth of the
    states at times) and counts the rest in the bag's metadata."""
    times = np.array([t for t, _ in state])
    assert times.size > 50 and times[-1] - times[0] > driven, (times.size, times[-1] - times[0])


def _child(parent: int, name: str) -> int:
    """The pid of the node process ``name`` that ``parent`` started: forked by its node fork server
    (``parent``'s child), named as the node in the process table (/proc/pid/comm)."""
    for server in realtime.child_processes(parent):
        for pid in realtime.child_processes(server):
            try:
                with open(f"/proc/{pid}/comm", encoding="utf-8") as fh:
                    if fh.read().strip() == name:
                        return pid
            except OSError:
                continue
    raise LookupError(f"no node process of {parent} named {name}")


class RigHiccup(UserWarning):
    """A run of the emulated rig ended on a fault of the machine that its test did not cause (a
    timing fault, the middleware failing at the start), and ran again."""


def _hiccup(output: str):
    """What of the machine ended a run, from its output or its metrics' faults and failure, None if
    nothing did: a fault the driver latched on its own timing (a stale command, a silent motor, a
    held cycle: a loaded machine's hiccup, caught), or a bring-up that the middleware failed (its
    shared-memory transport's error, or the orchestrator's saying it learnt no node of the run:
    soft_arm_experiments.orchestration._nameless_publishers)."""
    logged = re.search(r"\bfault(?:, all motors at zero torque)?: (.*)", output)
    if logged is not None and re.match(r"stale command|cycle held|motor \d+ silent", logged.group(1)):
        return logged.group(1)
    unwired = re.search(r"the graph is not up after .*", output)
    if unwired is not None and ("whose node this process never learnt" in unwired.group(0)
                                or "RTPS_TRANSPORT_SHM" in output):
        return unwired.group(0)
    return None


def _rerun_after_a_hiccup(attempt: str, hiccup) -> bool:
    """Whether a run that ``hiccup`` ended (:func:`_hiccup`; None: nothing did) runs once more: it
    proves nothing of the claim, since the driver caught the machine holding a node (the driver's
    job) or the run's processes never met; a second such run fails its test. Each rerun is said (a
    RigHiccup warning in pytest's summary), never passed over: a machine where they recur is too
    slow or too busy for this rig."""
    if hiccup is None or attempt.endswith("rerun"):
        return False
    warnings.warn(RigHiccup(f"the emulated rig's run ended on the machine's fault ({hiccup}); once more"))
    return True


def _until_activated(proc, attempt: str):
    """The output of the run ``proc`` up to its motor driver's activation; None when the machine's
    fault (:func:`_hiccup`) ended the run before it and the run is to go once more
    (:func:`_rerun_after_a_hiccup`); AssertionError with the run's output otherwise."""
    try:
        return wait_for_output(proc, "[motor_driver]: activated", timeout=120)
    except AssertionError as ended:
        if _rerun_after_a_hiccup(attempt, _hiccup(str(ended))):
            return None
        raise


def _with_node_stopped(config_dir, tmp_path, name: str, hold: float):
    """A run whose node ``name`` is stopped (SIGSTOP) 2 s after the motor driver's activation, for
    ``hold`` [s], then continued: (its whole output, its status, its results' directory). A run that
    the machine's fault ended before the stop runs once more (:func:`_rerun_after_a_hiccup`)."""
    for attempt in ("run", "rerun"):
        out = tmp_path / attempt
        proc = _experiment(config_dir, out, "--quiet")
        with killed_on_exit(proc):
            seen = _until_activated(proc, attempt)
            if seen is None:
                continue
            time.sleep(2.0)
            try:
                pid = _child(proc.pid, name)
            except LookupError as missing:      # the run ended already: say how
                output = seen + proc.communicate(timeout=60)[0]
                if _rerun_after_a_hiccup(attempt, _hiccup(output)):
                    continue
                raise AssertionError(f"{missing} 2 s after the driver's activation; the run's "
                                     f"output:\n{output}") from missing
            os.kill(pid, signal.SIGSTOP)
            try:
                time.sleep(hold)
            finally:
                os.kill(pid, signal.SIGCONT)
            return seen + proc.communicate(timeout=60)[0], proc.returncode, out
    raise AssertionError("unreachable: the rerun returns or raises")


def test_a_command_gap_faults_the_driver_and_the_run_is_no_result(tmp_path, config_dir):
    """The inner loop held for three watchdog periods while the motors are enabled: the driver's
    watchdog trips, the run ends at once with status 1, the motors are disabled, the bag stays
    readable and metrics.json is marked invalid with the fault and its time; no Table 1 row."""
    output, status, out = _with_node_stopped(config_dir, tmp_path, "inner_loop", 3 * TIMEOUT)
    assert status == 1, output
    assert "no result" in output and "[motor_driver]: deactivated" in output
    logged = re.search(r"fault, all motors at zero torque: (.*)", output)
    if logged is not None and logged.group(1).startswith("cycle held"):
        # the driver's own process held while the inner loop was stopped (about once in six suite
        # runs): a publish to a process that is stopped can wait until it continues, in the shared
        # memory transport's port check (docs/decisions/0005). Its watchdog trips on its own
        # deadline, the motors' firmware timeout holds meanwhile (the next test). Said as such,
        # not passed over.
        pytest.xfail(f"the driver's process was held while the inner loop was stopped: {logged.group(1)}")
    assert "stale command" in output
    assert "rms[mm]" not in output and "task velocity" not in output          # no Table 1 row
    with open(out / "metrics.json", encoding="utf-8") as fh:
        metrics = json.load(fh)
    assert metrics["valid"] is False and "stale command" in metrics["failure"]
    fault, = metrics["run"]["driver_faults"]
    assert "stale command" in fault["message"] and fault["time_s"] > 2.0    # the stop, 2 s after it
    series = read_series(str(out / "bag"))
    age = re.search(r"the latest is ([0-9.]+) s old", fault["message"])
    assert age is not None and TIMEOUT <= float(age.group(1)) <= 3 * TIMEOUT + 0.05, fault
    state = series["tendon/state"]
    assert_bag_holds_the_run(state, 1.0)
    # the run ended with the fault, not with the window: the state stops before the window from the
    # goal (the clik node's first report) could have ended, about 2 s after the goal on a quiet
    # machine; the message's timeline tells a stop that came late after the goal from a slow shutdown
    goal = min(t for t, d in series["diagnostics"] if any(s.name == "clik" for s in d.status))
    timeline = (f"state from {state[0][0] - goal:.2f} to {state[-1][0] - goal:.2f} s after the goal; "
                f"the fault {fault['time_s']:.2f} s after the enable")
    assert state[-1][0] - goal < WINDOW, timeline
    assert float(age.group(1)) < 2 * TIMEOUT, fault             # tripped while the loop was stopped


def test_a_stopped_driver_process_leaves_the_motors_to_their_firmware_timeout(tmp_path, config_dir):
    """The motor driver's own process stopped while the motors pull: its watchdog, a part of that
    process, cannot act; the motors' firmware timeout zeroes their command FIRMWARE_TIMEOUT after
    the last frame, in the hardware's own process. When the driver comes back its watchdog trips and
    the run is no result."""
    output, status, out = _with_node_stopped(config_dir, tmp_path, "emulated_rig", FIRMWARE_TIMEOUT + 0.3)
    silences = [float(s) for s in re.findall(r"heard no frame for ([0-9.]+) s: command zeroed", output)]
    assert len(silences) == 4, output                            # every motor, once
    assert all(FIRMWARE_TIMEOUT <= s < FIRMWARE_TIMEOUT + 0.05 for s in silences), silences
    assert status == 1 and "no result" in output, output
    with open(out / "metrics.json", encoding="utf-8") as fh:
        metrics = json.load(fh)
    # (the stop may come while the cycle thread publishes: then the fault says where it was held)
    held = re.fullmatch(r"fault: cycle held: ([0-9.]+) s since the previous cycle, the motors unwatched "
                        r"\(watchdog_timeout 0.25 s\)(; [0-9.]+ s of it in the node's publishing after "
                        r"the previous cycle)?", metrics["run"]["driver_faults"][0]["message"])
    assert metrics["valid"] is False and held is not None, metrics["run"]["driver_faults"]
    assert FIRMWARE_TIMEOUT + 0.3 <= float(held.group(1)) < FIRMWARE_TIMEOUT + 0.6


def test_the_bridge_takes_the_mocap_calibration_of_the_arm_file(interrupted):
    """An identified arm file carries the mocap calibration (soft-arm-identify writes it): with
    ``--arm-file`` the bridge maps Motive's points with it, not with mocap.yaml's. A calibration
    30 mm higher than mocap.yaml's puts the hanging arm's published markers 30 mm above the
    model's (the plant differs from the model by millimetres)."""
    _, _, out = interrupted
    frames = read_series(str(out / "bag"), topics=["mocap/markers"])["mocap/markers"]
    # the arm hanging, before any command: the first frame that saw every marker (the default
    # occlusions drop about 1 % of the markers)
    first = next(m for m in (markers_of(msg) for _, msg in frames) if np.all(np.isfinite(m)))
    model = build_model(load_arm_config())
    hanging = marker_positions(model, solve_equilibrium(model, np.zeros(model.n_tendons)).q)
    offset = (first - hanging).mean(axis=0)
    assert offset[2] == pytest.approx(0.03, abs=0.008), offset
    assert np.all(np.abs(offset[:2]) < 0.008), offset


def _deactivated_from_elsewhere(config_dir, out, context):
    """A run whose motor driver another node asks to deactivate 1 s after its activation: (whether
    it was deactivated, the run's whole output, its status). The other node and its client join
    the graph before the activation, as the rig's docs ask of every tool: this test's process has
    long been up, and a reader it adds mid-run can hold the driver's process for a third of a second
    (docs/decisions/0005), which the driver's watchdog rightly reports as a held cycle."""
    proc = _experiment(config_dir, out, "--quiet")
    with killed_on_exit(proc):
        operator = rclpy.create_node("operator", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(operator)
        try:
            client = operator.create_client(ChangeState, "/motor_driver/change_state")
            spin_until(executor, client.service_is_ready, 60.0, unless_ended=proc)
            try:
                seen = wait_for_output(proc, "[motor_driver]: activated", timeout=120)
            except AssertionError as ended:             # the run ended before: the caller says how
                return False, str(ended), proc.wait(timeout=60)
            time.sleep(1.0)
            deactivated = False
            if client.service_is_ready():
                future = client.call_async(ChangeState.Request(transition=Transition(label="deactivate")))
                spin_until(executor, future.done, 60.0, unless_ended=proc)
                deactivated = future.done() and future.result().success
        finally:
            executor.shutdown()
            operator.destroy_node()
        output = seen + proc.communicate(timeout=60)[0]
    return deactivated, output, proc.returncode


def test_a_driver_deactivated_from_elsewhere_ends_the_run_as_no_result(tmp_path, context, config_dir):
    """``ros2 lifecycle set /motor_driver deactivate`` from another terminal while the task runs: no
    fault latches (a deactivation is not one), but the motors no longer follow the controller, so
    the run ends at once, status 1, metrics.json invalid naming it."""
    for attempt in ("run", "rerun"):
        out = tmp_path / attempt
        deactivated, output, status = _deactivated_from_elsewhere(config_dir, out, context)
        # the claim is about a deactivation: a run that the machine's fault (:func:`_hiccup`) ended
        # before it could be done proves nothing of it; a deactivation refused or unanswered
        # otherwise is a failure
        if deactivated or not _rerun_after_a_hiccup(attempt, _hiccup(output)):
            break
    assert deactivated, ("the driver was not deactivated from elsewhere (not found, unanswered or "
                         f"refused):\n{output}")
    assert status == 1, output
    assert "rms[mm]" not in output
    with open(out / "metrics.json", encoding="utf-8") as fh:
        metrics = json.load(fh)
    assert metrics["valid"] is False
    assert "left the active state" in output and "left the active state" in metrics["failure"], output


def test_motors_flashed_with_another_firmware_stop_the_run_naming_the_preset(tmp_path, config_dir):
    """rig.yaml says AK80-9 (+-50 rad/s) but the motors' firmware is 1.1 (+-22.5 rad/s): the
    velocities read 2.2 times too fast. Once the arm moves the driver names the mismatch and the
    preset that fits, latches a fault, and the run ends as no result: the task is not run."""
    flashed = tmp_path / "config"
    shutil.copytree(config_dir, flashed)
    tree = yaml.safe_load((flashed / "emulator.yaml").read_text())
    tree["/**"]["ros__parameters"]["rig"]["emulator"]["firmware"] = "AK80-9-fw1.1"
    (flashed / "emulator.yaml").write_text(yaml.safe_dump(tree))
    held = ""
    for attempt in ("run", "rerun"):
        out = tmp_path / attempt
        proc = _experiment(str(flashed), out, "--quiet")
        with killed_on_exit(proc):
            output = proc.communicate(timeout=240)[0]
        # the machine's fault before the arm had moved enough to judge the scale leaves the claim unproven
        if "is not its firmware's" in output or not _rerun_after_a_hiccup(attempt, _hiccup(output)):
            break
        held = f"the first run ended on the machine's fault; its output:\n{output}\n"
    assert proc.returncode == 1, held + output
    assert "the preset AK80-9 (+-50 rad/s) is not its firmware's" in output, held + output
    assert "the preset AK80-9-fw1.1 would fit" in output and "rms[mm]" not in output, held + output
    with open(out / "metrics.json", encoding="utf-8") as fh:
        metrics = json.load(fh)
    assert metrics["valid"] is False and "AK80-9-fw1.1 would fit" in metrics["failure"], metrics
    fault, = metrics["run"]["driver_faults"]
    assert fault["time_s"] < 3.0                 # at the first move, not after the task
