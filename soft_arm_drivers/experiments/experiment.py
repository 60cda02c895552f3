"""``soft-arm-experiment <task>``: the main job. Runs one of the paper's experiments as the ROS 2
graph on the simulator, records the bag, writes the metrics and the figures.

By default all nodes (simulator, inner_loop, clik, task_runner, recorder) are composed in this
process and run in lockstep waves (deterministic: the same seed gives the same messages);
``--processes`` starts each node as its own process with the same parameters instead (the
simulator still steps once per command, over DDS). ``--emulated-hardware`` runs the rig's graph in
real time, one process per node, with the motor driver and the mocap bridge talking to emulated
CAN motors and an emulated Motive server in the simulator's place (:mod:`.emulated_rig`).
Output (``--output DIR``, default ``runs/<task>-<UTC time>``): ``bag/`` (rosbag2, MCAP),
``metrics.json``, ``figures/*.png``. Prints a progress line (composed runs), the paper-style table
and the paths (``--json``: the metrics as JSON on stdout). Ctrl-C stops everything cleanly (the
emulated motors are disabled first) and keeps what was recorded (exit status 130). A bad parameter
or an unreachable target exits with status 2; a node that dies or a run that cannot go on, with 1.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib.metadata
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from soft_arm_model.parameters import ConfigError, default_config_dir

from .metrics import Summary, TransitionMetrics, format_table

NODES = ("simulator", "inner_loop", "clik", "task_runner", "recorder")
STOP = threading.Event()       # set by the first Ctrl-C / SIGTERM: the run loops end at their next turn


def _request_stop(signum, frame):
    """First signal: stop at the next turn of the run loop; a second one interrupts at once."""
    if STOP.is_set():
        raise KeyboardInterrupt
    STOP.set()


def _ros_arguments(task: str, sets, config_dir: str | None) -> list:
    """--ros-args for every node: the package's parameter files, the task and the overrides."""
    d = config_dir or default_config_dir()
    args = ["--ros-args"]
    for name in ("arm", "control", "plant", "tasks", "graph"):
        args += ["--params-file", os.path.join(d, f"{name}.yaml")]
    args += ["-p", f"graph.task:={task}"]
    for pair in sets:
        key, sep, value = pair.partition("=")
        if not sep or key.split(".")[0] not in ("arm", "control", "plant", "tasks", "graph"):
            raise ConfigError(f"--set expects namespace.key=value with namespace one of arm, control, "
                              f"plant, tasks, graph; got {pair!r}")
        args += ["-p", f"{key}:={value}"]
    return args


def _progress(t: float, total: float):
    print(f"\r  simulated {t:6.1f} / {total:.1f} s", end="", file=sys.stderr, flush=True)


def _shut_down(nodes, executor):
    """End a composed run whatever stopped it: the task runner writes what it has, every node
    closes (the recorder its bag), then the executor, the nodes and rclpy go."""
    import rclpy
    for node in nodes:
        finish = getattr(node, "finish", None)
        if finish is not None and not node.done:
            finish()
        close = getattr(node, "close", None)
        if close is not None:
            close()
    if executor is not None:
        executor.shutdown()
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown()


