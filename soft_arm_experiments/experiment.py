"""``soft-arm-experiment <task>``: the main job. Runs one of the paper's experiments as the ROS 2
graph on the simulator, records the bag, writes the metrics and the figures.

By default all nodes (simulator, inner_loop, clik, task_runner, recorder) are composed in this
process and run in lockstep waves (deterministic: the same seed gives the same messages);
``--processes`` starts each node as its own process with the same parameters instead (the
simulator still steps once per command, over DDS). ``--emulated-hardware`` runs the rig's graph in
real time, one process per node, with the motor driver and the mocap bridge talking to emulated
CAN motors and an emulated Motive server in the simulator's place
(:mod:`soft_arm_drivers.sim.emulated_rig`; the process runs are in :mod:`.orchestration`).
Output (``--output DIR``, default ``runs/<task>-<UTC time>``): ``bag/`` (rosbag2, MCAP),
``metrics.json``, ``figures/*.png``. Prints a progress line (composed runs), the paper-style table
and the paths (``--json``: the metrics as JSON on stdout). Ctrl-C stops everything cleanly (the
emulated motors are disabled first) and keeps what was recorded (exit status 130). A bad parameter
or an unreachable target exits with status 2; a node that dies or a run that cannot go on, with 1.

``soft-arm-experiment calibrate [--rerun TASK]`` closes the loop: the identification experiment,
soft-arm-identify on its bag, then the task (default: triangle) with the identified arm as the
controller's model, each in the same way (``--processes``, ``--emulated-hardware``, ``--set``).

``--live [HOST:]PORT`` serves the run to the Foxglove app while it runs (the live_view node in a
process of its own, :mod:`.live_launch`) and writes the same view into ``view.mcap`` of the run.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import signal
import sys
import threading
import time
import traceback

from soft_arm_control.config import IDENTIFICATION
from soft_arm_model.config import write_arm_file
from soft_arm_model.parameters import ConfigError, default_config_dir

from .metrics import Summary, TrackingMetrics, TransitionMetrics, format_table, format_tracking
from .strike import PLANNED_ON_THE_GRAPH, format_strike
from .harness import add_setup_arguments, check_targets, load_setup, setup_overrides
from .live_launch import add_live_argument, live_view, parse_address
from .excitation import Excitation
from .orchestration import (STOP, exit_failure, feedback_arguments, node_environment, node_processes,
                            participants, request_stop, roles, run_emulated_hardware, run_processes)
from .writable import writable_directory

NAMESPACES = ("arm", "control", "plant", "tasks", "graph", "identification", "estimator")


def _ros_arguments(task: str, sets, config_dir: str | None, arm_file: str | None = None) -> list:
    """--ros-args for every node: the package's parameter files (``arm_file`` for arm.yaml, last, so
    that the estimator priors it carries replace estimator.yaml's), the task and the overrides."""
    d = config_dir or default_config_dir()
    args = ["--ros-args"]
    for name in NAMESPACES:
        if not (name == "arm" and arm_file):
            args += ["--params-file", os.path.join(d, f"{name}.yaml")]
    if arm_file:
        args += ["--params-file", os.path.abspath(arm_file)]
    args += ["-p", f"graph.task:={task}"]
    for pair in sets:
        key, sep, value = pair.partition("=")
        if not sep or key.split(".")[0] not in NAMESPACES:
            raise ConfigError(f"--set expects namespace.key=value with namespace one of "
                              f"{', '.join(NAMESPACES)}; got {pair!r}")
        args += ["-p", f"{key}:={value}"]
    return args


def _progress(t: float, total: float):
    print(f"\r  simulated {t:6.1f} / {total:.1f} s", end="", file=sys.stderr, flush=True)


def _shut_down(nodes, executor):
    """End a composed run whatever stopped it: the task runner writes what it has, every node
    closes (the recorder its bag), then the executor, the nodes and rclpy go. Each step runs
    whatever the one before raised (a runner that cannot write its result still leaves the bag
    closed), with SIGINT and SIGTERM ignored (a second Ctrl-C does not cut the bag short); the first
    error is raised at the end."""
    import rclpy
    held = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)} \
        if threading.current_thread() is threading.main_thread() else {}
    errors = []

    def attempt(step, *args):
        try:
            step(*args)
        except Exception as exc:          # noqa: BLE001 -- kept, raised once everything is closed
            errors.append(exc)
    try:
        for node in nodes:
            finish = getattr(node, "finish", None)
            if finish is not None and not node.done:
                attempt(finish)
            close = getattr(node, "close", None)
            if close is not None:
                attempt(close)
        if executor is not None:
            attempt(executor.shutdown)
        for node in nodes:
            attempt(node.destroy_node)
        attempt(rclpy.try_shutdown)
    finally:
        for sig, handler in held.items():
            signal.signal(sig, handler)
    if errors:
        raise errors[0]


