"""Benchmark of the closed loop through the emulated hardware. Prints a table, writes JSON.

    python bench/bench_emulated_rig.py [--task coiling] [--runs 1] [--load 0] [--live [reading|stalled]]
        [--set ns.key=value ...]
        [--output bench/results/emulated_rig.json]

Runs ``soft-arm-experiment <task> --emulated-hardware`` (each node its own process, real time)
``--runs`` times in a row and reports, per run: whether it is valid (a run the motor driver faulted
in is not: its failure), the task metrics (steady RMS, transitions in the mm band, best mm- and
cm-band task velocities), whether real-time scheduling was granted; the CPU share of each node
process (and of soft-arm-experiment, which orchestrates them; the emulated hardware and its Motive
server as ``emulated_rig/hardware`` and ``emulated_rig/motive``) over the enabled run (from /proc,
sampled every 0.5 s from the enable until 2 s before the task's end or the driver's deactivation:
each process between its first and its last sample, so that a run a fault ended early is measured
too) and its major page faults over the same span;
from the bag, the motors' state period (p50, p99, max, stamps not increasing), the mocap frame period
and the driver's own cycle statistics (its last /diagnostics: period p50/p99/max, p99 error, deadline
misses; its longest period reported during the run; the state-to-command latency through the
graph, p50/p99/max of its last 1000 answers, the worst p99 it reported during the run and the
p99 and max over the whole run; the time
from its activation to the first command), how the clik node took the goals (the time from each
``task/goal`` to the reference answering it, p50 and max, the goals answered, the mocap frames it
dropped), the
recorder's messages, their rate and its lost-message count; then over the runs: the valid ones, the
worst RMS and mm band, the cm-band velocity spread. ``--load N`` runs N other CPU-bound processes
beside the runs (a lab PC's other work: single-threaded 200x200 matrix products, normal policy).
``--live`` runs each with its live view and a viewer reading it (the live view's cost to the graph;
``--live stalled``: a viewer that subscribes to everything and never reads), and reports the live
view's CPU share as ``live_view_node``, the messages the viewer read and the scheduling policy of the
live view's threads (its middleware's, ``dds.*``, apart).
``--probe`` runs a stall probe on each CPU (SCHED_FIFO 99, pinned, waking every 1 ms, like
cyclictest) and reports, per run and CPU, the wake-ups later than :data:`STALL_MS` from the enable
to the run's end, each with the time the host's hypervisor took from that CPU around it (``steal``
in /proc/stat): a stall with no steal is the guest's own (real-time throttling, a kernel path), one
with steal is the virtual CPU not running at all.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from soft_arm_experiments.figures import read_series
from soft_arm_experiments.harness import load_setup

from timing import results_path, write_results

TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_ticks(pid: int) -> tuple | None:
    """(utime + stime [clock ticks], major page faults) of process ``pid``; None once it has
    exited."""
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[11]) + int(fields[12]), int(fields[9])


CPU_SAMPLE_PERIOD = 0.5      # s
DEACTIVATED = "[motor_driver]: deactivated"


def _sample_cpu(proc, nodes: dict, until: float, log: str) -> dict:
    """CPU time of every node process (name -> pid), sampled every :data:`CPU_SAMPLE_PERIOD` until
    the monotonic time ``until``, the motor driver's deactivation (in the experiment's ``log``: the
    run's end, or its fault; the teardown is not counted) or the experiment's end: name ->
    [(time [s], ticks, major page faults) of the first sample, of the last sample taken while the
    process lived]."""
    samples = {}
    while True:
        now = time.monotonic()
        for name, pid in nodes.items():
            ticks = _cpu_ticks(pid)
            if ticks is not None:
                samples.setdefault(name, [(now, *ticks)] * 2)[1] = (now, *ticks)
        if now >= until or proc.poll() is not None or DEACTIVATED in open(log, encoding="utf-8").read():
            return samples
        time.sleep(min(CPU_SAMPLE_PERIOD, max(until - now, 0.0)))


def _shares(samples: dict) -> dict:
    """Each node's CPU share [cores] between its first and last sample; a node sampled once (it
    exited within a sample period) is left out."""
    return {n: (b[1] - a[1]) / TICKS / (b[0] - a[0]) for n, (a, b) in sorted(samples.items()) if b[0] > a[0]}


def _major_faults(samples: dict) -> dict:
    """Each node's major page faults (a page read back from disk, the thread waiting) between its
    first and last sample."""
    return {n: b[2] - a[2] for n, (a, b) in sorted(samples.items()) if b[0] > a[0]}


def _children(parent: int) -> list:
    """(pid, command line arguments) of ``parent``'s child processes."""
    pids = subprocess.run(["pgrep", "-P", str(parent)], capture_output=True, text=True).stdout.split()
    out = []
    for pid in map(int, pids):
        with open(f"/proc/{pid}/cmdline", encoding="utf-8") as fh:
            out.append((pid, fh.read().split("\0")))
    return out


