"""Running the graph one process per node, as on the rig: the node processes (console scripts'
modules forked from the run's :mod:`.fork_server`, each in a process group of its own (setsid),
SCHED_FIFO where permitted), waiting until the graph is wired, the operator's service calls, and a
teardown that always runs (motors disabled, then the nodes stopped).

``STOP`` is set by the first Ctrl-C / SIGTERM of ``soft-arm-experiment``: the run loops end at their
next turn.
"""
from __future__ import annotations

import contextlib
import importlib.metadata
import math
import os
import signal
import subprocess
import sys
import threading
import time

from soft_arm_control.config import IDENTIFICATION
from soft_arm_drivers.can.command_source import UNKNOWN_NODE
from soft_arm_drivers.can.loopback_bus import free_udp_ports
from soft_arm_model.parameters import ConfigError, default_config_dir

from . import realtime
from .fork_server import STACKS_SIGNAL, STATUS_LOST, ForkServer

STOP = threading.Event()       # set by the first Ctrl-C / SIGTERM: the run loops end at their next turn


def request_stop(signum, frame):
    """First signal: stop at the next turn of the run loop; a second one interrupts at once."""
    if STOP.is_set():
        raise KeyboardInterrupt
    STOP.set()


# s: how long each wait of a bring-up may take before it stops the run, naming what it still waits
# for (a node's set-up, discovery, the first messages); the tests that watch a bring-up wait longer
BRINGUP_TIMEOUT = 60.0
# s: the run's own endpoints unchanged this long before the motors are enabled (their discovery over)
GRAPH_SETTLE = 2.0
# s: how long nodes of the run's names from another process may stay before the bring-up gives up:
# a process that ended without saying goodbye (killed) stays in the graph until its participant's
# lease runs out (Fast DDS: 20 s)
TWIN_GRACE = 30.0


def _wait_for_graph(node, children, flowing: tuple = (), settle: float = 0.0,
                    timeout: float = BRINGUP_TIMEOUT,
                    published: tuple = ("command", "reference", "state", "markers"),
                    twin_grace: float = TWIN_GRACE):
    """Until the graph is wired: a publisher of the run's own nodes on each of the ``published``
    topics (names of ``TOPICS``: by default the controller's and the plant's; a node creates them
    once its set-up is done), the run's recorder, messages arriving on the ``flowing``
    topics (names of ``TOPICS``: e.g. the controller answering the motors' state), and, with
    ``settle`` [s], no endpoint of the run's own nodes appearing or going for that long (their
    discovery over; other nodes on the domain, a ``ros2 topic echo`` or an RViz coming and going,
    are not waited for). Nodes of the run's names in the root namespace from another process
    (:func:`_own_nodes`) are waited out for ``twin_grace`` [s] (a process killed just before stays in
    the graph until its lease runs out), then the bring-up fails naming them. The probe
    subscriptions on the ``flowing`` topics leave the graph as soon as their messages have
    arrived, before it settles: kept, they would cost this process a callback per message for the
    whole run (tendon/command at the inner loop's rate and the mocap frames: a quarter of a core on
    a 2-core lab PC, bench_emulated_rig.py), and their leaving is one more change of the graph.
    RuntimeError when a node exits or after ``timeout`` [s], naming what is still missing or which
    node's endpoints kept changing. Returns the monotonic time [s] at which the run's own endpoints
    last changed (the settle counts from there)."""
    import rclpy

    from soft_arm_ros.contract import QOS, TOPICS, TYPES, message_class
    topics = ["/" + TOPICS[k] for k in published]
    counts, probes = {}, []
    for key in flowing:
        topic = TOPICS[key]
        counts[topic] = 0
        probes.append(node.create_subscription(
            message_class(TYPES[topic]), topic,
            lambda msg, topic=topic: counts.__setitem__(topic, counts[topic] + 1), QOS[topic]))
    deadline = time.monotonic() + timeout
    graph, since, changed = None, time.monotonic(), []
    names = children.node_names()
    twins_since = None
    while not STOP.is_set():
        children.check()
        now, twins = _own_nodes(node, names)
        twins_since = None if not twins else (twins_since or time.monotonic())
        if twins and time.monotonic() - twins_since > twin_grace:
            raise RuntimeError(
                f"another process has nodes named {', '.join('/' + n for n in twins)} on this ROS domain "
                f"(ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')}: another run, or nodes left "
                f"over, for {twin_grace:g} s): the run cannot tell its own from them; stop them, or run "
                "on another domain")
        # the run's own nodes' publishers and recorder: another process on the domain (a bag of an
        # earlier run played, a recorder left running) wires nothing of this run
        published_here = {t for publishers, _, _ in now.values() for t in publishers}
        missing = [t for t in topics if t not in published_here]
        missing += [f"{t} (no messages yet)" for t, n in counts.items() if n < 10]
        if "recorder" not in now:
            missing.append("the recorder")
        if now != graph:
            if graph is not None:
                changed = sorted(set(now.items()) ^ set(graph.items()))
            graph, since = now, time.monotonic()
        if twins:
            missing.append(f"the leaving of the other nodes named {twins}")
        if not missing and (probes or time.monotonic() - since >= settle):
            break
        if time.monotonic() > deadline:
            raise RuntimeError(
                f"the graph is not up after {timeout:g} s: " + (
                    f"nothing on {missing}" + _nameless_publishers(node, [t for t in topics if t in missing])
                    if missing else
                    f"the endpoints of {sorted({name for name, _ in changed})} keep changing "
                    f"(last {time.monotonic() - since:.1f} s ago; {settle:g} s without a change wanted)"))
        rclpy.spin_once(node, timeout_sec=0.05)
    else:
        return since
    if probes:
        for probe in probes:
            node.destroy_subscription(probe)
        return _wait_for_graph(node, children, settle=settle, timeout=min(timeout, settle + 30.0),
                               published=published)
    return since


