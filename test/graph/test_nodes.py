"""Each node alone, as its own process with real rclpy: parameters from YAML, a bad parameter stops
it with a clear message and status 2, SIGINT shuts it down cleanly; the recorder survives SIGTERM
with a closed bag and SIGKILL with a readable one."""
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from soft_arm_experiments.orchestration import node_module
from soft_arm_model.parameters import default_config_dir

from conftest import killed_on_exit, stop, wait_for_output

NODES = ("simulator", "inner_loop", "clik", "task_runner", "recorder")


def _params():
    d = default_config_dir()
    out = ["--ros-args"]
    for name in ("arm", "control", "plant", "tasks", "graph"):
        out += ["--params-file", os.path.join(d, f"{name}.yaml")]
    return out


def _start(node, *extra, cwd=None):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", node_module(node)] + _params() + list(extra),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            cwd=cwd)


@pytest.mark.parametrize("node", NODES)
def test_node_starts_from_yaml_and_stops_cleanly(node, tmp_path):
    extra = ["-p", f"output:={tmp_path / 'out'}"] if node in ("recorder", "task_runner") else []
    proc = _start(node, "-p", "graph.task:=coiling", *extra)
    with killed_on_exit(proc):
        log = wait_for_output(proc, "ready" if node not in ("recorder", "task_runner") else
                              ("recording" if node == "recorder" else "windows"))
        assert "coiling" in log or node in ("simulator", "inner_loop", "recorder")
        out = stop(proc, signal.SIGINT, 20)
    assert proc.returncode == 0, out


@pytest.mark.parametrize("node, param, message", [
    ("simulator", "graph.simulator.mode:=fast", "graph.simulator.mode = 'fast' is not valid"),
    ("inner_loop", "control.inner_loop.rate:=0.0", "control.inner_loop.rate = 0.0 is not valid"),
    ("clik", "graph.task:=square", "graph.task = 'square' is not valid"),
    ("task_runner", "tasks.coiling.targets:=[0.1]", "groups of 2 coordinates"),
    ("recorder", "graph.recorder.topics:=[nowhere]", "graph.recorder.topics entry 'nowhere'"),
])
def test_bad_parameter_stops_the_node_with_status_2(node, param, message):
    proc = _start(node, "-p", "graph.task:=coiling", "-p", param)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2, out
    assert message in out


def _publish_states(count):
    """Publish ``count`` JointStates on tendon/state from this process (rclpy)."""
    import rclpy
    from sensor_msgs.msg import JointState

    from soft_arm_ros.contract import QOS
    from soft_arm_ros.conversions import joint_state
    rclpy.init()
    node = rclpy.create_node("publisher_for_test")
    pub = node.create_publisher(JointState, "tendon/state", QOS["tendon/state"])
    deadline = time.monotonic() + 20
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    for k in range(count):
        pub.publish(joint_state(["a"], k * 0.002, position=[k * 1e-3]))
        time.sleep(0.001)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.shutdown()