def run_composed(ros_args: list, out: dict, progress=None, config_dir: str | None = None,
                 node_args: dict | None = None) -> dict:
    """All nodes in this process, lockstep waves. Returns run facts (simulated time, waves...).

    ``node_args``: extra command-line arguments per node name (e.g. remaps:
    ``{"simulator": ["--ros-args", "-r", "__ns:=/hw"]}``).
    """
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from soft_arm_control.clik_node import ClikNode
    from soft_arm_control.inner_loop_node import InnerLoopNode
    from soft_arm_drivers.recording.recorder_node import RecorderNode
    from soft_arm_drivers.sim.simulator_node import SimulatorNode

    from .lockstep import WaveExecutor
    from .task_runner_node import TaskRunnerNode

    # Ctrl-C stays Python's KeyboardInterrupt (no rclpy handler shutting the context mid-wave), so
    # that the shutdown below always runs in order.
    rclpy.init(args=["soft-arm-experiment"] + ros_args, signal_handler_options=SignalHandlerOptions.NO)
    nodes, executor = [], None
    try:
        node_args = node_args or {}

        def options(name):
            return {"start_parameter_services": False, "cli_args": node_args.get(name)}

        sim = SimulatorNode(config_dir, watchdog=False, **options("simulator"))
        nodes.append(sim)
        nodes += [InnerLoopNode(config_dir, **options("inner_loop")),
                  ClikNode(config_dir, **options("clik"))]
        runner = TaskRunnerNode(config_dir, parameter_overrides=[
            Parameter("output", value=out["metrics"])], **options("task_runner"))
        recorder = RecorderNode(config_dir, parameter_overrides=[
            Parameter("output", value=out["bag"]), Parameter("use_sim_time", value=True)],
            **options("recorder"))
        nodes += [runner, recorder]
        executor = WaveExecutor(nodes)
        start = time.monotonic()
        while not sim._started:
            executor.spin_timers(0.01)
        last_flush, reported = time.monotonic(), 0
        while not runner.done and not STOP.is_set():
            if executor.wave() == 0:
                raise RuntimeError("the graph went quiet before the experiment ended")
            if progress is not None and sim.rig.t >= reported + 1.0:
                reported = int(sim.rig.t)
                progress(sim.rig.t, runner.core.duration)
            if time.monotonic() - last_flush > 1.0:
                recorder.writer.flush()
                last_flush = time.monotonic()
        return {"simulated_s": sim.rig.t, "wall_s": time.monotonic() - start, "waves": executor.waves,
                "missing_commands": sim.missing_commands, "messages_recorded": recorder.count}
    finally:
        _shut_down(nodes, executor)