def _nameless_publishers(node, topics) -> str:
    """What a bring-up that timed out says of the publishers on the missing ``topics`` that this
    process discovered without learning their nodes ("" if none): their endpoints arrived, the
    descriptions of their processes' nodes (each process's ros_discovery_info) did not within the
    bring-up, so that the run's nodes could not be recognised. Most likely the middleware failed
    between the processes at their start (with Fast DDS, one known cause is a shared-memory port
    whose lock a process held past the middleware's 2 s timeout on a loaded machine,
    eProsima/Fast-DDS#6117, reported as an ``RTPS_TRANSPORT_SHM Error``); a new run starts new
    processes."""
    count = sum(info.node_name == UNKNOWN_NODE for topic in topics
                for info in node.get_publishers_info_by_topic(topic))
    if not count:
        return ""
    return (f"; {count} publisher{'s' if count > 1 else ''} on them whose node this process never "
            f"learnt: the processes' descriptions of their nodes did not reach it (most likely the "
            f"middleware failed between the processes at their start: look for its errors above): "
            f"run again")


def _own_nodes(node, names) -> tuple:
    """The run's own nodes ``names`` (in the root namespace, where the run starts them) as this
    process has discovered them, from one look at the graph: ({node name: its publishers,
    subscriptions and services}, the names more than one node has there). The domain's other nodes
    are left out, those of the same names in other namespaces too; a name two nodes have is the
    run's and another process's (another run, or a node left over), which the run cannot tell
    apart, nor the services it calls by name."""
    seen = [name for name, namespace in node.get_node_names_and_namespaces()
            if name in names and namespace == "/"]
    endpoints = {name: tuple(tuple(sorted(t for t, _ in query(name, "/"))) for query in (
        node.get_publisher_names_and_types_by_node, node.get_subscriber_names_and_types_by_node,
        node.get_service_names_and_types_by_node)) for name in set(seen)}
    return endpoints, sorted({name for name in seen if seen.count(name) > 1})


class _NoAnswer(RuntimeError):
    """A service was found but its answer did not come in time."""


def _call(node, client, request, timeout: float = 10.0, checked: bool = True):
    """Call a service through ``client`` and return its response; RuntimeError if it is not there,
    :class:`_NoAnswer` if it does not answer, or (``checked``) if it answers ``success = False``."""
    import rclpy
    if not client.wait_for_service(timeout_sec=timeout):
        raise RuntimeError(f"service {client.srv_name} is not available")
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if not future.done() or future.result() is None:
        raise _NoAnswer(f"service {client.srv_name} did not answer within {timeout:g} s")
    response = future.result()
    if checked and not response.success:
        raise RuntimeError(f"{client.srv_name} refused" + (f": {response.message}"
                                                           if getattr(response, "message", "") else ""))
    return response


