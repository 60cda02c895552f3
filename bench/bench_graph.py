"""Benchmarks of the ROS 2 graph on real rclpy. Prints a table, writes JSON.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_graph.py [--output bench/results/graph.json]

- State-to-command latency through real DDS between two processes: this process publishes
  ``tendon/state`` at 500 Hz and at 1 kHz (stamped with the wall clock), the ``inner_loop`` node runs
  as its own process (with a reference, so the whole P-satI-D+ law runs) and answers each state with
  a command carrying the state's stamp; the latency is receipt time minus stamp: p50, p99, max,
  and how many states got no answer.
- The triangle experiment on the composed graph in lockstep (``soft-arm-experiment triangle``):
  real-time factor and the Table 1 row, next to the ROS-free harness on the same protocol.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import rclpy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from soft_arm_experiments.harness import load_setup, run_experiment  # noqa: E402
from soft_arm_model.parameters import default_config_dir  # noqa: E402
from soft_arm_ros.contract import QOS  # noqa: E402
from soft_arm_ros.conversions import joint_state, seconds_to_stamp  # noqa: E402

from timing import results_path, write_results  # noqa: E402

NAMES = ["tendon_1", "tendon_2", "tendon_3", "tendon_4"]


def _inner_loop_process():
    d = default_config_dir()
    args = [sys.executable, "-m", "soft_arm_control.inner_loop_node", "--ros-args"]
    for name in ("arm", "control", "plant", "tasks", "graph"):
        args += ["--params-file", os.path.join(d, f"{name}.yaml")]
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def bench_latency(rates=(500.0, 1000.0), duration=5.0) -> dict:
    proc = _inner_loop_process()
    rclpy.init()
    node = rclpy.create_node("latency_probe")
    state_pub = node.create_publisher(JointState, "tendon/state", QOS["tendon/state"])
    ref_pub = node.create_publisher(JointState, "tendon/reference", QOS["tendon/reference"])
    received = {}

    def on_command(msg):
        received[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = time.time_ns()

    node.create_subscription(JointState, "tendon/command", on_command, QOS["tendon/command"])
    results = {}
    try:
        deadline = time.monotonic() + 60
        while (state_pub.get_subscription_count() == 0 or ref_pub.get_subscription_count() == 0) \
                and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        time.sleep(2.0)  # discovery settles
        ref_pub.publish(joint_state(NAMES, 0.0, position=[0.01] * 4, effort=[1.0] * 4))
        for _ in range(20):
            rclpy.spin_once(node, timeout_sec=0.05)
        for rate in rates:
            received.clear()
            sent = {}
            period = 1.0 / rate
            start = time.monotonic()
            k = 0
            while time.monotonic() - start < duration:
                target = start + k * period
                while time.monotonic() < target:
                    rclpy.spin_once(node, timeout_sec=0.0)
                msg = joint_state(NAMES, 0.0, position=[0.001 * (k % 10)] * 4, velocity=[0.0] * 4,
                                  effort=[1.0] * 4)
                now = time.time_ns()
                seconds_to_stamp(msg.header.stamp, now * 1e-9)
                sent[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = now
                state_pub.publish(msg)
                k += 1
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.01)
            lat = np.array([received[key] - t for key, t in sent.items() if key in received]) * 1e-6
            results[f"{int(rate)}_hz"] = {
                "states": len(sent), "answered": int(lat.size),
                "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99)),
                "max_ms": float(lat.max())}
    finally:
        node.destroy_node()
        rclpy.shutdown()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)
    return results


def bench_triangle() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "run")
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "soft_arm_experiments.experiment", "triangle",
                        "--output", out, "--quiet", "--json"], check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        with open(os.path.join(out, "metrics.json"), encoding="utf-8") as fh:
            graph = json.load(fh)
    harness = run_experiment(load_setup("triangle")).summary
    keys = ("rms_error", "velocity_cm", "velocity_mm", "peak_speed", "reached_cm", "reached_mm")
    return {"graph": graph["summary"], "graph_run": graph.get("run", {}), "graph_wall_s": wall,
            "harness": {k: getattr(harness, k) for k in keys}}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=results_path("graph.json"))
    args = parser.parse_args()
    latency = bench_latency()
    for rate, r in latency.items():
        print(f"state -> command latency at {rate}: p50 {r['p50_ms']:.3f} ms, p99 {r['p99_ms']:.3f} ms,"
              f" max {r['max_ms']:.3f} ms ({r['answered']}/{r['states']} answered; target p99 <= 2 ms)")
    tri = bench_triangle()
    run = tri["graph_run"]
    if run.get("simulated_s"):
        print(f"triangle on the graph (lockstep, composed): {run['simulated_s']:.0f} s simulated in "
              f"{run['wall_s']:.1f} s, real-time factor {run['simulated_s'] / run['wall_s']:.2f} "
              "(target >= 1)")
    for name in ("graph", "harness"):
        s = tri[name]
        print(f"  {name:8s} RMS {s['rms_error'] * 1e3:.2f} mm, mm band {s['velocity_mm']} m/s, "
              f"cm band {s['velocity_cm']} m/s, peak {s['peak_speed']:.2f} m/s, "
              f"{s['reached_mm']} transitions in the mm band")
    write_results(args.output, {"latency": latency, "triangle": tri})


if __name__ == "__main__":
    main()
