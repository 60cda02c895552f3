"""What a node's plumbing costs, per process. Prints a table, writes JSON.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_node_overhead.py [--seconds 5]
        [--output bench/results/node_overhead.json]

- Executors: one node with a 500 Hz timer publishing a tendon JointState (best effort, depth 1) and
  one node subscribing to it, in one process, spun for ``--seconds`` by rclpy's
  SingleThreadedExecutor and by the events executor (``make_executor``, what ``run_node`` spins).
  Reported: the process's CPU time per wall second and per callback, and the callbacks run.
- Garbage collector: a full collection (``gc.collect()``) in a process holding the inner-loop and
  CLIK nodes of the coiling task, as the set-up leaves it and after ``gc.freeze()`` (what
  ``run_node`` does once the node is built).
- Start: the CPU seconds a node's process takes until its node is set up and idle (its CPU time
  rising by less than 10 ms over half a second), started from a fresh interpreter (``python -m``,
  as ``ros2 run`` does) and forked from a run's node fork server (what ``soft-arm-experiment``
  does, :mod:`soft_arm_experiments.fork_server`), median of ``--repeats``; and the server's own.
"""
from __future__ import annotations

import argparse
import gc
import os
import time

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from soft_arm_ros.contract import QOS  # noqa: E402
from soft_arm_ros.conversions import joint_state  # noqa: E402
from soft_arm_ros.runtime import make_executor  # noqa: E402

from timing import process_cpu_seconds, results_path, write_results  # noqa: E402

NAMES = ["tendon_1", "tendon_2", "tendon_3", "tendon_4"]
RATE = 500.0     # Hz


def bench_executor(kind: str, seconds: float) -> dict:
    """CPU per callback of a 500 Hz timer and its subscriber under one executor kind."""
    context = rclpy.Context()
    rclpy.init(context=context)
    counts = {"timer": 0, "subscription": 0}
    try:
        talker = rclpy.create_node("overhead_talker", context=context)
        listener = rclpy.create_node("overhead_listener", context=context)
        pub = talker.create_publisher(JointState, "overhead", QOS["tendon/state"])

        def tick():
            counts["timer"] += 1
            pub.publish(joint_state(NAMES, time.time(), position=[0.0] * 4, velocity=[0.0] * 4,
                                    effort=[1.0] * 4))

        def receive(msg):
            counts["subscription"] += 1

        talker.create_timer(1.0 / RATE, tick)
        listener.create_subscription(JointState, "overhead", receive, QOS["tendon/state"])
        executor = SingleThreadedExecutor(context=context) if kind == "single_threaded" else \
            make_executor(context=context)
        executor.add_node(talker)
        executor.add_node(listener)
        end = time.monotonic() + 1.0                    # discovery and warm-up
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
        counts.update(timer=0, subscription=0)
        cpu, wall = time.process_time(), time.monotonic()
        while time.monotonic() - wall < seconds:
            executor.spin_once(timeout_sec=0.1)
        cpu, wall = time.process_time() - cpu, time.monotonic() - wall
        executor.shutdown()
        talker.destroy_node()
        listener.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    callbacks = counts["timer"] + counts["subscription"]
    return {"executor": kind, "cpu_share": cpu / wall, "cpu_per_callback_us": 1e6 * cpu / callbacks,
            "timer_callbacks": counts["timer"], "subscription_callbacks": counts["subscription"]}


def bench_gc() -> dict:
    """Full-collection pause with the controller nodes built, before and after gc.freeze()."""
    from soft_arm_control.clik_node import ClikNode
    from soft_arm_control.inner_loop_node import InnerLoopNode
    rclpy.init()
    try:
        task = [Parameter("graph.task", value="coiling")]
        nodes = [InnerLoopNode(parameter_overrides=task), ClikNode(parameter_overrides=task)]
        objects = len(gc.get_objects())
        gc.collect()
        t = time.perf_counter()
        gc.collect()
        before = time.perf_counter() - t
        gc.freeze()
        t = time.perf_counter()
        gc.collect()
        after = time.perf_counter() - t
        gc.unfreeze()
        for node in nodes:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return {"objects": objects, "full_collection_ms": 1e3 * before, "after_freeze_ms": 1e3 * after}