def _free_udp_port() -> int:
    """A UDP port of 127.0.0.1 free right now (for the emulated Motive server)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _wait_for_graph(node, children, flowing: tuple = (), settle: float = 0.0,
                    timeout: float = 120.0):
    """Until the graph is wired: a publisher on each of the controller's and the plant's topics (a
    node creates them once its set-up is done), a recorder, messages arriving on the ``flowing``
    topics (names of ``TOPICS``: e.g. the controller answering the motors' state), and, with
    ``settle`` [s], no endpoint appearing or going for that long (discovery over). The probe
    subscriptions stay (they go with ``node``). RuntimeError when a node exits or after ``timeout``
    [s]."""
    import rclpy

    from soft_arm_ros.contract import QOS, TOPICS, TYPES, message_class
    topics = ["/" + TOPICS[k] for k in ("command", "reference", "state", "markers")]
    counts = {}
    for key in flowing:
        topic = TOPICS[key]
        counts[topic] = 0
        node.create_subscription(message_class(TYPES[topic]), topic,
                                 lambda msg, topic=topic: counts.__setitem__(topic, counts[topic] + 1),
                                 QOS[topic])
    deadline = time.monotonic() + timeout
    graph, since = None, time.monotonic()
    while not STOP.is_set():
        children.check()
        missing = [t for t in topics if node.count_publishers(t) == 0]
        missing += [f"{t} (no messages yet)" for t, n in counts.items() if n < 10]
        if "recorder" not in node.get_node_names():
            missing.append("the recorder")
        now = _endpoints(node)
        if now != graph:
            graph, since = now, time.monotonic()
        if not missing and time.monotonic() - since >= settle:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"the graph is not up after {timeout:g} s: "
                               + (f"nothing on {missing}" if missing else "its endpoints keep changing"))
        rclpy.spin_once(node, timeout_sec=0.05)


def _endpoints(node) -> tuple:
    """The graph's nodes, and its topics with their publisher and subscriber counts."""
    return (tuple(sorted(node.get_node_names_and_namespaces())),
            tuple((topic, node.count_publishers(topic), node.count_subscribers(topic))
                  for topic, _ in sorted(node.get_topic_names_and_types())))


def _call(node, client, request, timeout: float = 10.0):
    """Call a service through ``client`` and return its response; RuntimeError if it is not there
    or does not answer, or if it answers ``success = False``."""
    import rclpy
    if not client.wait_for_service(timeout_sec=timeout):
        raise RuntimeError(f"service {client.srv_name} is not available")
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if not future.done() or future.result() is None:
        raise RuntimeError(f"service {client.srv_name} did not answer within {timeout:g} s")
    response = future.result()
    if not response.success:
        raise RuntimeError(f"{client.srv_name} refused: {response.message}")
    return response


class _Children:
    """The node processes of one run (the console scripts' modules with the run's arguments), on
    loopback; ``realtime``: the SCHED_FIFO priorities of the processes that have one."""

    def __init__(self, ros_args: list, extra: dict, realtime: dict | None = None):
        self.ros_args, self.extra, self.realtime = ros_args, extra, realtime or {}
        self.env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        self.procs: dict = {}

    def start(self, name: str):
        """Start a node in its own session (a Ctrl-C in the terminal reaches this process only,
        which stops the nodes in order), under SCHED_FIFO if it has a priority: set before the
        interpreter has started a thread, so that every thread of the node inherits it."""
        proc = subprocess.Popen(
            [sys.executable, "-m", node_module(name)] + self.ros_args + self.extra.get(name, []),
            env=self.env, start_new_session=True)
        self.procs[name] = proc
        if name in self.realtime:
            os.sched_setscheduler(proc.pid, os.SCHED_FIFO, os.sched_param(self.realtime[name]))

    def check(self, may_end=()):
        """RuntimeError if a node exited (those in ``may_end`` with status 0 may)."""
        for name, proc in self.procs.items():
            if proc.poll() is not None and not (name in may_end and proc.returncode == 0):
                raise RuntimeError(f"node {name} exited with status {proc.returncode}")

    def stop(self):
        """SIGINT to every node still running; SIGKILL to those not gone after 10 s."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in self.procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


@contextlib.contextmanager
def _orchestrating(children: _Children):
    """This process's node (graph queries, service calls) for a run of ``children``; on the way
    out, whatever happened, the node and rclpy go, then the children are stopped."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=["soft-arm-experiment"], signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node("soft_arm_experiment", start_parameter_services=False)
        try:
            yield node
        finally:
            node.destroy_node()
    finally:
        try:
            rclpy.try_shutdown()
        finally:
            children.stop()


def run_processes(ros_args: list, out: dict) -> dict:
    """Each node its own process, the same parameters: recorder, inner_loop, clik and simulator
    start; once the graph is wired (the controller's, the plant's and the recorder's endpoints
    exist) the task runner starts. Waits for it, then stops the others with SIGINT."""
    import rclpy
    children = _Children(ros_args, {"recorder": ["-p", f"output:={out['bag']}", "-p", "use_sim_time:=true"],
                                    "task_runner": ["-p", f"output:={out['metrics']}"]})
    start = time.monotonic()
    with _orchestrating(children) as node:
        for name in ("recorder", "inner_loop", "clik", "simulator"):
            children.start(name)
        _wait_for_graph(node, children)
        if not STOP.is_set():
            children.start("task_runner")
        while not STOP.is_set() and children.procs["task_runner"].poll() is None:
            children.check(may_end=("task_runner",))
            rclpy.spin_once(node, timeout_sec=0.2)
        if not STOP.is_set():
            children.check(may_end=("task_runner",))
    return {"wall_s": time.monotonic() - start}


def run_emulated_hardware(ros_args: list, out: dict, duration: float,
                          config_dir: str | None = None) -> dict:
    """The rig's graph in real time, each node its own process, with the ``emulated_rig`` (the
    motor_driver node with the CAN motor emulators and the NatNet server emulator behind it,
    :mod:`.emulated_rig`) and the ``mocap_bridge`` in the simulator's place; ``duration`` [s]: the
    task's, ``config_dir``: where rig.yaml, mocap.yaml and emulator.yaml are (default: the package's).

    As an operator runs the rig: every node starts (the task runner waiting for ``~/start``); once
    the graph is wired and settled and the controller answers the motors' state, the motors are
    zeroed (tendons slack) and enabled through the driver's services and the task starts; when the
    task runner has written the metrics (RuntimeError if not within ``duration`` + 60 s) the motors
    are disabled, then the nodes are stopped. No process joins or leaves the graph while the motors
    are enabled: DDS discovery can hold a publisher, the driver's included, for a few hundred ms.
    The driver's faults are printed as they latch and those latched while the motors were enabled
    are listed in the run facts (``driver_faults``)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from std_srvs.srv import SetBool, Trigger

    from soft_arm_ros.conversions import stamp_to_seconds

    d = config_dir or default_config_dir()
    files = [a for name in ("rig.yaml", "mocap.yaml", "emulator.yaml")
             for a in ("--params-file", os.path.join(d, name))]
    port = _free_udp_port()
    realtime = _realtime_permitted()
    if not realtime:
        print("soft-arm-experiment: real-time scheduling is not permitted here (it needs root, "
              "CAP_SYS_NICE or an rtprio limit): a busy computer may hold the emulated hardware "
              "long enough for the motor driver's watchdog to trip", file=sys.stderr)
    children = _Children(ros_args, {
        "recorder": ["-p", f"output:={out['bag']}"],
        "task_runner": ["-p", f"output:={out['metrics']}", "-p", "wait_for_start:=true"],
        "emulated_rig": files + ["-p", f"rig.mocap.command_port:={port}"],
        "mocap_bridge": files + ["-p", f"rig.mocap.command_port:={port}", "-p", "rig.mocap.data_port:=0"]},
        _REALTIME if realtime else None)
    faults = []
    enabled_at = math.inf                  # system time [s] from which a fault counts
    start = time.monotonic()

    def facts():
        return {"wall_s": time.monotonic() - start, "emulated_hardware": True, "realtime": realtime,
                "driver_faults": faults}

    def on_diagnostics(msg):
        """Print the motor driver's faults as they latch (the run goes on: it is the operator's
        call on the rig, and the metrics will show it); keep those latched while enabled."""
        for status in msg.status:
            if status.name == "motor_driver" and status.level == DiagnosticStatus.ERROR \
                    and stamp_to_seconds(msg.header.stamp) >= enabled_at and status.message not in faults:
                faults.append(status.message)
                print(f"\nsoft-arm-experiment: motor_driver {status.message}", file=sys.stderr)

    with _orchestrating(children) as node:
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        # every client is created, and its server discovered, before the motors are enabled
        zero = node.create_client(Trigger, "/motor_driver/zero")
        enable = node.create_client(SetBool, "/motor_driver/enable")
        begin = node.create_client(Trigger, "/task_runner/start")
        for name in ("recorder", "emulated_rig", "mocap_bridge", "inner_loop", "clik", "task_runner"):
            children.start(name)
        _wait_for_graph(node, children, ("command", "markers"), settle=2.0)
        for client in (zero, enable, begin):
            if not STOP.is_set() and not client.wait_for_service(timeout_sec=10.0):
                raise RuntimeError(f"service {client.srv_name} is not available")
        if STOP.is_set():
            return facts()
        _call(node, zero, Trigger.Request())
        try:
            response = _call(node, enable, SetBool.Request(data=True))
            enabled_at = time.time()
            if response.message != "enabled":              # a fault latched while disabled
                print(f"soft-arm-experiment: motor_driver {response.message}", file=sys.stderr)
            _call(node, begin, Trigger.Request())
            deadline = time.monotonic() + duration + 60.0
            while not STOP.is_set() and not os.path.exists(out["metrics"]):
                children.check()
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the task runner wrote no metrics within {duration + 60.0:g} s")
                rclpy.spin_once(node, timeout_sec=0.1)
        finally:
            try:
                _call(node, enable, SetBool.Request(data=False), timeout=2.0)
            except RuntimeError as exc:
                print(f"soft-arm-experiment: could not disable the motors: {exc}", file=sys.stderr)
    return facts()


# Real time on a shared computer. The emulated hardware (plant, motors and Motive in one process)
# and the processes the loop closes through run under SCHED_FIFO where the system permits it: under
# the normal policy a busy two-core computer holds one of them, or a DDS thread it waits on while it
# publishes, for 0.1-0.3 s now and then, and the motor driver's watchdog rightly trips. On the rig,
# run motor_driver, mocap_bridge and inner_loop the same way (README, "On the rig, and on the emulated rig").
_REALTIME = {"emulated_rig": 30, "inner_loop": 20, "mocap_bridge": 20}


def _realtime_permitted() -> bool:
    """Whether this process may give its children SCHED_FIFO (tried on itself, then undone)."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(_REALTIME.values())))
        os.sched_setscheduler(0, policy, param)
        return True
    except (AttributeError, OSError):
        return False