def _nodes(parent: int) -> dict:
    """The experiment's node processes: module name -> pid, a node's own worker process (the
    emulated hardware of emulated_rig) as ``<node>/hardware`` and the worker's Motive server as
    ``<node>/motive``."""
    out = {}
    for pid, args in _children(parent):
        if "-m" in args:
            name = args[args.index("-m") + 1].rsplit(".", 1)[-1]
            out[name] = pid
            for child, child_args in _children(pid):
                if any("spawn_main" in a for a in child_args):
                    out[f"{name}/hardware"] = child
                    for motive, motive_args in _children(child):
                        if "soft_arm_drivers.sim.emulated_motive" in motive_args:
                            out[f"{name}/motive"] = motive
    return out


def _periods(stamps) -> dict:
    d = np.diff(np.asarray(stamps, dtype=float))
    return {"messages": int(len(stamps)), "p50_ms": float(1e3 * np.median(d)),
            "p99_ms": float(1e3 * np.percentile(d, 99)), "max_ms": float(1e3 * d.max()),
            "not_increasing": int(np.sum(d <= 0))}


DRIVER_TIMING = ("period_p50_ms", "period_p99_ms", "period_max_ms", "period_error_p99_ms", "deadline_misses",
                 "state_to_command_p50_ms", "state_to_command_p99_ms", "state_to_command_max_ms",
                 "unmatched_commands", "activate_to_first_command_ms", "state_to_command_run_p99_ms",
                 "state_to_command_run_max_ms")


def _driver_timing(series) -> dict:
    """The motor driver's last reported cycle statistics (its /diagnostics values, recorded), the
    worst state-to-command p99 it reported while commands came and its longest period reported in
    the run (each report covers its last 1000 cycles)."""
    reports = [{kv.key: kv.value for kv in status.values} for _, msg in series.get("diagnostics", [])
               for status in msg.status if status.name == "motor_driver"]
    reports = [r for r in reports if "period_p99_ms" in r]
    if not reports:
        return {}
    out = {k: float(reports[-1].get(k) or "nan") for k in DRIVER_TIMING}
    p99 = [float(r["state_to_command_p99_ms"]) for r in reports
           if r.get("state_to_command_p99_ms", "nan") != "nan"]
    out["state_to_command_p99_worst_ms"] = max(p99) if p99 else float("nan")
    longest = [float(r["period_max_ms"]) for r in reports if r.get("period_max_ms", "nan") != "nan"]
    out["period_max_worst_ms"] = max(longest) if longest else float("nan")
    return out


