"""``soft-arm-experiment <task>``: the main job. Runs one of the paper's experiments as the ROS 2
graph on the simulator, records the bag, writes the metrics and the figures.

By default all nodes (simulator, inner_loop, clik, task_runner, recorder) are composed in this
process and run in lockstep waves (deterministic: the same seed gives the same messages);
``--processes`` starts each node as its own process with the same parameters instead (the
simulator still steps once per command, over DDS). Output (``--output DIR``, default
``runs/<task>-<UTC time>``): ``bag/`` (rosbag2, MCAP), ``metrics.json``, ``figures/*.png``.
Prints a progress line, the paper-style table and the paths (``--json``: the metrics as JSON on
stdout). Ctrl-C stops everything cleanly and keeps what was recorded. A bad parameter or an
unreachable target exits with status 2.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from soft_arm_control.metrics import TransitionMetrics, Summary, format_table
from soft_arm_model.config import ConfigError, default_config_dir

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
    from soft_arm_control.task_runner_node import TaskRunnerNode

    from .lockstep import WaveExecutor
    from .recorder_node import RecorderNode
    from .simulator_node import SimulatorNode

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


def run_emulated_hardware(ros_args: list, out: dict, progress=None, config_dir: str | None = None,
                          duration: float = 0.0) -> dict:
    """The rig's graph in real time against emulated hardware, all in this process: the motor
    driver on a python-can ``virtual`` bus with the CAN motor emulator behind it (the plant of
    plant.yaml, stepped in real time by the emulator), the mocap bridge receiving NatNet frames of
    the same plant from the server emulator over UDP on 127.0.0.1; inner_loop, clik, task_runner and
    recorder unchanged."""
    import can
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from soft_arm_control.clik_node import ClikNode
    from soft_arm_control.inner_loop_node import InnerLoopNode
    from soft_arm_control.task_runner_node import TaskRunnerNode
    from soft_arm_model import ArmData, marker_positions

    from .can_emulator import CanMotorEmulator, EmulatorThread, arm_plant
    from .mocap_bridge import load_mocap_config
    from .mocap_bridge_node import MocapBridgeNode
    from .motor_driver import load_driver_config
    from .motor_driver_node import MotorDriverNode
    from .natnet_emulator import NatNetEmulator
    from .recorder_node import RecorderNode

    d = config_dir or default_config_dir()
    channel = f"soft_arm_{os.getpid()}"
    plant = arm_plant(d, tension=0.05)
    # the emulated motors are flashed with a 0.5 N m torque range (0.024 N of tension per step) and
    # zeroed on the hanging arm, whose shortening the controller's model predicts
    from soft_arm_model import build_model, solve_equilibrium, tendon_lengths
    from soft_arm_control.harness import load_setup
    setup = load_setup("coiling", d)
    model = build_model(setup.arm)
    hanging = solve_equilibrium(model, np.full(model.n_tendons, setup.control.tension_min)).q
    zero = list(model.rest_tendon_lengths - tendon_lengths(model, hanging))
    rig_overrides = {"interface": '"virtual"', "channel": f'"{channel}"',
                     "torque_ranges": [0.5] * model.n_tendons, "zero_shortening": zero}
    driver_config = load_driver_config(os.path.join(d, "rig.yaml"), rig_overrides,
                                       plant.model.n_tendons)
    emulator_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    emulator = CanMotorEmulator.for_config(driver_config, emulator_bus, plant,
                                           start_time=time.time())
    mocap = load_mocap_config(os.path.join(d, "mocap.yaml"))
    data = ArmData(plant.model)
    natnet = NatNetEmulator(lambda t: marker_positions(plant.model, plant.q, data),
                            calibration=mocap.calibration, rate=240.0).start()
    # Ctrl-C stays Python's KeyboardInterrupt (no rclpy handler shutting the context mid-wave), so
    # that the shutdown below always runs in order.
    rclpy.init(args=["soft-arm-experiment"] + ros_args, signal_handler_options=SignalHandlerOptions.NO)
    nodes, executor, can_thread = [], None, None
    try:
        can_thread = EmulatorThread(emulator).start()
        # One Python process serves the emulated motors, the driver and the controller, so a CLIK
        # precomputation can hold the interpreter for tens of ms: a longer watchdog than the rig's.
        driver = MotorDriverNode(d, parameter_overrides=[
            Parameter("rig.motors.interface", value="virtual"),
            Parameter("rig.motors.channel", value=channel),
            Parameter("rig.motors.watchdog_timeout", value=0.2),
            Parameter("rig.motors.reply_timeout", value=0.2),
            Parameter("rig.motors.torque_ranges", value=[0.5] * model.n_tendons),
            Parameter("rig.motors.zero_shortening", value=[float(z) for z in zero])])
        bridge = MocapBridgeNode(d, parameter_overrides=[
            Parameter("rig.mocap.command_port", value=natnet.command_port),
            Parameter("rig.mocap.data_port", value=0)])
        nodes += [driver, bridge, InnerLoopNode(d), ClikNode(d)]
        runner = TaskRunnerNode(d, parameter_overrides=[Parameter("output", value=out["metrics"])])
        recorder = RecorderNode(d, parameter_overrides=[Parameter("output", value=out["bag"])])
        nodes += [runner, recorder]
        driver.driver.zero()                                 # the tendons hang slack
        driver.driver.enable(time.monotonic())
        executor = SingleThreadedExecutor()
        for node in nodes:
            executor.add_node(node)
        start = time.monotonic()
        reported = 0
        while not runner.done and not STOP.is_set() and (
                not duration or time.monotonic() - start < duration):
            executor.spin_once(timeout_sec=0.01)
            if progress is not None and runner.core.t0 is not None and \
                    time.monotonic() - start >= reported + 1.0:
                reported = int(time.monotonic() - start)
                progress(time.monotonic() - start, runner.core.duration)
        return {"wall_s": time.monotonic() - start, "emulated_hardware": True}
    finally:
        _shut_down(nodes, executor)
        if can_thread is not None:
            can_thread.stop()
        natnet.close()
        emulator_bus.shutdown()


def run_processes(ros_args: list, out: dict) -> dict:
    """Each node its own process (console scripts), the same parameters; waits for the task
    runner, then stops the others with SIGINT."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    procs = {}
    start = time.monotonic()
    try:
        for name in ("recorder", "inner_loop", "clik", "task_runner", "simulator"):
            extra = []
            if name == "recorder":
                extra = ["-p", f"output:={out['bag']}", "-p", "use_sim_time:=true"]
            elif name == "task_runner":
                extra = ["-p", f"output:={out['metrics']}"]
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", _MODULES[name]] + ros_args + extra, env=env)
        while procs["task_runner"].poll() is None and not STOP.is_set():
            for name, proc in procs.items():
                if proc.poll() is not None and name != "task_runner":
                    raise RuntimeError(f"node {name} exited with status {proc.returncode}")
            time.sleep(0.2)
        if not STOP.is_set() and procs["task_runner"].returncode != 0:
            raise RuntimeError(f"task_runner exited with status {procs['task_runner'].returncode}")
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
    return {"wall_s": time.monotonic() - start}