def _wait_for_services(node, children, clients, timeout: float = BRINGUP_TIMEOUT):
    """Until every client's server is discovered (a node's set-up done); RuntimeError when a node
    exits or after ``timeout`` [s]."""
    import rclpy
    deadline = time.monotonic() + timeout
    while not STOP.is_set():
        children.check()
        missing = [c.srv_name for c in clients if not c.service_is_ready()]
        if not missing:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"services {missing} are not available after {timeout:g} s")
        rclpy.spin_once(node, timeout_sec=0.05)


# the state a lifecycle transition ends in, by its label
GOAL_STATES = {"configure": "inactive", "activate": "active", "deactivate": "inactive",
               "cleanup": "unconfigured"}


def _change_state(node, client, label: str, timeout: float = 10.0):
    """Ask a managed node for the lifecycle transition ``label`` (as ``ros2 lifecycle set``);
    RuntimeError if it fails (the node logs why). An answer that does not come within ``timeout``
    [s] is checked against the node's state (``get_state``): a response lost in discovery (the
    server answered before it knew the client) is no failure when the node is in the transition's
    goal state."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import GetState
    name = client.srv_name.rsplit('/', 2)[-2]
    request = client.srv_type.Request(transition=Transition(label=label))
    try:
        _call(node, client, request, timeout)
    except _NoAnswer as exc:
        getter = node.create_client(GetState, client.srv_name.replace("change_state", "get_state"))
        try:
            state = _call(node, getter, GetState.Request(), timeout, checked=False).current_state.label
        except RuntimeError:
            state = None
        finally:
            node.destroy_client(getter)
        if state != GOAL_STATES.get(label):
            raise RuntimeError(f"{label} of {name} failed: {exc} (see that node's log)") from None
        print(f"soft-arm-experiment: {label} of {name}: no answer within {timeout:g} s, but {name} is "
              f"{state}: going on", file=sys.stderr)
    except RuntimeError as exc:
        raise RuntimeError(f"{label} of {name} failed: {exc} (see that node's log)") from None


def _start(node, client, timeout: float = 10.0):
    """Start the runner through its ``~/start`` ``client``; RuntimeError if it refuses. An answer
    that does not come within ``timeout`` [s] was lost in discovery or the call never arrived: the
    call is made again, and the runner's ALREADY_STARTED then says that the first one took effect."""
    from std_srvs.srv import Trigger

    from soft_arm_ros.contract import ALREADY_STARTED
    try:
        _call(node, client, Trigger.Request(), timeout)
    except _NoAnswer as exc:
        response = _call(node, client, Trigger.Request(), timeout, checked=False)
        if not response.success and response.message != ALREADY_STARTED:
            raise RuntimeError(f"{client.srv_name} refused: {response.message}") from None
        print(f"soft-arm-experiment: {exc}; asked again, it is started: going on", file=sys.stderr)


# the nodes of a process whose console script is not named after its one node
_PROCESS_NODES = {"emulated_rig": ("motor_driver",)}


STOP_TIMEOUT = 10.0      # s, from the SIGINT to a node until it is killed (exit_failure names it)
STACKS_WAIT = 1.0        # s, for a node that did not stop to write its stacks before it is killed