START_NODES = ("inner_loop", "clik", "recorder")


def _idle_cpu(pid: int, timeout: float = 60.0) -> float:
    """The CPU seconds of process ``pid`` once it has gone idle (less than 10 ms over 0.5 s)."""
    deadline = time.monotonic() + timeout
    history = []
    while time.monotonic() < deadline:
        history.append(process_cpu_seconds(pid))
        if len(history) > 5 and history[-1] - history[-6] < 0.01:
            return history[-1]
        time.sleep(0.1)
    raise RuntimeError(f"process {pid} did not go idle within {timeout:g} s")


def bench_start(repeats: int) -> dict:
    """CPU seconds to set up each of :data:`START_NODES`, fresh and forked (median of ``repeats``)."""
    import shutil
    import signal
    import statistics
    import subprocess
    import sys
    import tempfile

    from soft_arm_experiments.experiment import _ros_arguments
    from soft_arm_experiments.fork_server import ForkServer
    from soft_arm_experiments.orchestration import node_environment, node_module
    out = {"fresh_s": {}, "forked_s": {}}
    env = node_environment()
    with tempfile.TemporaryDirectory() as tmp:
        args = _ros_arguments("coiling", [], None) + ["-p", f"output:={tmp}/bag"]
        servers = []
        for name in START_NODES:
            fresh, forked = [], []
            for _ in range(repeats):
                shutil.rmtree(f"{tmp}/bag", ignore_errors=True)
                proc = subprocess.Popen([sys.executable, "-m", node_module(name)] + args, env=env,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                fresh.append(_idle_cpu(proc.pid))
                proc.send_signal(signal.SIGINT)
                proc.wait(30)
                server = ForkServer(env, output=subprocess.DEVNULL)
                servers.append(_idle_cpu(server.process.pid))
                shutil.rmtree(f"{tmp}/bag", ignore_errors=True)
                child = server.start(name, node_module(name), args)
                forked.append(_idle_cpu(child.pid))
                child.send_signal(signal.SIGINT)
                child.wait(30)
                server.close()
            out["fresh_s"][name] = statistics.median(fresh)
            out["forked_s"][name] = statistics.median(forked)
        out["server_s"] = statistics.median(servers)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="duration of each executor run [s]")
    parser.add_argument("--repeats", type=int, default=3, help="starts of each node, each way")
    parser.add_argument("--output", default=results_path("node_overhead.json"))
    args = parser.parse_args()
    executors = [bench_executor(kind, args.seconds) for kind in ("single_threaded", "events")]
    collector = bench_gc()
    start = bench_start(args.repeats)
    print(f"{'executor':<16} {'CPU':>6} {'per callback':>13} {'callbacks':>10}")
    for r in executors:
        print(f"{r['executor']:<16} {r['cpu_share']:6.1%} {r['cpu_per_callback_us']:10.0f} us "
              f"{r['timer_callbacks'] + r['subscription_callbacks']:10d}")
    print(f"\nfull collection with the inner-loop and CLIK nodes built ({collector['objects']} "
          f"objects): {collector['full_collection_ms']:.1f} ms; after gc.freeze(): "
          f"{collector['after_freeze_ms']:.2f} ms")
    print(f"\n{'node process set up':<20} {'fresh':>7} {'forked':>7}   (CPU s, median of {args.repeats})")
    for name in START_NODES:
        print(f"{name:<20} {start['fresh_s'][name]:7.2f} {start['forked_s'][name]:7.2f}")
    print(f"{'the fork server':<20} {'':>7} {start['server_s']:7.2f}   (once per run)")
    write_results(args.output, {"rate_hz": RATE, "seconds_per_run": args.seconds, "executors": executors,
                                "gc": collector, "start": start})


if __name__ == "__main__":
    main()