def _goal_latency(bag_dir: str) -> dict:
    """How the clik node took the task runner's goals, from the recorder's receive times: per goal,
    the time from ``task/goal`` to the first ``arm/configuration_reference`` of a new goal index
    with the goal's target (a goal never answered was rejected or never taken), p50 and max [ms],
    the goals answered of those sent, and the mocap frames the node dropped (its last report)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    pending, latency, seen, dropped, sent = [], [], set(), 0, 0
    with AnyReader([Path(bag_dir)], default_typestore=typestore) as reader:
        topics = ("/task/goal", "/arm/configuration_reference", "/diagnostics")
        connections = [c for c in reader.connections if c.topic in topics]
        for conn, t, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/task/goal":
                pending.append((t, np.array(msg.target)))
                sent += 1
            elif conn.topic == "/arm/configuration_reference":
                if msg.goal in seen:
                    continue
                seen.add(msg.goal)
                match = [k for k, (_, x) in enumerate(pending)
                         if x.shape == (len(msg.target),) and np.allclose(x, msg.target, atol=1e-6)]
                if match:
                    latency.append(1e-6 * (t - pending.pop(match[-1])[0]))
            else:
                for status in msg.status:
                    if status.name == "clik":
                        values = {kv.key: kv.value for kv in status.values}
                        dropped = int(values.get("frames_dropped", dropped))
    return {"goals": sent, "answered": len(latency),
            "p50_ms": float(np.median(latency)) if latency else float("nan"),
            "max_ms": max(latency) if latency else float("nan"), "frames_dropped": dropped}


def _recording(bag_dir: str) -> dict:
    """What the recorder kept (``metadata.yaml``): messages, their rate over the bag's span
    [messages/s], and the messages it counted lost (per topic and in all)."""
    with open(os.path.join(bag_dir, "metadata.yaml"), encoding="utf-8") as fh:
        info = yaml.safe_load(fh)["rosbag2_bagfile_information"]
    lost = json.loads((info.get("custom_data") or {}).get("soft_arm.lost_messages", "{}"))
    span = info["duration"]["nanoseconds"] * 1e-9
    return {"messages": info["message_count"], "rate_per_s": info["message_count"] / span if span else 0.0,
            "lost": sum(lost.values()), "lost_by_topic": lost}


def _burn():
    """One CPU-bound process of other work (until killed)."""
    a = np.random.default_rng(0).standard_normal((200, 200))
    while True:
        a = np.tanh(a @ a)


STALL_MS = 5.0       # a probe's wake-up later than this is a stall [ms]


def _steal_ticks(cpu: int) -> int:
    """Time [clock ticks] the hypervisor has taken from ``cpu`` since boot (/proc/stat)."""
    with open("/proc/stat", encoding="utf-8") as fh:
        for line in fh:
            if line.startswith(f"cpu{cpu} "):
                return int(line.split()[8])
    raise ValueError(f"no cpu{cpu} in /proc/stat")


def _probe(cpu: int, path: str):
    """A stall probe on ``cpu`` (until killed): SCHED_FIFO 99 (OSError if not permitted), waking
    every 1 ms; appends ``[monotonic time [s], lateness [ms], steal since the previous read [ms]]``
    to ``path`` for each wake-up later than :data:`STALL_MS` (steal is read every 0.1 s and after a
    stall)."""
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(99))
    with open(path, "w", encoding="utf-8") as out:             # the file says the probe is on
        last = read = time.monotonic()
        steal = _steal_ticks(cpu)
        while True:
            time.sleep(0.001)
            now = time.monotonic()
            late_ms = (now - last) * 1e3 - 1.0
            if late_ms > STALL_MS or now - read > 0.1:
                ticks = _steal_ticks(cpu)
                if late_ms > STALL_MS:
                    out.write(json.dumps([now, late_ms, (ticks - steal) * 1e3 / TICKS]) + "\n")
                    out.flush()
                steal, read = ticks, now
            last = now


def start_probes(folder: str) -> dict:
    """A stall probe per CPU of this process, once all are on: cpu -> (process, its output file)."""
    out = {}
    for cpu in sorted(os.sched_getaffinity(0)):
        path = os.path.join(folder, f"stalls_cpu{cpu}.jsonl")
        out[cpu] = (_spawn(f"_probe({cpu}, {path!r})"), path)
    while not all(os.path.exists(path) for _, path in out.values()):
        if any(p.poll() is not None for p, _ in out.values()):
            raise RuntimeError("a stall probe ended as it started (SCHED_FIFO 99 needs root, "
                               "CAP_SYS_NICE or an rtprio limit)")
        time.sleep(0.1)
    return out


def _stalls(probes: dict, start: float, end: float) -> dict:
    """Per CPU, the probe's stalls between the monotonic times ``start`` and ``end``: their count,
    and each as (time after ``start`` [s], lateness [ms], steal [ms]), longest first."""
    out = {}
    for cpu, (_, path) in probes.items():
        with open(path, encoding="utf-8") as fh:
            rows = [json.loads(line) for line in fh if line.endswith("\n")]    # whole lines
        rows = sorted(([t - start, late, steal] for t, late, steal in rows if start <= t <= end),
                      key=lambda r: -r[1])
        out[f"cpu{cpu}"] = {"count": len(rows), "longest": rows[:5]}
    return out


def _spawn(call: str) -> subprocess.Popen:
    """A process running ``bench_emulated_rig.<call>``, its numerical libraries single-threaded."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    code = f"import sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); " \
           f"import bench_emulated_rig; bench_emulated_rig.{call}"
    return subprocess.Popen([sys.executable, "-c", code], env=env)