class _Children:
    """The node processes of one run (the console scripts' modules with the run's arguments), on
    loopback, forked from the run's :class:`~.fork_server.ForkServer` (started with the first);
    ``realtime``: the SCHED_FIFO priorities of the processes that have one (their CPUs given by
    :meth:`go_realtime`, once they are set up), the others at ``niceness`` (where permitted)."""

    def __init__(self, ros_args: list, extra: dict, realtime: dict | None = None, niceness: int = 0):
        self.ros_args, self.extra, self.realtime = ros_args, extra, realtime or {}
        self.niceness = niceness
        self.env = node_environment()
        self.procs: dict = {}
        self.server = None
        # name: exit status, once stop() has ended them (-9: killed); a run's facts hold this dict
        # itself, which stop() fills after the run returns them (in _orchestrating's way out)
        self.exits: dict = {}

    def node_names(self) -> set:
        """The names of the nodes the started processes run (the emulated rig's: motor_driver)."""
        return {node for name in self.procs for node in _PROCESS_NODES.get(name, (name,))}

    def start(self, name: str):
        """Start a node, forked as :mod:`.fork_server` says (a process group of its own, SIGINT
        when this process ends, its threads' stacks on :data:`STACKS_SIGNAL`), under SCHED_FIFO
        if it has a priority, else at the niceness: set before the node's module runs, so that
        every thread of the node inherits it."""
        if self.server is None:
            self.server = ForkServer(self.env)
        self.procs[name] = self.server.start(
            name, node_module(name), self.ros_args + self.extra.get(name, []), fifo=self.realtime.get(name),
            niceness=0 if name in self.realtime else self.niceness)

    def go_realtime(self):
        """Once the nodes are set up: every thread of the real-time nodes of the motors' loop off
        the emulated hardware's CPU, the emulated hardware (emulated_rig's child process) at
        HARDWARE_PRIORITY on that CPU, and the nodes of :data:`realtime.BESIDE_HARDWARE` (the mocap
        bridge) on it too, and the middleware threads of every other node, and of this process,
        just above the normal policy (:mod:`.realtime` says why)."""
        off = realtime.hardware_cpu()
        nodes = None if off is None else os.sched_getaffinity(0) - {off}
        for name, priority in self.realtime.items():
            pid = self.procs[name].pid
            beside = name in realtime.BESIDE_HARDWARE and off is not None
            realtime.schedule(pid, priority, {off} if beside else nodes)
            if name == "emulated_rig":
                for hardware in realtime.child_processes(pid):
                    realtime.schedule(hardware, realtime.HARDWARE_PRIORITY, None if off is None else {off})
        if not self.realtime:
            return                  # real time not permitted: the middleware's threads too stay put
        others = [proc.pid for name, proc in self.procs.items() if name not in self.realtime]
        for pid in others + [os.getpid()]:
            realtime.schedule(pid, realtime.MIDDLEWARE_PRIORITY, named=realtime.MIDDLEWARE_THREADS)

    def check(self, may_end=()):
        """RuntimeError if a node exited (those in ``may_end`` with status 0 may), or the fork server
        they were forked from (its nodes end with it)."""
        if self.server is not None:
            self.server.check()
        for name, proc in self.procs.items():
            if proc.poll() is not None and not (name in may_end and proc.returncode == 0):
                raise RuntimeError(f"node {name} exited with status {proc.returncode}")

    def stop(self, timeout: float = STOP_TIMEOUT):
        """SIGINT to every node still running; SIGKILL to those not gone ``timeout`` [s] later, once
        each has written where its threads are (:data:`STACKS_SIGNAL`, at most
        :data:`STACKS_WAIT` [s]) under a line that names it. Keeps each one's exit status in
        :attr:`exits`: a node whose shutdown failed (a driver whose zero-torque frames did not
        leave, a recorder that could not close its bag) says so there."""
        try:
            self._stop(timeout)
        finally:
            if self.server is not None:
                self.server.close()

    def _stop(self, timeout: float):
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for name, proc in self.procs.items():
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                print(f"soft-arm-experiment: node {name} did not stop within {timeout:g} s; its "
                      "threads as it hangs:", file=sys.stderr, flush=True)
                proc.send_signal(STACKS_SIGNAL)
                try:
                    proc.wait(timeout=STACKS_WAIT)
                except subprocess.TimeoutExpired:
                    pass
                proc.kill()
                proc.wait()
            self.exits[name] = proc.returncode


def exit_failure(exits: dict) -> str | None:
    """What the nodes' exit statuses (name: status, :attr:`_Children.exits`) say went wrong on the
    way out; None when every one is 0."""
    bad = [f"node {name} " + (f"was killed (it did not stop within {STOP_TIMEOUT:g} s)"
                              if code == -signal.SIGKILL else
                              "ended after the node fork server, its exit status lost" if code == STATUS_LOST
                              else f"exited with status {code}")
           for name, code in exits.items() if code != 0]
    return "; ".join(bad) or None