def run_composed(ros_args: list, out: dict, progress=None, config_dir: str | None = None,
                 node_args: dict | None = None, task: str = "", feedback: str = "mocap") -> dict:
    """All nodes of a run of ``task`` (:func:`~.orchestration.roles`) in this process, lockstep
    waves. Returns run facts (simulated time, waves...).

    ``node_args``: extra command-line arguments per node name (e.g. remaps:
    ``{"simulator": ["--ros-args", "-r", "__ns:=/hw"]}``); ``feedback``: what the clik closes its
    loop on (:func:`~.orchestration.feedback_arguments`).
    """
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from soft_arm_control.clik_node import ClikNode
    from soft_arm_control.inner_loop_node import InnerLoopNode
    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_drivers.recording.recorder_node import RecorderNode
    from soft_arm_drivers.sim.simulator_node import SimulatorNode

    from .excitation_node import ExcitationNode
    from .lockstep import WaveExecutor
    from .task_runner_node import TaskRunnerNode

    classes = {"inner_loop": InnerLoopNode, "clik": ClikNode, "task_runner": TaskRunnerNode,
               "excitation": ExcitationNode, "shape_estimator": ShapeEstimatorNode}
    controller, runner_name = roles(task, feedback)

    # Ctrl-C stays Python's KeyboardInterrupt (no rclpy handler shutting the context mid-wave), so
    # that the shutdown below always runs in order.
    rclpy.init(args=["soft-arm-experiment"] + ros_args, signal_handler_options=SignalHandlerOptions.NO)
    nodes, executor = [], None
    try:
        node_args = dict(node_args or {})
        if feedback_arguments(feedback):
            node_args["clik"] = (node_args.get("clik") or ["--ros-args"]) + feedback_arguments(feedback)

        def options(name):
            return {"start_parameter_services": False, "cli_args": node_args.get(name)}

        sim = SimulatorNode(config_dir, in_waves=True, **options("simulator"))
        nodes.append(sim)
        nodes += [classes[name](config_dir, **options(name)) for name in controller]
        runner = classes[runner_name](config_dir, parameter_overrides=[
            Parameter("output", value=out["metrics"])], **options(runner_name))
        recorder = RecorderNode(config_dir, parameter_overrides=[
            Parameter("output", value=out["bag"]), Parameter("use_sim_time", value=True)],
            **options("recorder"))
        nodes += [runner, recorder]
        executor = WaveExecutor(nodes)
        start = time.monotonic()
        # the recorder subscribes to what it discovers: every topic published here, before the first
        # wave (what is published meanwhile is held for it), so that every run records the same
        published = {pub.topic_name for node in nodes for pub in node.publishers}
        while not sim._started or recorder.unsubscribed(published):
            executor.spin_timers(0.01)
            if time.monotonic() - start > 30.0:
                raise RuntimeError(
                    "the simulator did not start within 30 s: it waits for a publisher of tendon/command "
                    "and a subscriber of mocap/markers (the recorder's topics?)" if not sim._started else
                    f"the recorder did not find the publishers of {recorder.unsubscribed(published)} "
                    f"within 30 s")
        last_flush, reported = time.monotonic(), 0
        while not runner.done and not STOP.is_set():
            if executor.wave() == 0:
                raise RuntimeError("the graph went quiet before the experiment ended")
            if progress is not None and sim.rig.t >= reported + 1.0:
                reported = int(sim.rig.t)
                progress(sim.rig.t, runner.core.duration)
            if time.monotonic() - last_flush > 1.0:
                recorder.take()                   # what the waves delivered to it, written
                recorder.writer.flush()
                last_flush = time.monotonic()
        return {"simulated_s": sim.rig.t, "wall_s": time.monotonic() - start, "waves": executor.waves,
                "missing_commands": sim.missing_commands, "messages_recorded": recorder.count}
    finally:
        _shut_down(nodes, executor)