def _read(bag):
    with AnyReader([pathlib.Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        return [reader.deserialize(raw, conn.msgtype) for conn, _, raw in reader.messages()]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_recorder_closes_the_bag_on_signals(tmp_path, sig):
    bag = tmp_path / "bag"
    proc = _start("recorder", "-p", f"output:={bag}", "-p", "graph.recorder.topics:=[tendon/state]")
    with killed_on_exit(proc):
        wait_for_output(proc, "recording")
        _publish_states(200)
        out = stop(proc, sig, 20)
    assert proc.returncode == 0, out
    from mcap.reader import make_reader
    with open(bag / "bag_0.mcap", "rb") as fh:
        assert make_reader(fh).get_summary() is not None          # closed: summary and footer
    messages = _read(bag)
    assert len(messages) >= 150                                   # best effort on loopback
    assert [m.position[0] for m in messages] == sorted(m.position[0] for m in messages)


def test_recorder_bag_survives_sigkill(tmp_path):
    bag = tmp_path / "bag"
    proc = _start("recorder", "-p", f"output:={bag}", "-p", "graph.recorder.topics:=[tendon/state]",
                  "-p", "graph.recorder.chunk_size:=2048")
    with killed_on_exit(proc):
        wait_for_output(proc, "recording")
        _publish_states(300)
        stop(proc, signal.SIGKILL, 20)
    messages = _read(bag)                       # no summary: the readers scan the chunks
    assert len(messages) >= 200                 # all but the last chunk (a few dozen messages)
    assert (bag / "metadata.yaml").exists()


def test_simulator_in_realtime_holds_the_tension_and_counts_missing_commands():
    import rclpy
    from geometry_msgs.msg import PoseArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from soft_arm_drivers.sim.simulator_node import SimulatorNode
    from soft_arm_ros.contract import QOS
    from soft_arm_ros.conversions import joint_state
    rclpy.init()
    try:
        sim = SimulatorNode(parameter_overrides=[Parameter("graph.simulator.mode", value="realtime"),
                                                 Parameter("graph.task", value="coiling")])
        peer = rclpy.create_node("peer")
        command = peer.create_publisher(JointState, "tendon/command", QOS["tendon/command"])
        frames = []
        peer.create_subscription(PoseArray, "mocap/markers", frames.append, QOS["mocap/markers"])
        executor = SingleThreadedExecutor()
        executor.add_node(sim)
        executor.add_node(peer)
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        assert 0.3 < sim.rig.t < 2.0                     # steps on the wall clock
        assert sim.missing_commands > 10                 # nobody commands: counted, not a crash
        assert all(u == pytest.approx(0.05) for u in sim.rig.tension)
        assert frames                                    # mocap keeps streaming
        names = ["tendon_1", "tendon_2", "tendon_3", "tendon_4"]
        for effort in ([0.05, 0.05, 1.0, float("nan")], [0.05, 0.05, 1.0, 0.5]):
            command.publish(joint_state(names, sim.rig.t, effort=effort))
            end = time.monotonic() + 0.3
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)
        assert sim.bad_commands == 1
        assert list(sim.rig.tension) == [0.05, 0.05, 1.0, 0.5]
        executor.shutdown()
        sim.destroy_node()
        peer.destroy_node()
    finally:
        rclpy.try_shutdown()


def _lockstep_run(wall: float, factor: float, in_waves: bool = False) -> float:
    """Simulated seconds [s] a lockstep simulator (``max_real_time_factor`` = ``factor``) makes in
    ``wall`` seconds against a peer that answers every state at once."""
    import rclpy
    from geometry_msgs.msg import PoseArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from soft_arm_drivers.sim.simulator_node import SimulatorNode
    from soft_arm_ros.contract import QOS
    from soft_arm_ros.conversions import joint_state
    rclpy.init()
    try:
        sim = SimulatorNode(in_waves=in_waves, parameter_overrides=[
            Parameter("graph.task", value="coiling"),
            Parameter("graph.simulator.max_real_time_factor", value=factor)])
        peer = rclpy.create_node("peer")
        command = peer.create_publisher(JointState, "tendon/command", QOS["tendon/command"])
        peer.create_subscription(JointState, "tendon/state", lambda msg: command.publish(
            joint_state(sim.names, 0.0, effort=[0.05] * 4)), QOS["tendon/state"])
        peer.create_subscription(PoseArray, "mocap/markers", lambda msg: None, QOS["mocap/markers"])
        executor = SingleThreadedExecutor()
        executor.add_node(sim)
        executor.add_node(peer)
        deadline = time.monotonic() + 20.0
        while sim.rig.t == 0.0:                        # until the peer's first answer
            assert time.monotonic() < deadline, "no command answered the simulator's first state"
            executor.spin_once(timeout_sec=0.01)
        start, t0 = time.monotonic(), sim.rig.t
        while time.monotonic() < start + wall:
            executor.spin_once(timeout_sec=0.01)
        simulated = sim.rig.t - t0
        executor.shutdown()
        sim.destroy_node()
        peer.destroy_node()
        return simulated
    finally:
        rclpy.try_shutdown()


def test_simulator_in_lockstep_keeps_to_its_real_time_factor():
    """Answered at once, a lockstep simulator runs faster than a quarter of real time unpaced
    (the composed run's wave executor), and at most a quarter (plus one step) with
    ``max_real_time_factor`` 0.25, not far below it either."""
    assert _lockstep_run(1.0, 0.25, in_waves=True) > 0.5
    simulated = _lockstep_run(1.0, 0.25)
    assert 0.15 < simulated <= 0.25 * (1.0 + 0.01) + 0.002


def _clik(task, sent, **parameters):
    """A clik node for ``task`` with more ``parameters`` (dotted name: value), its references
    appended to ``sent`` instead of published (rclpy initialised by the caller)."""
    from rclpy.parameter import Parameter

    from soft_arm_control.clik_node import ClikNode
    node = ClikNode(parameter_overrides=[Parameter("graph.task", value=task)]
                    + [Parameter(name, value=value) for name, value in parameters.items()])
    node.ref_pub.publish = sent.append
    node.q_pub.publish = lambda msg: None
    return node


def _goal(target, mode="clik", labels=None, frame="arm_base", phase=""):
    from soft_arm_interfaces.msg import TaskGoal
    msg = TaskGoal(mode=mode, phase=phase, labels=labels or [], target=[float(v) for v in target])
    msg.header.frame_id = frame
    return msg


def test_clik_node_rejects_bad_goals_and_keeps_the_last_reference():
    import rclpy
    from rclpy.parameter import Parameter

    from soft_arm_control.clik_node import ClikNode
    rclpy.init()
    try:
        node = ClikNode(parameter_overrides=[Parameter("graph.task", value="coiling")])
        sent, references = [], []
        node.ref_pub.publish = sent.append
        node.q_pub.publish = references.append
        x, z = node.labels                                     # marker4.x, marker4.z
        node.on_goal(_goal([-0.349, -0.009], labels=[z, x]))    # taken by its labels
        assert len(sent) == 1 and node.rejected_goals == 0
        ref, = references
        assert list(sent[0].velocity) == [0.0] * 4                  # a precomputed step: fixed
        assert (ref.goal, ref.mode, list(ref.labels), ref.header.frame_id) == (0, "clik", [x, z], "arm_base")
        assert list(ref.target) == [-0.009, -0.349] and len(ref.q_d) == node.model.n
        assert abs(ref.x_model[0] - ref.target[0]) < 1e-4 and abs(ref.x_model[1] - ref.target[1]) < 1e-4
        first = node.outer.reference
        node.on_goal(_goal([0.3, 0.3]))                         # unreachable
        node.on_goal(_goal([0.01]))                             # wrong size
        node.on_goal(_goal([0.0, -0.3], "sideways"))            # unknown mode
        node.on_goal(_goal([0.017, -0.313], "replay"))          # never reached
        node.on_goal(_goal([-0.009, -0.349], frame="world"))    # another frame
        node.on_goal(_goal([-0.009, -0.349], labels=[x, "marker3.z"]))     # another task's
        node.on_goal(_goal([-0.009, -0.349], "track", phase="upward"))     # a phase without trajectory
        assert node.rejected_goals == 7 and len(sent) == 1
        assert node.outer.reference is first
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_a_slow_clik_takes_a_goal_at_once_and_drops_the_frames_it_cannot_keep_up_with():
    """A CLIK step of 12.5 ms against 240 Hz frames (a loaded computer), on the events executor the
    node runs on, which queues an event per frame, so that a goal sent 1.5 s in would wait seconds
    behind them: the frames that arrive during a step are dropped (every step but the last drops
    some), the goal is taken within 0.25 s, the drops are counted and reported, and a step is taken
    per step's worth of time
    (docs/decisions/0006-clik-node-drops-frames-queued-behind-a-slow-step.md)."""
    import threading

    import rclpy
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from geometry_msgs.msg import PoseArray
    from soft_arm_interfaces.msg import TaskGoal

    from soft_arm_control.clik_node import ClikNode
    from soft_arm_ros.contract import QOS, TOPICS
    from soft_arm_ros.conversions import pose_array
    from soft_arm_ros.runtime import make_executor
    rclpy.init()
    try:
        node = ClikNode(parameter_overrides=[Parameter("graph.task", value="coiling")])
        taken, steps, reports = [], [], []

        def slow_step(t, x, sigma=None):
            time.sleep(0.0125)
            steps.append(t)

        def goal(t, x_d, mode, **kwargs):
            taken.append(time.monotonic())
            raise ValueError("taken")                     # rejected: no reference to compute

        node.outer.frame, node.outer.goal = slow_step, goal
        node.diagnostics_pub.publish = reports.append
        source = Node("frames")
        frames = source.create_publisher(PoseArray, TOPICS["markers"], QOS["mocap/markers"])
        goals = source.create_publisher(TaskGoal, TOPICS["goal"], QOS["task/goal"])
        executor = make_executor()
        executor.add_node(node)
        deadline = time.monotonic() + 20.0
        while min(frames.get_subscription_count(), goals.get_subscription_count()) < 1:
            assert time.monotonic() < deadline, "the clik node's subscriptions were not matched"
            executor.spin_once(timeout_sec=0.05)
        markers = [[0.0, 0.0, -0.1 * k] for k in range(1, node.model.marker_X.size + 1)]
        sent = []
        # built before the stream starts: the publishing thread holds the GIL only to publish, not
        # for the milliseconds of building messages the node's executor would wait behind
        stream = [pose_array(markers, k / 240.0) for k in range(720)]      # 3 s at 240 Hz
        goal_message = _goal([-0.349, -0.009], "replay")

        def publish():
            start = time.monotonic()
            for k, message in enumerate(stream):
                frames.publish(message)
                if k == 360:
                    sent.append(time.monotonic())
                    goals.publish(goal_message)
                time.sleep(max(0.0, start + (k + 1) / 240.0 - time.monotonic()))

        thread = threading.Thread(target=publish)
        thread.start()
        end = time.monotonic() + 3.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        thread.join()
        assert taken, "the goal was not taken within 2 s of being sent"
        assert taken[0] - sent[0] < 0.25 and node.rejected_goals == 1
        assert node.frames.dropped >= len(steps) - 1 and node.frames.processed == len(steps)
        assert 120 < len(steps) < 240                     # one per 12.5-16.7 ms in 3 s
        from soft_arm_control.outer_loop import GoalReport
        node.outer.reports.append(GoalReport([0.0, 0.0], "clik"))
        node.publish_diagnostics()
        values = {kv.key: kv.value for kv in reports[-1].status[0].values}
        assert int(values["frames_dropped"]) == node.frames.dropped
        executor.shutdown()
        source.destroy_node()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_inner_loop_node_takes_a_reference_s_rate_from_its_velocity_field():
    """tendon/reference's velocity: the reference's shortening rates (by name, any order); an empty
    field is a fixed reference; a field of the wrong length is refused, the last reference kept."""
    import rclpy

    from soft_arm_control.inner_loop_node import InnerLoopNode
    from soft_arm_ros.conversions import joint_state
    rclpy.init()
    try:
        node = InnerLoopNode()
        names = list(node.names)
        node.on_reference(joint_state(names[::-1], 0.0, position=[0.01, 0.02, 0.03, 0.04],
                                      velocity=[0.4, 0.3, 0.2, 0.1], effort=[1.0] * 4))
        assert np.allclose(node.core.s_ref_dot, [0.1, 0.2, 0.3, 0.4])
        assert np.allclose(node.core.s_ref, [0.04, 0.03, 0.02, 0.01])
        node.on_reference(joint_state(names, 0.0, position=[0.0] * 4, effort=[1.0] * 4))
        assert np.all(node.core.s_ref_dot == 0.0) and node.rejected == 0
        bad = joint_state(names, 0.0, position=[0.02] * 4, effort=[1.0] * 4)
        bad.velocity = [0.1, 0.2]
        node.on_reference(bad)
        assert node.rejected == 1 and np.all(node.core.s_ref == 0.0)
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_clik_node_rejects_a_fragile_goal():
    """With 3.5 g at the tip the triangle's second vertex is near a fold of the model (0.44 Hz held
    by the inner loop, below control.clik.min_frequency): rejected; the third (0.91 Hz) is taken."""
    import rclpy
    rclpy.init()
    try:
        sent = []
        node = _clik("triangle", sent, **{"arm.tip_mass": 0.0035})
        node.on_goal(_goal([-0.03, 0.138, -0.241, 0.056]))
        assert node.rejected_goals == 1 and not sent
        node.on_goal(_goal([0.048, 0.123, -0.282, 0.043]))
        assert node.rejected_goals == 1 and len(sent) == 1
        node.destroy_node()
        node = _clik("triangle", sent, **{"arm.tip_mass": 0.0035, "control.clik.min_frequency": 0.0})
        node.on_goal(_goal([-0.03, 0.138, -0.241, 0.056]))       # the check off
        assert node.rejected_goals == 0 and len(sent) == 2
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_clik_node_solves_its_seed_equilibria_before_the_first_goal(monkeypatch):
    """The triangle's third vertex is not reached from the hanging arm: its reference starts from
    the seed equilibria. The node solves them at start-up, not at that goal (0.7 s idle, 2.4-4.9 s
    under load, the arm holding the last vertex meanwhile): at the goal none is solved."""
    import rclpy
    from rclpy.parameter import Parameter

    from soft_arm_control import outer_loop
    from soft_arm_control.clik import TargetError
    from soft_arm_control.clik_node import ClikNode
    rclpy.init()
    try:
        node = ClikNode(parameter_overrides=[Parameter("graph.task", value="triangle")])
        third = np.array([0.048, 0.123, -0.282, 0.043])
        outer = node.outer
        with pytest.raises(TargetError):                        # it needs the seeds
            outer.clik.precompute(third, outer.start.q, tol=outer.tolerance, search=False)
        monkeypatch.setattr(outer_loop, "equilibrium_seeds", lambda *a: pytest.fail("solved after start-up"))
        solved = outer.seeds()
        assert len(solved) == len(node.control.seed_levels) ** len(node.task.tendons)
        sent = []
        node.ref_pub.publish = sent.append
        node.q_pub.publish = lambda msg: None
        node.on_goal(_goal(third))
        assert node.rejected_goals == 0 and len(sent) == 1 and outer.seeds() is solved
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_task_runner_waits_for_start_and_stays_up_after_the_last_window(tmp_path):
    """wait_for_start: frames before ~/start are ignored; the schedule starts with the first frame
    after it; the metrics are written whole at the end and the node stays up (done is False)."""
    import rclpy
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from soft_arm_experiments.task_runner_node import TaskRunnerNode
    from soft_arm_ros.conversions import pose_array
    out = tmp_path / "metrics.json"
    rclpy.init()
    try:
        node = TaskRunnerNode(parameter_overrides=[
            Parameter("graph.task", value="coiling"), Parameter("output", value=str(out)),
            Parameter("wait_for_start", value=True),
            Parameter("tasks.coiling.phases", value=["upward"]),
            Parameter("tasks.coiling.phase.upward.sequence", value=[1]),
            Parameter("tasks.coiling.phase.upward.window", value=1.0)])
        goals = []
        node.pub.publish = goals.append
        markers = [[0.0, 0.0, -0.1 * k] for k in range(1, 5)]
        node.on_markers(pose_array(markers, 10.0))
        assert goals == [] and node.core.t0 is None
        response = node.on_start(Trigger.Request(), Trigger.Response())
        assert response.success and "coiling" in response.message
        assert not node.on_start(Trigger.Request(), Trigger.Response()).success
        for k in range(60):                                    # 1.2 s of frames at 50 Hz
            node.on_markers(pose_array(markers, 11.0 + 0.02 * k))
        assert len(goals) == 1 and node.core.t0 == 11.0
        assert node.finished and not node.done
        assert json.loads(out.read_text())["task"] == "coiling"
        assert not (tmp_path / "metrics.json.partial").exists()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_the_task_runners_windows_go_on_at_the_arms_pace_through_steps_of_the_frames_clock(tmp_path):
    """The frames' stamps step 100 s forward, later 50 s back (NTP, a re-anchored mocap clock): no
    window is skipped or held, each goal goes out at its window's start counted in frames, and the
    metrics say how many steps the clock took. On the stamps alone the forward step ended the task
    at once, the second window's goal never sent."""
    import rclpy
    from rclpy.parameter import Parameter

    from soft_arm_experiments.task_runner_node import TaskRunnerNode
    from soft_arm_ros.conversions import pose_array
    out = tmp_path / "metrics.json"
    rclpy.init()
    try:
        node = TaskRunnerNode(parameter_overrides=[
            Parameter("graph.task", value="coiling"), Parameter("output", value=str(out)),
            Parameter("tasks.coiling.phases", value=["upward"]),
            Parameter("tasks.coiling.phase.upward.sequence", value=[1, 2]),
            Parameter("tasks.coiling.phase.upward.window", value=0.5)])
        sent = []
        node.pub.publish = sent.append
        markers = [[0.0, 0.0, -0.1 * k] for k in range(1, 5)]
        stamp, at = 20.0, []
        for k in range(60):                                    # 1.2 s of frames at 50 Hz
            stamp += 100.0 if k == 10 else (-50.0 if k == 35 else 0.02)
            before = len(sent)
            node.on_markers(pose_array(markers, stamp))
            at += [k] * (len(sent) - before)
            if node.finished:
                break
        assert at == [0, 25] and node.finished and k == 50, (at, k)
        metrics = json.loads(out.read_text())
        assert metrics["frame_clock_steps"] == 2 and metrics["complete"] is True
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize("param, message", [
    ("rig.motors.interface:=socketcan", "rig.motors.interface = 'socketcan' is not valid for the "
                                        "emulated rig"),
    ("rig.mocap.server_address:=192.0.2.1", "rig.mocap.server_address = '192.0.2.1' is not valid"),
    ("rig.motors.channel:=can0", "rig.motors.channel = 'can0' is not valid: soft_arm_loopback channel"),
    ("rig.emulator.reply_delay:=0.5", "rig.emulator.reply_delay = 0.5 is not valid"),
    ("rig.emulator.command_timeout:=0.02", "rig.emulator.command_timeout = 0.02 is not valid: expected 0 "
                                           "or a time longer than rig.motors.watchdog_timeout"),
])
def test_emulated_rig_refuses_what_is_not_an_emulation(param, message):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.run([sys.executable, "-m", node_module("emulated_rig")] + _params()
                          + ["-p", param],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert message in proc.stdout + proc.stderr


def test_ctrl_c_stops_the_experiment_and_keeps_the_bag(tmp_path):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "soft_arm_experiments.experiment", "triangle",
                             "--output", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)
    with killed_on_exit(proc):
        wait_for_output(proc, "recording", timeout=90)            # the recorder is up: it runs
        time.sleep(3.0)
        output = stop(proc, signal.SIGINT, 60)
    assert proc.returncode == 130, output
    messages = _read(out / "bag")
    assert len(messages) > 100
    if (out / "metrics.json").exists():           # the windows played so far: no result
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["valid"] is False and metrics["complete"] is False, metrics
        assert metrics["failure"] == "interrupted before the run played to its end"


def test_inner_loop_node_keeps_commanding_through_a_clock_step_and_names_it():
    """States whose stamps step back 5 s mid-run (NTP corrected the rig PC's clock): every state is
    answered, stamped like it, and /diagnostics names the clock step (WARN, status inner_loop)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from soft_arm_control.inner_loop_node import InnerLoopNode
    from soft_arm_ros.contract import QOS
    from soft_arm_ros.conversions import joint_state, stamp_to_seconds
    from conftest import spin_until
    rclpy.init()
    try:
        node = InnerLoopNode()
        names = list(node.names)
        rig = rclpy.create_node("rig")
        commands, diagnostics = [], []
        rig.create_subscription(JointState, "tendon/command", commands.append, QOS["tendon/command"])
        rig.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
        states = rig.create_publisher(JointState, "tendon/state", QOS["tendon/state"])
        reference = rig.create_publisher(JointState, "tendon/reference", QOS["tendon/reference"])
        executor = SingleThreadedExecutor()
        for n in (node, rig):
            executor.add_node(n)
        spin_until(executor, lambda: states.get_subscription_count() and reference.get_subscription_count()
                   and node.pub.get_subscription_count())
        reference.publish(joint_state(names, 0.0, position=[0.002] * 4, effort=[1.0] * 4))
        spin_until(executor, lambda: node.core.s_ref is not None)
        stamps = [1000.0 + 0.002 * k for k in range(100)]
        stamps += [stamps[-1] - 5.0 + 0.002 * k for k in range(1, 101)]
        for t in stamps:
            states.publish(joint_state(names, t, position=[0.001] * 4, velocity=[0.0] * 4))
            count = len(commands)
            spin_until(executor, lambda: len(commands) > count)
        answered = [stamp_to_seconds(c.header.stamp) for c in commands]
        np.testing.assert_allclose(answered, stamps, atol=1e-9)                 # every state, in order
        assert node.rejected == 0 and node.core.clock.steps_back == 1
        spin_until(executor, lambda: any(s.name == "inner_loop" and s.level == DiagnosticStatus.WARN
                                         for d in diagnostics for s in d.status))
        warning = next(s for d in diagnostics for s in d.status if s.level == DiagnosticStatus.WARN)
        assert warning.message == "clock step: 1 clock step (0 forward, 1 back); the latest back by 4.998 s"
        assert {v.key: v.value for v in warning.values}["clock_steps_back"] == "1"
        xi = node.core.pid.xi
        assert np.all(np.isfinite(xi)) and np.all(xi > 0)                     # integrating through it
        executor.shutdown()
        rig.destroy_node()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize("jump", [1e9, -5.0])
def test_clik_node_keeps_stepping_through_a_clock_step_of_the_frames(jump):
    """One mocap frame stamped 1e9 s ahead, or every frame from one on stepped back 5 s: the online
    CLIK steps at every frame after it as before (it held its steps until the stamps caught up, for
    good or for 5 s), the step is counted and its messages carry the frames' stamps."""
    import rclpy

    from soft_arm_ros.conversions import pose_array, stamp_to_seconds
    from soft_arm_model import marker_positions, solve_equilibrium
    rclpy.init()
    try:
        sent = []
        node = _clik("coiling", sent, **{"control.clik.rate": 120.0})
        hanging = marker_positions(node.model, solve_equilibrium(node.model, [0.05] * 4).q)
        stamps = [100.0 + k / 120.0 for k in range(240)]
        node.on_markers(pose_array(hanging, stamps[0]))
        node.on_goal(_goal([-0.349, -0.009], "online"))
        for t in stamps[1:120]:
            node.on_markers(pose_array(hanging, t))
        before = len(sent)
        if jump > 0:
            node.on_markers(pose_array(hanging, stamps[119] + jump))    # one frame from another clock
            after = stamps[120:]
        else:
            after = [t + jump for t in stamps[120:]]                       # every frame from here on
        for t in after:
            node.on_markers(pose_array(hanging, t))
        stepped = len(sent) - before
        assert stepped >= len(after) - 2, (stepped, len(after))
        assert node.frame_clock.steps == (2 if jump > 0 else 1)
        assert stamp_to_seconds(sent[-1].header.stamp) == pytest.approx(after[-1], abs=1e-6)
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_a_goal_taken_before_any_frame_starts_at_the_first_frame_on_any_clock():
    """A restarted clik node takes the latched goal before the first mocap frame, and the frames are
    stamped on the wall clock (1.7e9 s): the goal's switch delay (2 s) counts from the first frame,
    not from the CLIK's time 0, so no online step comes in the first second and steps come after
    the delay (they came from the first frame, the delay taken as long past)."""
    import rclpy

    from soft_arm_model import marker_positions, solve_equilibrium
    from soft_arm_ros.conversions import pose_array
    rclpy.init()
    try:
        node = _clik("coiling", [], **{"control.clik.rate": 120.0})
        hanging = marker_positions(node.model, solve_equilibrium(node.model, [0.05] * 4).q)
        bent = marker_positions(node.model, solve_equilibrium(node.model, [0.05, 0.05, 0.6, 0.05]).q)
        node.on_goal(_goal(node.task.space.from_markers(bent)))
        assert node.rejected_goals == 0
        delay = node.control.switch_delay
        start = 1.7e9
        for k in range(120):
            node.on_markers(pose_array(hanging, start + k / 120.0))
        goal = node.outer.reports[-1]
        assert goal.online_steps == 0, goal.online_steps
        for k in range(120, int(120 * (delay + 1.0))):
            node.on_markers(pose_array(hanging, start + k / 120.0))
        assert goal.online_steps > 60, goal.online_steps
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_a_clock_step_seen_on_a_frame_dropped_behind_a_slow_step_names_the_step():
    """The frames' stamps jump 2 s forward: on a frame the node processes the warning names the
    mocap's clock alone; on a frame that arrived during the node's own 50 ms step (dropped behind
    it) it also names that step and its wall time, the node's lateness being the other cause."""
    import re
    import rclpy

    from soft_arm_ros.conversions import pose_array
    from soft_arm_model import marker_positions, solve_equilibrium
    rclpy.init()
    try:
        node = _clik("coiling", [])
        warnings = []

        class Logger:
            def warning(self, text, **_):
                warnings.append(text)
        node.get_logger = Logger
        hanging = marker_positions(node.model, solve_equilibrium(node.model, [0.05] * 4).q)
        for k in range(10):
            node.on_markers(pose_array(hanging, 100.0 + k / 240.0))
        node.on_markers(pose_array(hanging, 102.0))
        assert len(warnings) == 1 and "forward by 1.9625 s" in warnings[0] and "own step" not in warnings[0]
        late = [pose_array(hanging, 104.0)]
        node._take_frame = lambda: late.pop() if late else None

        def slow_step(t, x, sigma=None):
            time.sleep(0.05)
        node.outer.frame = slow_step
        node.on_frame(pose_array(hanging, 102.0 + 1 / 240.0))
        assert len(warnings) == 3 and "forward by 1.99583 s" in warnings[1], warnings
        assert "1 of 2 dropped" in warnings[2]                  # the late frame, counted
        step = re.search(r"during this node's own step of ([0-9.e-]+) s \(wall\)", warnings[1])
        assert step is not None and 0.05 <= float(step.group(1)) < 1.0, warnings[1]
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_on_an_estimate_each_frame_steps_on_its_own_tips_covariance_even_when_the_tip_comes_after():
    """The shape estimator publishes a frame on fused/markers and its tip on fused/tip with the same
    stamp; here each frame arrives before its tip, and the tip is seen (zero covariance) on every
    other frame only, estimated (10 mm) on the rest. Each frame waits for its own tip: the frames
    whose tip was estimated take no step (they took the previous frame's zero covariance, and a
    full step); a tip that never comes leaves its frame without a step when the next frame comes."""
    import rclpy

    from soft_arm_control.shape_estimator_node import tip_message
    from soft_arm_model import marker_positions, solve_equilibrium
    from soft_arm_ros.conversions import pose_array
    rclpy.init()
    try:
        node = _clik("coiling", [], **{"control.clik.feedback": "estimate"})
        hanging = marker_positions(node.model, solve_equilibrium(node.model, [0.05] * 4).q)
        x = node.task.space.from_markers(hanging)
        node.on_tip(tip_message(hanging[-1], np.zeros((3, 3)), 100.0))
        node.on_markers(pose_array(hanging, 100.0))
        node.on_goal(_goal(x + np.array([0.01, 0.0]), "online"))
        goal = node.outer.reports[-1]
        stepped = []
        for k in range(1, 121):
            t = 100.0 + k / 240.0
            before = goal.online_steps
            node.on_markers(pose_array(hanging, t))
            assert node.waiting is not None and node.waiting[2] == pytest.approx(t, abs=1e-9)   # its tip
            node.on_tip(tip_message(hanging[-1], np.eye(3) * (0.0 if k % 2 else 1e-4), t))
            assert node.waiting is None
            stepped.append(goal.online_steps > before)
        assert stepped == [k % 2 == 1 for k in range(1, 121)]     # on the seen tips' frames only
        assert goal.uncertain_frames >= 55
        steps = goal.online_steps
        node.on_markers(pose_array(hanging, 101.0))          # its tip lost: the next frame comes
        node.on_markers(pose_array(hanging, 101.0 + 1 / 240.0))
        node.on_tip(tip_message(hanging[-1], np.zeros((3, 3)), 101.0 + 1 / 240.0))
        assert goal.online_steps == steps + 1 and node.waiting is None
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize("variance, stepped", [(None, False), (1e-4, False), (0.0, True)])
def test_on_an_estimate_the_clik_node_steps_only_on_what_the_tip_covariance_defends(variance, stepped):
    """The clik node on ``control.clik.feedback: estimate``, an online goal 10 mm off the hanging
    arm: without a fused/tip message, or with the tip's 10 mm standard deviation, no online step is
    taken (the goal is uncertain); with a zero covariance (the mocap saw the tip) it steps."""
    import rclpy

    from soft_arm_control.shape_estimator_node import tip_message
    from soft_arm_model import marker_positions, solve_equilibrium
    from soft_arm_ros.conversions import pose_array
    rclpy.init()
    try:
        sent = []
        node = _clik("coiling", sent, **{"control.clik.feedback": "estimate"})
        hanging = marker_positions(node.model, solve_equilibrium(node.model, [0.05] * 4).q)
        x = node.task.space.from_markers(hanging)
        node.on_markers(pose_array(hanging, 100.0))
        node.on_goal(_goal(x + np.array([0.01, 0.0]), "online"))
        first = np.array(node.outer.reference.shortening)
        for k in range(1, 120):
            t = 100.0 + k / 240.0
            if variance is not None:
                node.on_tip(tip_message(hanging[-1], np.eye(3) * variance, t))
            node.on_markers(pose_array(hanging, t))
        goal = node.outer.reports[-1]
        moved = float(np.max(np.abs(np.array(node.outer.reference.shortening) - first)))
        assert (moved > 1e-4) == stepped, moved
        assert (goal.online_steps > 20) == stepped and (goal.uncertain_frames > 20) != stepped
        assert (goal.status == "uncertain") != stepped, goal.status
        assert goal.fraction == (1.0 if stepped else 0.0)
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