@contextlib.contextmanager
def _orchestrating(children: _Children, nodes: tuple):
    """This process's node (graph queries, service calls) for a run of ``children``, whose node
    processes are ``nodes``, once the domain has room for them and this one
    (:func:`soft_arm_ros.localhost_discovery.check_room`: RuntimeError, before anything starts, if
    not); on the way out, whatever happened, the node and rclpy go, then the children are stopped."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from soft_arm_ros.localhost_discovery import check_room
    check_room(participants(nodes), children.env)
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


# The nodes that answer the plant, and the one that plays the run and writes its result (parameter
# ``output``), of a task and of the identification experiment (``soft-arm-experiment identification``)
ROLES = {"task": (("inner_loop", "clik"), "task_runner"), "identification": ((), "excitation")}


# what the clik's mocap/markers is remapped onto for each feedback (soft-arm-experiment --feedback;
# the names of soft_arm_ros.contract.TOPICS, which this module imports only where it uses rclpy)
FEEDBACK_TOPICS = {"mocap": None, "fused": "fused/markers", "estimate": "estimate/markers"}


def roles(task: str, feedback: str = "mocap") -> tuple:
    """(controller nodes, runner node) of a run of ``task``; the shape estimator is a controller
    node when the online CLIK's ``feedback`` is not the mocap."""
    controller, runner = ROLES["identification" if task == IDENTIFICATION else "task"]
    if controller and FEEDBACK_TOPICS[feedback] is not None:
        controller = controller + ("shape_estimator",)
    return controller, runner


def node_environment() -> dict:
    """The environment of a run's node processes: this one's, their discovery kept on this computer."""
    return dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")


def node_processes(task: str, feedback: str = "mocap", emulated_hardware: bool = False) -> tuple:
    """The node processes of a run of ``task`` with the simulator (:func:`run_processes`) or the
    emulated rig (:func:`run_emulated_hardware`) in the order they start, the runner last; the
    orchestrator's own process comes beside them."""
    controller, runner = roles(task, feedback)
    if emulated_hardware:
        return ("recorder", "emulated_rig", "mocap_bridge", *controller, runner)
    return ("recorder", *controller, "simulator", runner)


def participants(nodes: tuple) -> int:
    """The processes on ROS of a run whose node processes are ``nodes`` (:func:`node_processes`):
    theirs and the orchestrator's."""
    return len(nodes) + 1


def feedback_arguments(feedback: str) -> list:
    """The clik's arguments (after ``--ros-args``) that close its loop on ``feedback``: the remapping
    of its mocap/markers, and ``control.clik.feedback``, which puts an estimate under the trust
    region (:mod:`soft_arm_control.trust_region`)."""
    topic = FEEDBACK_TOPICS[feedback]
    if topic is None:
        return []
    return ["-r", f"mocap/markers:={topic}", "-p", f"control.clik.feedback:={feedback}"]


# how many times its duration a run of processes may take before it is stopped as stalled: the
# simulator keeps to graph.simulator.max_real_time_factor (1), and a loaded computer slows it further
PROCESSES_SLOWDOWN = 10.0


def run_processes(ros_args: list, out: dict, task: str = "", feedback: str = "mocap",
                  duration: float = math.inf) -> dict:
    """Each node its own process, the same parameters: the recorder, the controller's nodes and the
    simulator start; once the graph is wired (the controller's, the plant's and the recorder's
    endpoints exist) the runner (task runner, or excitation for the identification experiment)
    starts, waiting for ``~/start``; once its publisher is known and discovery has settled it is
    started (in lockstep the plant runs as fast as the graph answers: a goal discovered late would
    reach the controller seconds of simulated time after the window began). Waits for its result
    (RuntimeError if not within :data:`PROCESSES_SLOWDOWN` times the task's ``duration`` [s] and a
    minute), then stops the nodes with SIGINT."""
    from std_srvs.srv import Trigger
    controller, runner = roles(task, feedback)
    children = _Children(ros_args, {
        "recorder": ["-p", f"output:={out['bag']}", "-p", "use_sim_time:=true"],
        runner: ["-p", f"output:={out['metrics']}", "-p", "wait_for_start:=true"],
        "clik": feedback_arguments(feedback)})
    start = time.monotonic()
    nodes = node_processes(task, feedback)
    plant_side = nodes[:-1]                                      # the runner starts once they are up
    with _orchestrating(children, nodes) as node:
        begin = node.create_client(Trigger, f"/{runner}/start")
        for name in plant_side:
            children.start(name)
        _wait_for_graph(node, children, published=("command", "reference", "state", "markers")
                        if controller else ("state", "markers"))
        if STOP.is_set():
            return {"wall_s": time.monotonic() - start, "node_exits": children.exits}
        children.start(runner)
        _wait_for_graph(node, children, settle=0.5, published=("goal",) if controller else ("command",))
        if not STOP.is_set() and not begin.wait_for_service(timeout_sec=10.0):
            raise RuntimeError(f"service {begin.srv_name} is not available")
        if not STOP.is_set():
            _start(node, begin)
        limit = PROCESSES_SLOWDOWN * duration + 60.0
        _await_result(node, children, out["metrics"], limit,
                      f"the {runner} node wrote no result within {limit:g} s "
                      f"({PROCESSES_SLOWDOWN:g} times the run's {duration:g} s and a minute)")
    return {"wall_s": time.monotonic() - start, "node_exits": children.exits}