def start_load(n: int) -> list:
    """``n`` processes of other work beside the runs, single-threaded each."""
    return [_spawn("_burn()") for _ in range(n)]


def _free_tcp_port() -> int:
    """A TCP port of 127.0.0.1 free a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


POLICIES = {getattr(os, name): name for name in ("SCHED_OTHER", "SCHED_BATCH", "SCHED_IDLE", "SCHED_FIFO",
                                                 "SCHED_RR") if hasattr(os, name)}


def _thread_policies(pid: int) -> dict:
    """How the threads of process ``pid`` are scheduled: for its middleware threads (``dds``, named
    ``dds.*``) and the others, policy (with the FIFO priority or the niceness) -> threads."""
    out = {}
    for tid in map(int, os.listdir(f"/proc/{pid}/task")):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm", encoding="utf-8") as fh:
                group = "dds" if fh.read().startswith("dds.") else "other"
            policy = os.sched_getscheduler(tid)
            fifo = policy in (os.SCHED_FIFO, os.SCHED_RR)
            level = os.sched_getparam(tid).sched_priority if fifo else os.getpriority(os.PRIO_PROCESS, tid)
        except OSError:
            continue                                  # ended meanwhile
        name = f"{POLICIES.get(policy, policy)} {level}"
        out.setdefault(group, {})[name] = out.get(group, {}).get(name, 0) + 1
    return out


def one_run(task: str, sets: list, duration: float, probes=None, live: str | None = None) -> dict:
    """One ``soft-arm-experiment <task> --emulated-hardware`` run: its metrics (``valid`` false when
    the driver faulted), CPU share per node, the state and mocap periods, the driver's timing and,
    with ``probes`` (:func:`start_probes`), the stalls of each CPU from the enable to the end; with
    ``live``, the run's live view (``--live``) with a viewer subscribed to everything from the enable
    on, reading it all (``"reading"``) or nothing (``"stalled"``)."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    with tempfile.TemporaryDirectory() as tmp:
        run, log = os.path.join(tmp, "run"), os.path.join(tmp, "log")
        with open(log, "w", encoding="utf-8") as fh:
            port = _free_tcp_port() if live else None
            proc = subprocess.Popen([sys.executable, "-m", "soft_arm_experiments.experiment", task,
                                     "--emulated-hardware", "--quiet", "--output", run]
                                    + [a for s in sets for a in ("--set", s)]
                                    + (["--live", f"127.0.0.1:{port}"] if live else []),
                                    stdout=fh, stderr=subprocess.STDOUT, env=env)
        viewer = None                                 # (stop, counts) of the live view's viewer
        try:
            while "[motor_driver]: activated" not in open(log, encoding="utf-8").read():
                if proc.poll() is not None:
                    raise RuntimeError("the experiment ended before the motors were enabled:\n"
                                       + open(log, encoding="utf-8").read())
                time.sleep(0.1)
            enabled = time.monotonic()
            if live:                                  # a viewer subscribed to everything from the enable on
                from bench_live_view import _viewer
                viewer = (threading.Event(), {})
                threading.Thread(target=_viewer, args=(port, live == "reading", *viewer), daemon=True).start()
            nodes = {"soft-arm-experiment": proc.pid, **_nodes(proc.pid)}    # the orchestrator too
            policies = _thread_policies(nodes["live_view_node"]) if "live_view_node" in nodes else None
            samples = _sample_cpu(proc, nodes, time.monotonic() + max(duration - 2.0, 1.0), log)
            status = proc.wait(timeout=duration + 120)
            ended = time.monotonic()
        finally:
            if viewer is not None:
                viewer[0].set()
            if proc.poll() is None:
                proc.kill()
        metrics_path = os.path.join(run, "metrics.json")
        if not os.path.exists(metrics_path):
            raise RuntimeError(f"the experiment exited with {status} and no metrics:\n"
                               + open(log, encoding="utf-8").read())
        with open(metrics_path, encoding="utf-8") as fh:
            metrics = json.load(fh)
        series = read_series(os.path.join(run, "bag"))
        recording = _recording(os.path.join(run, "bag"))
        goals = _goal_latency(os.path.join(run, "bag"))
    return {"status": status, "valid": metrics.get("valid", False), "failure": metrics.get("failure"),
            "summary": metrics.get("summary"), "run": metrics["run"],
            "cpu_share": _shares(samples), "major_faults": _major_faults(samples),
            "state_period": _periods([t for t, _ in series["tendon/state"]]),
            "mocap_period": _periods([t for t, _ in series["mocap/markers"]]),
            "driver_timing": _driver_timing(series), "goal_latency": goals, "recording": recording,
            "stalls": _stalls(probes, enabled, ended) if probes else None,
            "live": live, "live_view_messages": viewer[1].get("messages", 0) if live else None,
            "live_viewer_closed_s": viewer[1]["closed"] - enabled if live and "closed" in viewer[1] else None,
            "live_view_policies": policies}


