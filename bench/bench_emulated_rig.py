"""Benchmark of the closed loop through the emulated hardware. Prints a table, writes JSON.

    python bench/bench_emulated_rig.py [--task coiling] [--set ns.key=value ...]
        [--output bench/results/emulated_rig.json]

Runs ``soft-arm-experiment <task> --emulated-hardware`` (each node its own process, real time) and
reports: the task metrics (steady RMS, transitions in the mm band, best mm- and cm-band task
velocities), the driver faults latched while the motors were enabled, whether real-time scheduling
was granted; the CPU share of each node process over the enabled run (from /proc, sampled 2 s after
enabling and 2 s before the task's end); and, from the bag, the motors' state period (p50, p99,
max, stamps not increasing) and the mocap frame period.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from soft_arm_drivers.experiments.figures import read_series
from soft_arm_drivers.experiments.harness import load_setup

from timing import results_path, write_results

TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_ticks(pid: int) -> int:
    with open(f"/proc/{pid}/stat", encoding="utf-8") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])            # utime + stime


def _nodes(parent: int) -> dict:
    """The experiment's node processes: module name -> pid."""
    pids = subprocess.run(["pgrep", "-P", str(parent)], capture_output=True, text=True).stdout.split()
    out = {}
    for pid in map(int, pids):
        with open(f"/proc/{pid}/cmdline", encoding="utf-8") as fh:
            args = fh.read().split("\0")
        if "-m" in args:
            out[args[args.index("-m") + 1].rsplit(".", 1)[-1]] = pid
    return out


def _periods(stamps) -> dict:
    d = np.diff(np.asarray(stamps, dtype=float))
    return {"messages": int(len(stamps)), "p50_ms": float(1e3 * np.median(d)),
            "p99_ms": float(1e3 * np.percentile(d, 99)), "max_ms": float(1e3 * d.max()),
            "not_increasing": int(np.sum(d <= 0))}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="coiling")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE")
    parser.add_argument("--output", default=results_path("emulated_rig.json"))
    args = parser.parse_args()
    setup = load_setup(args.task, overrides=[s for s in args.sets if not s.startswith("graph.")])
    duration = sum(ph.window * len(ph.sequence) for ph in setup.task.phases)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    with tempfile.TemporaryDirectory() as tmp:
        run, log = os.path.join(tmp, "run"), os.path.join(tmp, "log")
        sets = [a for s in args.sets for a in ("--set", s)]
        with open(log, "w", encoding="utf-8") as fh:
            proc = subprocess.Popen([sys.executable, "-m", "soft_arm_drivers.experiment", args.task,
                                     "--emulated-hardware", "--quiet", "--output", run] + sets,
                                    stdout=fh, stderr=subprocess.STDOUT, env=env)
        try:
            while "[motor_driver]: enabled" not in open(log, encoding="utf-8").read():
                if proc.poll() is not None:
                    raise RuntimeError("the experiment ended before the motors were enabled:\n"
                                       + open(log, encoding="utf-8").read())
                time.sleep(0.1)
            time.sleep(2.0)
            nodes = _nodes(proc.pid)
            t0, before = time.monotonic(), {n: _cpu_ticks(p) for n, p in nodes.items()}
            time.sleep(max(duration - 4.0, 1.0))
            after = {n: _cpu_ticks(p) for n, p in nodes.items()}
            wall = time.monotonic() - t0
            status = proc.wait(timeout=duration + 120)
        finally:
            if proc.poll() is None:
                proc.kill()
        if status != 0:
            raise RuntimeError(f"the experiment exited with {status}:\n" + open(log, encoding="utf-8").read())
        with open(os.path.join(run, "metrics.json"), encoding="utf-8") as fh:
            metrics = json.load(fh)
        series = read_series(os.path.join(run, "bag"))
    cpu = {n: (after[n] - before[n]) / TICKS / wall for n in sorted(nodes)}
    state = _periods([t for t, _ in series["tendon/state"]])
    mocap = _periods([t for t, _ in series["mocap/markers"]])
    summary = metrics["summary"]
    print(f"{args.task} through the emulated hardware ({duration:g} s of task, real-time scheduling "
          f"{'granted' if metrics['run']['realtime'] else 'refused'}):")
    print(f"  steady RMS {summary['rms_error'] * 1e3:.2f} mm, {summary['reached_mm']}/"
          f"{summary['transitions']} transitions in the mm band, task velocity mm band "
          f"{summary['velocity_mm']} m/s, cm band {summary['velocity_cm']} m/s")
    print("  CPU per node: " + ", ".join(f"{n} {c:.0%}" for n, c in cpu.items())
          + f" (total {sum(cpu.values()):.0%} of {os.cpu_count()} cores)")
    for name, p in (("tendon/state", state), ("mocap/markers", mocap)):
        print(f"  {name:14s} period p50 {p['p50_ms']:.2f} ms, p99 {p['p99_ms']:.2f} ms, max "
              f"{p['max_ms']:.1f} ms, {p['not_increasing']} stamps not increasing ({p['messages']})")
    write_results(args.output, {"task": args.task, "sets": args.sets, "duration_s": duration,
                                "summary": summary, "run": metrics["run"], "cpu_share": cpu,
                                "state_period": state, "mocap_period": mocap})


if __name__ == "__main__":
    main()