def _await_result(node, children, path: str, limit: float, late: str, until=lambda: False,
                  period: float = 0.2):
    """Spin ``node`` (``period`` [s] at a time), checking that ``children`` live, until the result
    file ``path`` exists, :data:`STOP` is set or ``until()`` is true; RuntimeError(``late``) if none
    of them within ``limit`` [s] on the monotonic clock."""
    import rclpy
    deadline = time.monotonic() + limit
    while not STOP.is_set() and not until() and not os.path.exists(path):
        children.check()
        if time.monotonic() > deadline:
            raise RuntimeError(late)
        rclpy.spin_once(node, timeout_sec=period)


def run_emulated_hardware(ros_args: list, out: dict, duration: float,
                          config_dir: str | None = None, task: str = "", arm_file: str | None = None,
                          feedback: str = "mocap") -> dict:
    """The rig's graph in real time, each node its own process, with the ``emulated_rig`` (the
    motor_driver node with the CAN motor emulators and the NatNet server emulator behind it,
    :mod:`.emulated_rig`) and the ``mocap_bridge`` in the simulator's place; ``duration`` [s]: the
    task's, ``task``: its name (the identification experiment has the excitation node in the
    controller's and the task runner's place), ``config_dir``: where rig.yaml, mocap.yaml and
    emulator.yaml are (default: the package's), ``arm_file``: the controller's arm file, whose mocap
    calibration (if it has one) the bridge uses.

    As an operator runs the rig: every node starts (the task runner waiting for ``~/start``); the
    managed drivers are configured (the motor driver finds its motors, the bridge its Motive server)
    and the bridge activated; once the graph is wired and settled and the controller answers the
    motors' state, the motors are zeroed (tendons slack), the motor driver is activated and the task
    starts; when the task runner has written the metrics (RuntimeError if not within ``duration`` +
    60 s) the motor driver is deactivated (refused or unanswered, without a fault recorded: a fault
    of the run, :func:`_deactivate_at_end`), then the nodes are stopped. No process joins or leaves
    the graph while the motors are enabled: DDS discovery can hold a publisher, the driver's
    included, for a few hundred ms. A fault the driver latches while the motors are enabled
    (watchdog, motor error, e-stop) ends the run at once, the driver inactive: the faults are
    printed as they latch and listed in the run facts (``driver_faults``: message and ``time_s``
    after the enable), and a faulted run is no result (the caller marks its metrics invalid)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from lifecycle_msgs.srv import ChangeState
    from std_srvs.srv import Trigger

    from soft_arm_ros.conversions import stamp_to_seconds

    d = config_dir or default_config_dir()
    files = [a for name in ("rig.yaml", "mocap.yaml", "emulator.yaml")
             for a in ("--params-file", os.path.join(d, name))]
    port, = free_udp_ports(1)                     # the emulated Motive server's
    fifo = realtime.permitted(max(_REALTIME.values()))
    if not fifo:
        print("soft-arm-experiment: real-time scheduling is not permitted here (it needs root, "
              "CAP_SYS_NICE or an rtprio limit): a busy computer may hold the emulated hardware "
              "long enough for the motor driver's watchdog to trip", file=sys.stderr)
    controller, runner = roles(task, feedback)
    children = _Children(ros_args, {
        "clik": feedback_arguments(feedback),
        "recorder": ["-p", f"output:={out['bag']}"],
        runner: ["-p", f"output:={out['metrics']}", "-p", "wait_for_start:=true"],
        # the one node whose commands the driver takes: the inner loop, or the excitation
        "emulated_rig": files + ["-p", f"rig.mocap.command_port:={port}",
                                 "-p", f"rig.motors.command_publisher:=/{(controller or (runner,))[0]}"],
        # the bridge takes the mocap calibration of an arm file (an identified one) over mocap.yaml's;
        # the emulated Motive stays in the rig's frame, that of mocap.yaml
        "mocap_bridge": files + (["--params-file", os.path.abspath(arm_file)] if arm_file else [])
        + ["-p", f"rig.mocap.command_port:={port}", "-p", "rig.mocap.data_port:=0"]},
        _REALTIME if fifo else None, _NICENESS if fifo else 0)
    watch = DriverFaultWatch()
    faults = watch.faults
    start = time.monotonic()

    settling = {}                          # s from the drivers' set-up: own endpoints quiet, settled, enabled

    def facts():
        return {"wall_s": time.monotonic() - start, "emulated_hardware": True, "realtime": fifo,
                "driver_faults": faults, **settling, "node_exits": children.exits}

    def on_diagnostics(msg):
        """Print the motor driver's faults latched while the motors are enabled, and its leaving the
        active state while the task runs (``ros2 lifecycle set`` from elsewhere):
        :class:`DriverFaultWatch`."""
        stamp = stamp_to_seconds(msg.header.stamp)
        for status in msg.status:
            if status.name != "motor_driver":
                continue
            state = next((kv.value for kv in status.values if kv.key == "lifecycle_state"), "active")
            fault = watch.status(stamp, status.level == DiagnosticStatus.ERROR, status.message, state)
            if fault is not None:
                print(f"\nsoft-arm-experiment: motor_driver {fault['message']} "
                      f"({fault['time_s']:.2f} s after the enable): the run ends", file=sys.stderr)

    started = node_processes(task, feedback, emulated_hardware=True)
    with _orchestrating(children, started) as node:
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        # every client is created, and its server discovered, before the motors are enabled
        zero = node.create_client(Trigger, "/motor_driver/zero")
        driver = node.create_client(ChangeState, "/motor_driver/change_state")
        bridge = node.create_client(ChangeState, "/mocap_bridge/change_state")
        begin = node.create_client(Trigger, f"/{runner}/start")
        for name in started:
            children.start(name)
        # the whole bring-up within BRINGUP_TIMEOUT, each wait naming what it still waits for
        deadline = time.monotonic() + BRINGUP_TIMEOUT

        def left() -> float:
            return max(1.0, deadline - time.monotonic())
        _wait_for_services(node, children, (zero, driver, bridge, begin), timeout=left())
        if STOP.is_set():
            return facts()
        for client, label in ((driver, "configure"), (bridge, "configure"), (bridge, "activate")):
            _change_state(node, client, label, timeout=min(10.0, left()))
        drivers_up = time.monotonic()
        quiet_from = _wait_for_graph(node, children, ("command", "markers"), settle=GRAPH_SETTLE,
                                     timeout=left(), published=("command", "reference", "state", "markers")
                                     if controller else ("command", "state", "markers"))
        settling["graph_settled_s"] = round(time.monotonic() - drivers_up, 3)
        settling["graph_quiet_s"] = round(quiet_from - drivers_up, 3)
        if STOP.is_set():
            return facts()
        children.go_realtime()
        _call(node, zero, Trigger.Request(), timeout=min(10.0, left()))
        try:
            _change_state(node, driver, "activate", timeout=min(10.0, left()))
            watch.enabled(time.time(), time.monotonic())
            settling["motors_enabled_s"] = round(time.monotonic() - drivers_up, 3)
            watch.driving = True
            _start(node, begin)
            _await_result(node, children, out["metrics"], duration + 60.0,
                          f"the {runner} node wrote no result within {duration + 60.0:g} s",
                          until=lambda: bool(faults), period=0.1)
        finally:
            watch.driving = False
            _deactivate_at_end(node, driver, watch)
    return facts()


class DriverFaultWatch:
    """What the motor driver's ``/diagnostics`` say of a run on the emulated rig (ROS-free): a fault
    it latches while the motors are enabled, or its leaving the active state while the task runs
    (:attr:`driving`), each kept once in :attr:`faults` (``message``, ``time_s`` after the enable on
    this process's monotonic clock): a faulted run is no result.

    A status counts once the motors are enabled: stamped (the driver's clock, the system time on
    this computer) at or after the enable's system time, or coming after a status of the active
    driver that came after the enable. The stamp alone would let a system clock stepped back after
    the enable hide every fault for the step's length; the active driver's status alone would miss
    a fault that deactivates the driver before it reports itself active. A status of before the
    enable (queued, the fault the enable cleared) is neither."""

    def __init__(self):
        self.faults: list = []
        self.driving = False               # the task runs on active motors
        self._enabled_at = math.inf        # system time [s] of the enable
        self._enabled_mono = math.inf      # this process's monotonic time [s] of the enable
        self._armed = False                # a status of the active driver came after the enable

    def enabled(self, system_time: float, monotonic: float):
        """The motors were enabled (the driver's activate answered) at these times [s]."""
        self._enabled_at, self._enabled_mono = float(system_time), float(monotonic)

    @property
    def was_enabled(self) -> bool:
        return math.isfinite(self._enabled_mono)

    def since_enabled(self) -> float:
        """Seconds since the enable on this process's monotonic clock."""
        return time.monotonic() - self._enabled_mono

    def status(self, stamp: float, error: bool, message: str, lifecycle_state: str):
        """One ``motor_driver`` status, stamped ``stamp`` [s, the driver's clock]: ``error`` its
        level, ``message``, the node's ``lifecycle_state``. The fault it adds (a dict) or None."""
        if self.was_enabled and lifecycle_state == "active":
            self._armed = True
        if not (self._armed or stamp >= self._enabled_at):
            return None
        text = message if error else (f"left the active state ({lifecycle_state}) while the task ran"
                                      if self.driving and lifecycle_state != "active" else None)
        if text is None or any(f["message"] == text for f in self.faults):
            return None
        fault = {"message": text, "time_s": round(self.since_enabled(), 3)}
        self.faults.append(fault)
        return fault


def _deactivate_at_end(node, driver, watch: DriverFaultWatch):
    """Deactivate the motor driver (through its change_state ``driver`` client) at a run's end.
    Refused after a fault the run recorded, it is expected: the fault deactivated the driver. Refused
    or unanswered otherwise, the motors' end is unknown to the run (a fault it has not yet heard of,
    a driver that hangs): once the motors were enabled that is recorded in ``watch.faults`` (a
    faulted run is no result)."""
    try:
        _change_state(node, driver, "deactivate", timeout=2.0)
    except RuntimeError as exc:
        print(f"soft-arm-experiment: motor_driver deactivate: {exc}", file=sys.stderr)
        if not watch.faults and watch.was_enabled:
            watch.faults.append({"message": f"not deactivated at the run's end: {exc}",
                                 "time_s": round(watch.since_enabled(), 3)})


# Real time on a shared computer: the processes the loop closes through (the motor driver, in
# emulated_rig, the mocap bridge and the inner loop) run under SCHED_FIFO where the system permits
# it, on their CPUs once they are set up (realtime.py says why and how). On the rig, run motor_driver,
# mocap_bridge and inner_loop the same way (README, "On the rig, and on the emulated rig").
_REALTIME = {"emulated_rig": 30, "inner_loop": 20, "mocap_bridge": 20}
# The other nodes (recorder, clik, task runner) run ahead of a lab PC's other work: at niceness 0,
# beside one CPU-bound process, the recorder loses up to 30 % of the messages
# (docs/decisions/0003-emulated-hardware-runs-below-the-nodes-on-a-cpu-of-its-own.md).
_NICENESS = -10


def node_module(name: str) -> str:
    """The module of the node console script ``name``, from the package's entry points (setup.py is
    their one source); ConfigError if no such script is installed."""
    found = [ep for ep in importlib.metadata.entry_points(group="console_scripts", name=name)
             if ep.value.startswith("soft_arm_")]
    if not found:
        raise ConfigError(f"no soft_arm console script {name!r} is installed (pip install -e .)")
    return found[0].value.partition(":")[0]