def node_module(name: str) -> str:
    """The module of the node console script ``name``, from the package's entry points (setup.py is
    their one source); ConfigError if no such script is installed."""
    found = [ep for ep in importlib.metadata.entry_points(group="console_scripts", name=name)
             if ep.value.startswith("soft_arm_")]
    if not found:
        raise ConfigError(f"no soft_arm console script {name!r} is installed (pip install -e .)")
    return found[0].value.partition(":")[0]


def _load_metrics(path: str):
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    rows = [TransitionMetrics(**r) for r in data["transitions"]]
    return data, rows, Summary(**data["summary"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="soft-arm-experiment", description=__doc__.splitlines()[0])
    parser.add_argument("task", help="task name in tasks.yaml (triangle, coiling, ...)")
    parser.add_argument("--output", metavar="DIR", help="run directory (default: runs/<task>-<time>)")
    parser.add_argument("--processes", action="store_true", help="one process per node")
    parser.add_argument("--emulated-hardware", action="store_true",
                        help="motor driver + CAN emulator and mocap bridge + NatNet emulator in the "
                             "simulator's place (real time)")
    parser.add_argument("--config", metavar="DIR", help="directory with the parameter files")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE",
                        help="override one parameter (repeatable)")
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress line (composed runs print one)")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        from .harness import load_setup
        setup = load_setup(args.task, args.config,
                           [s for s in args.sets if not s.startswith("graph.")])
        ros_args = _ros_arguments(args.task, args.sets, args.config)
    except (ConfigError, ValueError) as exc:
        print(f"soft-arm-experiment: {exc}", file=sys.stderr)
        return 2
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
    run_dir = os.path.abspath(args.output or os.path.join("runs", f"{args.task}-{stamp}"))
    if os.path.exists(os.path.join(run_dir, "bag")):
        print(f"soft-arm-experiment: {run_dir} already holds a run", file=sys.stderr)
        return 2
    os.makedirs(run_dir, exist_ok=True)
    out = {"bag": os.path.join(run_dir, "bag"), "metrics": os.path.join(run_dir, "metrics.json"),
           "figures": os.path.join(run_dir, "figures")}
    STOP.clear()
    previous = {sig: signal.signal(sig, _request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(args, setup, ros_args, out)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run(args, setup, ros_args: list, out: dict) -> int:
    """Run the graph the way ``args`` says, then report; the exit status."""
    progress = None if args.quiet else _progress
    failed = None
    try:
        if args.emulated_hardware:
            duration = sum(ph.window * len(ph.sequence) for ph in setup.task.phases)
            facts = run_emulated_hardware(ros_args, out, duration, args.config)
        elif args.processes:
            facts = run_processes(ros_args, out)
        else:
            facts = run_composed(ros_args, out, progress, args.config)
    except KeyboardInterrupt:
        facts = {}
    except ConfigError as exc:
        print(f"\nsoft-arm-experiment: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:            # a node died, a service refused, a deadline passed
        facts, failed = {}, str(exc)
        print(f"\nsoft-arm-experiment: {exc}", file=sys.stderr)
    interrupted = STOP.is_set()
    if progress is not None:
        print(file=sys.stderr)
    figures = []
    if os.path.isdir(out["bag"]):
        from .figures import make_figures
        figures = make_figures(out["bag"], setup.task, out["figures"])
    if failed is not None or not os.path.exists(out["metrics"]):
        print(f"soft-arm-experiment: {'interrupted; ' if interrupted else ''}"
              f"{'no metrics written' if failed is None else 'the run failed'}; bag: {out['bag']}",
              file=sys.stderr)
        return 130 if interrupted else 1
    data, rows, summary = _load_metrics(out["metrics"])
    data["run"] = facts
    with open(out["metrics"], "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2)
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(format_table(rows, summary))
        if facts.get("simulated_s"):
            print(f"\nsimulated {facts['simulated_s']:.1f} s in {facts['wall_s']:.1f} s "
                  f"(real-time factor {facts['simulated_s'] / facts['wall_s']:.2f})")
        print(f"bag:     {out['bag']}\nmetrics: {out['metrics']}")
        for path in figures:
            print(f"figure:  {path}")
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
