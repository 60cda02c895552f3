"""The orchestrator's bring-up judges the run's own nodes: what other processes on the same ROS
domain publish wires nothing of the run."""
import time

import pytest


class _OwnNodes:
    """The children of a run as the bring-up sees them: their node names, none exited."""

    def __init__(self, names):
        self.names = set(names)

    def node_names(self):
        return self.names

    def check(self, may_end=()):
        pass


def test_the_bring_up_does_not_take_another_processs_publishers_for_the_runs():
    """A node of another run (a bag played, an old graph left running) publishes every topic the
    bring-up waits for; the run's own recorder is up, its controller and plant are not: the wait
    names the topics still missing and ends at its bound, where it took the other node's
    publishers for the run's and let the run start on them."""
    import rclpy
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import JointState

    from soft_arm_experiments.orchestration import _wait_for_graph
    from soft_arm_ros.contract import QOS, TOPICS
    rclpy.init()
    try:
        other = rclpy.create_node("player")
        for key, kind in (("command", JointState), ("reference", JointState), ("state", JointState),
                          ("markers", PoseArray)):
            other.create_publisher(kind, TOPICS[key], QOS[TOPICS[key]])
        recorder = rclpy.create_node("recorder")                 # kept: a node collected is gone
        orchestrator = rclpy.create_node("soft_arm_experiment")
        with pytest.raises(RuntimeError, match=r"the graph is not up after 3 s: nothing on "
                           r"\['/tendon/command', '/tendon/reference', '/tendon/state', '/mocap/markers'\]"):
            _wait_for_graph(orchestrator, _OwnNodes({"recorder", "inner_loop", "clik", "simulator"}),
                            timeout=3.0)
        assert orchestrator.count_publishers("/" + TOPICS["command"]) == 1 and recorder.get_name()
    finally:
        rclpy.try_shutdown()


def test_a_node_of_the_runs_name_from_another_process_stops_the_bring_up_naming_it():
    """A recorder left over on the domain beside the run's own: the bring-up waits for it to leave
    (a killed process's nodes stay until their lease runs out), then stops naming it, where it took
    whichever it saw for the run's (and the run's service calls would reach both).
    Nodes of the same names in another namespace (another robot's graph) are not the run's: their
    publishers on every topic wire nothing of it."""
    import rclpy
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import JointState

    from soft_arm_experiments.orchestration import _wait_for_graph
    from soft_arm_ros.contract import QOS, TOPICS
    rclpy.init()
    try:
        elsewhere = [rclpy.create_node(name, namespace="/robot_2") for name in ("recorder", "simulator")]
        for key, kind in (("command", JointState), ("reference", JointState), ("state", JointState),
                          ("markers", PoseArray)):
            elsewhere[1].create_publisher(kind, "/" + TOPICS[key], QOS[TOPICS[key]])
        orchestrator = rclpy.create_node("soft_arm_experiment")
        own = _OwnNodes({"recorder", "inner_loop", "clik", "simulator"})
        with pytest.raises(RuntimeError, match=r"the graph is not up after 2 s: nothing on .*the recorder"):
            _wait_for_graph(orchestrator, own, timeout=2.0)
        twins = [rclpy.create_node("recorder"), rclpy.create_node("recorder")]
        started = time.monotonic()
        with pytest.raises(RuntimeError, match=r"another process has nodes named /recorder on this ROS "
                                               r"domain .*stop them, or run on another domain"):
            _wait_for_graph(orchestrator, own, timeout=30.0, twin_grace=1.0)
        assert time.monotonic() - started < 10.0 and all(n.get_name() for n in elsewhere + twins)
    finally:
        rclpy.try_shutdown()


class _Checked(_OwnNodes):
    """Children that count the checks of their lives."""

    def __init__(self):
        super().__init__(())
        self.checks = 0

    def check(self, may_end=()):
        self.checks += 1


def test_the_wait_for_a_result_ends_at_its_bound_naming_what_is_late(tmp_path):
    """A run whose result never comes (a stalled graph) is stopped at its bound with the reason the
    caller gives, its children checked as it waits; a result, a stop asked by the caller or Ctrl-C
    end the wait at once."""
    import time

    import rclpy

    from soft_arm_experiments import orchestration
    rclpy.init()
    try:
        node = rclpy.create_node("soft_arm_experiment")
        children, result = _Checked(), tmp_path / "metrics.json"
        start = time.monotonic()
        with pytest.raises(RuntimeError, match="the task_runner node wrote no result within 0.3 s"):
            orchestration._await_result(node, children, str(result), 0.3,
                                        "the task_runner node wrote no result within 0.3 s", period=0.05)
        assert 0.3 <= time.monotonic() - start < 2.0 and children.checks >= 3
        orchestration._await_result(node, children, str(result), 0.3, "late", until=lambda: True)
        result.write_text("{}")
        orchestration._await_result(node, children, str(result), 0.0, "late")
        result.unlink()
        orchestration.STOP.set()
        try:
            orchestration._await_result(node, children, str(result), 0.0, "late")
        finally:
            orchestration.STOP.clear()
    finally:
        rclpy.try_shutdown()


