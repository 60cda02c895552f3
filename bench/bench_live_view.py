"""Live view benchmark: what the live_view node costs beside a running graph. Prints, writes JSON.

    python bench/bench_live_view.py [--seconds 10] [--output bench/results/live_view.json]

The simulator runs on the wall clock (``graph.simulator.mode: realtime``: 500 Hz tendon/state,
240 Hz mocap/markers, 30 Hz arm/shape) in a process of its own, the live_view node in another.
Measured over ``--seconds`` each: the live view's CPU (its process's user + system time per second
of wall time) with no viewer, with a viewer that reads everything, and with one subscribed that
reads nothing; the simulator's CPU beside it (its steps are what the graph does), and the simulated
seconds per wall second (1: it keeps the clock).
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time

from timing import results_path, write_results


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] of process ``pid`` so far (Linux /proc)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _viewer(port: int, read: bool, stop: threading.Event, counts: dict):
    """A Foxglove WebSocket client subscribed to every channel; ``read``: it takes every message."""
    from websockets.sync.client import connect
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=30) as ws:
        channels = {}
        while len(channels) < 4:
            message = ws.recv(timeout=30)
            if isinstance(message, str) and json.loads(message).get("op") == "advertise":
                channels.update({c["topic"]: c for c in json.loads(message)["channels"]})
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": c["id"]} for k, c in enumerate(channels.values())]}))
        counts["subscribed"] = True
        while not stop.is_set():
            if read:
                try:
                    ws.recv(timeout=0.1)
                    counts["messages"] = counts.get("messages", 0) + 1
                except TimeoutError:
                    pass
            else:
                time.sleep(0.05)


def _phase(view, sim, seconds: float) -> dict:
    cpu_view, cpu_sim, wall = _cpu_seconds(view.pid), _cpu_seconds(sim.pid), time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - wall
    return {"live_view_cpu": (_cpu_seconds(view.pid) - cpu_view) / wall,
            "simulator_cpu": (_cpu_seconds(sim.pid) - cpu_sim) / wall}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--output", default=results_path("live_view.json"))
    args = parser.parse_args(argv)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    port = _free_port()
    sim = subprocess.Popen([sys.executable, "-m", "soft_arm_drivers.sim.simulator_node", "--ros-args",
                            "-p", "graph.simulator.mode:=realtime", "-p", "graph.task:=triangle"],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    view = subprocess.Popen([sys.executable, "-m", "soft_arm_experiments.live_view_node", "--ros-args",
                             "-p", f"view.port:={port}"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    out = {"seconds": args.seconds}
    try:
        time.sleep(5.0)                               # both up, discovery over
        out["no_viewer"] = _phase(view, sim, args.seconds)
        for name, read in (("reading_viewer", True), ("stalled_viewer", False)):
            stop, counts = threading.Event(), {}
            thread = threading.Thread(target=_viewer, args=(port, read, stop, counts), daemon=True)
            thread.start()
            deadline = time.monotonic() + 30.0
            while not counts.get("subscribed") and time.monotonic() < deadline:
                time.sleep(0.05)
            out[name] = _phase(view, sim, args.seconds)
            out[name]["messages_per_s"] = counts.get("messages", 0) / args.seconds
            stop.set()
            thread.join(timeout=10)
    finally:
        for process in (view, sim):
            process.terminate()
            process.wait(timeout=10)
    print(f"live view beside the simulator (wall clock), {args.seconds:g} s each (CPU in cores):")
    for name in ("no_viewer", "reading_viewer", "stalled_viewer"):
        r = out[name]
        extra = f", {r['messages_per_s']:.0f} messages/s read" if "messages_per_s" in r else ""
        print(f"  {name:15} live_view {r['live_view_cpu']:.3f}, simulator {r['simulator_cpu']:.3f}{extra}")
    write_results(args.output, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