_MODULES = {"simulator": "soft_arm_drivers.simulator_node", "recorder": "soft_arm_drivers.recorder_node",
            "inner_loop": "soft_arm_control.inner_loop_node", "clik": "soft_arm_control.clik_node",
            "task_runner": "soft_arm_control.task_runner_node"}


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
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        from soft_arm_control.harness import load_setup
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
    progress = None if args.quiet else _progress
    STOP.clear()
    signal.signal(signal.SIGINT, _request_stop)
    signal.signal(signal.SIGTERM, _request_stop)
    try:
        if args.emulated_hardware:
            facts = run_emulated_hardware(ros_args, out, progress, args.config)
        elif args.processes:
            facts = run_processes(ros_args, out)
        else:
            facts = run_composed(ros_args, out, progress, args.config)
    except KeyboardInterrupt:
        facts = {}
    except ConfigError as exc:
        print(f"\nsoft-arm-experiment: {exc}", file=sys.stderr)
        return 2
    interrupted = STOP.is_set()
    if progress is not None:
        print(file=sys.stderr)
    figures = []
    if os.path.isdir(out["bag"]):
        from .figures import make_figures
        figures = make_figures(out["bag"], setup.task, out["figures"])
    if not os.path.exists(out["metrics"]):
        print(f"soft-arm-experiment: {'interrupted; ' if interrupted else ''}no metrics written; "
              f"bag: {out['bag']}", file=sys.stderr)
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