def test_a_composed_run_closes_its_bag_even_when_its_runner_cannot_write_its_result():
    """The composed run's shut-down: the task runner's result cannot be written (a full disk), and
    the recorder after it still closes its bag, every node is destroyed, and the runner's error is
    raised once all is closed (it left the bag without its summary)."""
    from soft_arm_experiments.experiment import _shut_down
    done = []

    class Node:
        def __init__(self, name, failing=False):
            self.name, self.failing, self.done = name, failing, False

        def finish(self):
            if self.failing:
                raise OSError(28, "No space left on device")
            done.append(f"{self.name} finished")

        def close(self):
            done.append(f"{self.name} closed")

        def destroy_node(self):
            done.append(f"{self.name} destroyed")
    with pytest.raises(OSError, match="No space left"):
        _shut_down([Node("task_runner", failing=True), Node("recorder")], None)
    assert done == ["task_runner closed", "recorder finished", "recorder closed", "task_runner destroyed",
                    "recorder destroyed"]


def test_a_node_ends_with_the_orchestrator_even_when_it_is_killed(tmp_path):
    """soft-arm-experiment killed outright (SIGKILL, the OOM killer: no finally runs) leaves no node
    running the rig: each node process gets the SIGINT its shutdown answers when its parent dies."""
    import os
    import signal
    import subprocess
    import sys
    import time
    script = tmp_path / "orchestrator.py"
    script.write_text(
        "import time\n"
        "from soft_arm_experiments.experiment import _ros_arguments\n"
        "from soft_arm_experiments.orchestration import _Children\n"
        "children = _Children(_ros_arguments('coiling', [], None), {})\n"
        "children.start('task_runner')\n"
        "print(children.procs['task_runner'].pid, flush=True)\n"
        "time.sleep(120)\n")
    orchestrator = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                                    env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    node = None
    try:
        node = int(orchestrator.stdout.readline())
        time.sleep(3.0)                                       # the node is up (or coming up)
        assert _running(node)
        orchestrator.kill()
        orchestrator.wait()
        deadline = time.monotonic() + 20.0
        while _running(node) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _running(node), "the node outlived its orchestrator"
    finally:
        orchestrator.kill()
        if node is not None and _running(node):
            os.kill(node, signal.SIGKILL)                      # not left behind by a failure


def test_a_node_that_does_not_stop_writes_where_it_hangs_then_is_killed(tmp_path, capfd, monkeypatch):
    """A node process (forked as every node of a run) whose shutdown hangs, deaf to the SIGINT as a
    node's shutdown is: after the stop's timeout its threads' stacks come out on its stderr, under a
    line naming it, then it is killed, and its exit says so."""
    import signal
    import time

    from soft_arm_experiments import orchestration
    from soft_arm_experiments.orchestration import _Children, exit_failure
    closing = tmp_path / "closing"
    (tmp_path / "hung_node.py").write_text(
        "import pathlib, signal, sys, time\n"
        "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "def stuck_on_its_way_out():\n"
        "    pathlib.Path(sys.argv[1]).write_text('closing')\n"
        "    time.sleep(60)\n"
        "stuck_on_its_way_out()\n", encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    monkeypatch.setattr(orchestration, "node_module", lambda name: "hung_node")
    children = _Children([str(closing)], {})
    try:
        children.start("hung")
        deadline = time.monotonic() + 30.0
        while not closing.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert closing.exists(), "the node never ran"
        children.stop(timeout=0.5)
    finally:
        for proc in children.procs.values():
            proc.kill()
        if children.server is not None:
            children.server.close()
    assert children.exits == {"hung": -signal.SIGKILL}
    err = capfd.readouterr().err
    assert "stuck_on_its_way_out" in err and "hung_node.py" in err, err
    assert "node hung did not stop within 0.5 s; its threads as it hangs:" in err
    assert err.index("its threads as it hangs") < err.index("stuck_on_its_way_out")
    assert exit_failure(children.exits) == "node hung was killed (it did not stop within 10 s)"


def _running(pid: int) -> bool:
    """Whether the process ``pid`` runs (a zombie nobody reaped has ended)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


class _GraphWithoutNames:
    """What a process whose middleware failed at the start sees of the run: publishers on every
    topic the bring-up waits for, none of their nodes known by name."""

    def get_node_names_and_namespaces(self):
        return []

    def get_publishers_info_by_topic(self, topic):
        from types import SimpleNamespace

        from soft_arm_experiments.orchestration import UNKNOWN_NODE
        return [SimpleNamespace(node_name=UNKNOWN_NODE, node_namespace="_NODE_NAMESPACE_UNKNOWN_")]


def test_a_bring_up_that_sees_publishers_without_their_nodes_says_the_middleware_failed(monkeypatch):
    """The run's publishers discovered but not its nodes (their processes' descriptions never
    arrived): the wait ends at its bound naming what is missing, how many publishers came without
    their node and that a new run is the remedy, where it said only that nothing was there."""
    import time

    import rclpy

    from soft_arm_experiments.orchestration import _wait_for_graph
    monkeypatch.setattr(rclpy, "spin_once", lambda node, timeout_sec: time.sleep(timeout_sec))
    with pytest.raises(RuntimeError, match=r"the graph is not up after 0.2 s: nothing on "
                       r"\['/tendon/command', '/tendon/state', 'the recorder'\]; 2 publishers on them "
                       r"whose node this process never learnt: .*the middleware failed between the "
                       r"processes at their start.*: run again"):
        _wait_for_graph(_GraphWithoutNames(), _OwnNodes({"recorder", "inner_loop"}), timeout=0.2,
                        published=("command", "state"))