def _speed(v) -> str:
    return "-" if v is None else f"{v:.3f} m/s"


def spread(runs: list) -> dict:
    """Run-to-run figures of the valid runs: RMS worst, mm band worst, cm-band velocity max/min."""
    valid = [r["summary"] for r in runs if r["valid"]]
    out = {"runs": len(runs), "valid_runs": len(valid)}
    if valid:
        v_cm = [s["velocity_cm"] for s in valid if s["velocity_cm"]]
        out.update(rms_worst_mm=1e3 * max(s["rms_error"] for s in valid),
                   mm_band_worst=min(s["reached_mm"] for s in valid), transitions=valid[0]["transitions"],
                   velocity_cm_spread=max(v_cm) / min(v_cm) if v_cm else None)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="coiling")
    parser.add_argument("--runs", type=int, default=1, help="consecutive runs (the spread needs >= 2)")
    parser.add_argument("--load", type=int, default=0,
                        help="CPU-bound processes of other work beside the runs")
    parser.add_argument("--probe", action="store_true", help="a stall probe on each CPU (see above)")
    parser.add_argument("--live", nargs="?", const="reading", choices=("reading", "stalled"),
                        help="each run with its live view (--live) and a viewer reading it (stalled: "
                             "one subscribed that never reads)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE")
    parser.add_argument("--output", default=results_path("emulated_rig.json"))
    args = parser.parse_args()
    setup = load_setup(args.task, overrides=[s for s in args.sets if not s.startswith("graph.")])
    duration = sum(ph.window * len(ph.sequence) for ph in setup.task.phases)
    runs, load = [], start_load(args.load)
    with tempfile.TemporaryDirectory() as tmp:
        probes = start_probes(tmp) if args.probe else {}
        try:
            for k in range(args.runs):
                runs.append(_report(k, one_run(args.task, args.sets, duration, probes, args.live)))
        finally:
            for p in load + [p for p, _ in probes.values()]:
                p.kill()
    total = spread(runs)
    line = f"{args.task} over {total['runs']} runs with {args.load} other CPU-bound processes: " \
           f"{total['valid_runs']} valid"
    if total["valid_runs"]:
        v = total["velocity_cm_spread"]
        line += (f"; RMS worst {total['rms_worst_mm']:.2f} mm, mm band worst {total['mm_band_worst']}/"
                 f"{total['transitions']}, cm-band velocity spread (max/min) "
                 + ("-" if v is None else f"{v:.2f}"))
    print(line)
    write_results(args.output, {"task": args.task, "sets": args.sets, "load": args.load, "live": args.live,
                                "duration_s": duration, "runs": runs, "spread": total})