def _load_metrics(path: str):
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    rows = [TransitionMetrics(**r) for r in data["transitions"]]
    return data, rows, Summary(**data["summary"])


CALIBRATE = "calibrate"


def _calibrate(args) -> int:
    """``calibrate``: the identification experiment (``<output>/identification``), the fit
    (``<output>/arm_identified.yaml``, figures in ``identification/fit``) and ``args.rerun``'s task
    with that arm and ``--accept-closest`` (``<output>/<task>``), each run as ``args`` says; stops
    at the first that fails, with its exit status."""
    from .identify_cli import main as identify
    if args.rerun in (CALIBRATE, IDENTIFICATION):
        print(f"soft-arm-experiment: --rerun {args.rerun} is not valid: expected a task of tasks.yaml",
              file=sys.stderr)
        return 2
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
    run_dir = os.path.abspath(args.output or os.path.join("runs", f"{CALIBRATE}-{stamp}"))
    problem = writable_directory(run_dir)
    if problem is not None:
        print(f"soft-arm-experiment: --output {run_dir}: {problem}", file=sys.stderr)
        return 2
    config = ["--config", args.config] if args.config else []
    sets = [a for s in args.sets for a in ("--set", s)]
    common = config + sets + (["--plant-file", args.plant_file] if args.plant_file else []) + \
        ["--feedback", args.feedback] + (["--live", args.live] if args.live else []) + [
        flag for flag, on in (("--processes", args.processes), ("--quiet", args.quiet),
                              ("--emulated-hardware", args.emulated_hardware)) if on]
    start_arm = ["--arm-file", args.arm_file] if args.arm_file else []
    arm_file = os.path.join(run_dir, "arm_identified.yaml")
    ident = os.path.join(run_dir, IDENTIFICATION)
    print(f"soft-arm-experiment calibrate: 1/3 the identification experiment -> {ident}", file=sys.stderr)
    code = main([IDENTIFICATION, "--output", ident] + common + start_arm)
    if code != 0:
        return code
    print(f"soft-arm-experiment calibrate: 2/3 the fit -> {arm_file}", file=sys.stderr)
    fit_sets = [a for s in args.sets if s.split(".")[0] in ("arm", IDENTIFICATION) for a in ("--set", s)]
    code = identify([os.path.join(ident, "bag"), "--output", arm_file, "--plot", os.path.join(ident, "fit")]
                    + config + fit_sets + start_arm)
    if code != 0:
        return code
    rerun = os.path.join(run_dir, args.rerun)
    print(f"soft-arm-experiment calibrate: 3/3 {args.rerun} with the identified arm -> {rerun}",
          file=sys.stderr)
    return main([args.rerun, "--output", rerun, "--arm-file", arm_file, "--accept-closest"] + common
                + (["--json"] if args.json else []))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="soft-arm-experiment", description=__doc__.splitlines()[0])
    parser.add_argument("task", help="task name in tasks.yaml (triangle, coiling, ...), identification, "
                                     "or calibrate (identification, fit, then --rerun's task)")
    parser.add_argument("--rerun", metavar="TASK", default="triangle",
                        help="calibrate: the task rerun with the identified arm (default: triangle)")
    parser.add_argument("--output", metavar="DIR", help="run directory (default: runs/<task>-<time>)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--processes", action="store_true", help="one process per node (simulator)")
    where.add_argument("--emulated-hardware", action="store_true",
                       help="motor driver + CAN emulator and mocap bridge + NatNet emulator in the "
                            "simulator's place (real time; every node a process of its own)")
    add_setup_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress line (composed runs print one)")
    add_live_argument(parser, "the live_view node beside the run")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.task == CALIBRATE:
        return _calibrate(args)
    try:
        args.sets = setup_overrides(args)
        setup = load_setup(args.task, args.config,
                           [s for s in args.sets if not s.startswith("graph.")], args.arm_file)
        closest, notes = check_targets(setup, args.accept_closest)     # before anything moves
        for note in notes:
            print(f"soft-arm-experiment: {note}", file=sys.stderr)
        if closest:
            args.sets += closest
            setup = load_setup(args.task, args.config,
                               [s for s in args.sets if not s.startswith("graph.")], args.arm_file)
        strike = setup.task is not None and setup.task.pendulum is not None
        if strike and setup.task.strike_timing == "planned":
            raise ConfigError(PLANNED_ON_THE_GRAPH)
        if strike and args.emulated_hardware:
            raise ConfigError(f"the emulated rig has no pendulum: run {args.task} on the simulator "
                              "(without --emulated-hardware)")
        ros_args = _ros_arguments(args.task, args.sets, args.config, args.arm_file)
        if args.live is not None:
            parse_address(args.live)
    except (ConfigError, ValueError) as exc:          # TargetError is a ValueError
        print(f"soft-arm-experiment: {exc}", file=sys.stderr)
        return 2
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
    run_dir = os.path.abspath(args.output or os.path.join("runs", f"{args.task}-{stamp}"))
    held = [name for name in ("bag", "metrics.json", "excitation.json")
            if os.path.exists(os.path.join(run_dir, name))]
    if held:                # an earlier run's result would be taken for this one's
        print(f"soft-arm-experiment: {run_dir} already holds a run ({', '.join(held)})", file=sys.stderr)
        return 2
    problem = writable_directory(run_dir)
    if problem is not None:
        print(f"soft-arm-experiment: --output {run_dir}: {problem}", file=sys.stderr)
        return 2
    if args.arm_file and not setup.plant.plant_file:
        # every node's plant is the arm of plant.yaml over arm.yaml, not over the controller's arm
        plant_file = os.path.join(run_dir, "plant_arm.yaml")
        write_arm_file(plant_file, setup.plant.plant_arm(setup.arm),
                       "The simulated plant of this run: plant.yaml over arm.yaml (the controller's "
                       f"arm is {os.path.abspath(args.arm_file)}).")
        ros_args += ["-p", f"plant.plant_file:={plant_file}"]
    result = "metrics.json" if setup.task is not None else "excitation.json"
    out = {"bag": os.path.join(run_dir, "bag"), "metrics": os.path.join(run_dir, result),
           "figures": os.path.join(run_dir, "figures")}
    STOP.clear()
    # a hang-up (the terminal closed, the ssh connection lost) stops the run as a Ctrl-C does: the
    # motors off, the bag closed; by default it would end this process and leave the nodes running
    previous = {sig: signal.signal(sig, request_stop)
                for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        with contextlib.ExitStack() as stack:
            try:
                # the view meets the run's node processes (and this one) on their discovery range,
                # or this process, whose nodes the composed run holds, on its own
                apart = args.processes or args.emulated_hardware
                processes = participants(node_processes(args.task, args.feedback, args.emulated_hardware)) \
                    if apart else 1
                view = live_view(args.live, ros_args, os.path.join(run_dir, "view.mcap"), stopped=STOP.is_set,
                                 processes=processes, environ=node_environment() if apart else os.environ)
                address = stack.enter_context(view)
            except RuntimeError as exc:
                print(f"soft-arm-experiment: --live {args.live}: {exc}", file=sys.stderr)
                return 2
            if address is not None:
                print(f"soft-arm-experiment: live view on {address} (Foxglove app: Open connection, "
                      "Foxglove WebSocket; layout config/foxglove_layout.json)", file=sys.stderr)
            return _run(args, setup, ros_args, out)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run(args, setup, ros_args: list, out: dict) -> int:
    """Run the graph the way ``args`` says, then report; the exit status."""
    progress = None if args.quiet else _progress
    failed = None
    duration = sum(ph.window * len(ph.sequence) for ph in setup.task.phases) \
        if setup.task is not None else Excitation(setup.excitation, len(setup.arm.tendons)).duration
    try:
        if args.emulated_hardware:
            facts = run_emulated_hardware(ros_args, out, duration, args.config, args.task, args.arm_file,
                                          args.feedback)
        elif args.processes:
            facts = run_processes(ros_args, out, args.task, args.feedback, duration)
        else:
            facts = run_composed(ros_args, out, progress, args.config, task=args.task,
                                 feedback=args.feedback)
    except KeyboardInterrupt:
        facts = {}
    except ConfigError as exc:
        print(f"\nsoft-arm-experiment: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:            # a node died, a service refused, a deadline passed
        facts, failed = {}, str(exc)
        print(f"\nsoft-arm-experiment: {exc}", file=sys.stderr)
    except Exception as exc:               # a composed node's callback raised: its traceback, no result
        traceback.print_exc()
        facts, failed = {}, f"a node failed: {type(exc).__name__}: {exc}"
    interrupted = STOP.is_set()
    if progress is not None:
        print(file=sys.stderr)
    faults = facts.get("driver_faults") or []
    if failed is None and faults:
        failed = "the motor driver faulted: " + "; ".join(
            f"{f['message']} ({f['time_s']:.2f} s after the enable)" for f in faults)
    if failed is None:
        # filled as the nodes were stopped, after the run: a node that failed during the run or on
        # its way out (a driver whose zero-torque frames did not leave, a recorder that could not
        # close its bag)
        failed = exit_failure(facts.get("node_exits") or {})
    if setup.task is None:
        return _identification_result(args, out, facts, failed, interrupted)
    figures = []
    if os.path.isdir(out["bag"]):
        from .figures import make_figures
        figures = make_figures(out["bag"], setup.task, out["figures"], setup.arm)
    status = _no_result(out, facts, failed, interrupted, "no metrics written")
    if status is not None:
        return status
    _mark_valid(out["metrics"], facts)
    data, rows, summary = _load_metrics(out["metrics"])
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(format_table(rows, summary, setup.task.paper_peak_speed))
        if "strike" in data:
            print("\n" + format_strike(data["strike"]))
        if "tracking" in data:
            print("\n" + format_tracking([TrackingMetrics(**r) for r in data["tracking"]]))
        if facts.get("simulated_s"):
            print(f"\nsimulated {facts['simulated_s']:.1f} s in {facts['wall_s']:.1f} s "
                  f"(real-time factor {facts['simulated_s'] / facts['wall_s']:.2f})")
        print(f"bag:     {out['bag']}\nmetrics: {out['metrics']}")
        for path in figures:
            print(f"figure:  {path}")
    return 130 if interrupted else 0


def _no_result(out: dict, facts: dict, failed: str | None, interrupted: bool, missing: str) -> int | None:
    """The exit status of a run that left no result, None if it left one. A run that ``failed``
    (a node died, the hardware faulted: the reason) has its result file marked invalid over
    whatever it wrote (a runner may have finished before the fault was seen); one that wrote none
    says ``missing``."""
    name = os.path.basename(out["metrics"])
    if failed is None and not _complete(out["metrics"]):
        failed = f"{'interrupted' if interrupted else 'stopped'} before the run played to its end"
    if failed is not None:
        _update(out["metrics"], valid=False, failure=failed, run=facts)
        print(f"soft-arm-experiment: {failed}: no result ({name} marked invalid); bag: {out['bag']}",
              file=sys.stderr)
    elif not os.path.exists(out["metrics"]):
        print(f"soft-arm-experiment: {'interrupted; ' if interrupted else ''}{missing}; bag: {out['bag']}",
              file=sys.stderr)
    else:
        return None
    return 130 if interrupted else 1


def _complete(path: str) -> bool:
    """Whether the result file at ``path`` (if any) says its run played to its end (a runner stopped
    early writes what it has, ``complete`` false)."""
    if not os.path.exists(path):
        return True
    with open(path, encoding="utf-8") as fh:
        return json.load(fh).get("complete", True) is not False


def _mark_valid(path: str, facts: dict):
    """A run's result file is a result: ``valid`` true, with the run facts."""
    _update(path, valid=True, run=facts)


def _update(path: str, **values):
    """Set ``values`` in the JSON file at ``path`` (created if missing), replaced whole: a second
    Ctrl-C or a full disk mid-write leaves the file as it was."""
    data = {}
    if os.path.exists(path):
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    data.update(values)
    writing = path + ".writing"
    with open(writing, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2)
    os.replace(writing, path)


def _identification_result(args, out: dict, facts: dict, failed: str | None, interrupted: bool) -> int:
    """The end of an identification experiment: the schedule it played (``excitation.json``, with the
    run facts) and the next command; exit 1 if it did not play to the end or the hardware faulted
    (such a bag is not an identification experiment: ``excitation.json`` is marked invalid)."""
    status = _no_result(out, facts, failed, interrupted,
                        "the identification experiment did not play to its end")
    if status is not None:
        return status
    _mark_valid(out["metrics"], facts)
    with open(out["metrics"], encoding="utf-8") as fh:
        data = json.load(fh)
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(f"identification experiment: {len(data['segments'])} segments, {data['duration']:.1f} s")
        print(f"bag:      {out['bag']}\nschedule: {out['metrics']}\n"
              f"next:     soft-arm-identify {out['bag']} --output arm_identified.yaml")
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