def _report(k: int, r: dict) -> dict:
    """Print run k's figures; gives r back."""
    summary = r["summary"]
    print(f"run {k + 1}: {'valid' if r['valid'] else 'INVALID: ' + str(r['failure'])}; real-time "
          f"scheduling {'granted' if r['run'].get('realtime') else 'refused'}")
    if summary:
        print(f"  steady RMS {summary['rms_error'] * 1e3:.2f} mm, {summary['reached_mm']}/"
              f"{summary['transitions']} transitions in the mm band, task velocity mm band "
              f"{_speed(summary['velocity_mm'])}, cm band {_speed(summary['velocity_cm'])}")
    cpu = r["cpu_share"]
    if cpu:
        print("  CPU per node: " + ", ".join(f"{n} {c:.0%}" for n, c in cpu.items())
              + f" (total {sum(cpu.values()):.0%} of {os.cpu_count()} cores)")
        print("  major page faults per node: " + ", ".join(f"{n} {k}" for n, k in r["major_faults"].items()))
    else:
        print("  CPU per node: not measured (the run ended within a sample period of the enable)")
    for name, key in (("tendon/state", "state_period"), ("mocap/markers", "mocap_period")):
        p = r[key]
        print(f"  {name:14s} period p50 {p['p50_ms']:.2f} ms, p99 {p['p99_ms']:.2f} ms, max "
              f"{p['max_ms']:.1f} ms, {p['not_increasing']} stamps not increasing ({p['messages']})")
    d = r["driver_timing"]
    if d:
        print(f"  driver cycle (its last 1000): period p50 {d['period_p50_ms']:.2f} ms, p99 "
              f"{d['period_p99_ms']:.2f} ms, max {d['period_max_ms']:.1f} ms, p99 error "
              f"{d['period_error_p99_ms']:.2f} ms, {d['deadline_misses']:.0f} deadline misses in the run, "
              f"longest period reported in the run {d['period_max_worst_ms']:.1f} ms")
        print(f"  state to command (its last 1000): p50 {d['state_to_command_p50_ms']:.2f} ms, p99 "
              f"{d['state_to_command_p99_ms']:.2f} ms, max {d['state_to_command_max_ms']:.1f} ms; worst p99 "
              f"reported in the run {d['state_to_command_p99_worst_ms']:.2f} ms; "
              f"{d['unmatched_commands']:.0f} commands matched no state")
        print(f"  state to command (the whole run): p99 {d['state_to_command_run_p99_ms']:.2f} ms, max "
              f"{d['state_to_command_run_max_ms']:.1f} ms")
        print(f"  activate to the first motor command: {d['activate_to_first_command_ms']:.1f} ms")
    for cpu, st in (r["stalls"] or {}).items():
        print(f"  {cpu} stalls > {STALL_MS:.0f} ms: {st['count']}" + "".join(
            f"; {late:.1f} ms at {t:.2f} s (steal {steal:.0f} ms)" for t, late, steal in st["longest"][:3]))
    g = r["goal_latency"]
    print(f"  clik: {g['answered']}/{g['goals']} goals answered, goal to reference p50 {g['p50_ms']:.1f} ms, "
          f"max {g['max_ms']:.1f} ms; {g['frames_dropped']} mocap frames dropped")
    if r["live"]:
        cpu_view = r["cpu_share"].get("live_view_node", float("nan"))
        closed = r["live_viewer_closed_s"]
        print(f"  live view ({r['live']} viewer): {cpu_view:.3f} cores, {r['live_view_messages']} messages "
              f"read; threads {r['live_view_policies']}"
              + ("" if closed is None else f"; the viewer's connection closed {closed:.1f} s in"))
    rec = r["recording"]
    print(f"  recorder: {rec['messages']} messages, {rec['rate_per_s']:.0f} messages/s, {rec['lost']} lost"
          + (f" ({rec['lost_by_topic']})" if rec["lost"] else ""))
    return r


if __name__ == "__main__":
    main()
