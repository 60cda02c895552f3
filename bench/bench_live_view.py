"""Live view benchmark: what the live_view node costs beside a running graph. Prints, writes JSON.

    python bench/bench_live_view.py [--seconds 10] [--first-scene 3] [--output bench/results/live_view.json]

The simulator runs on the wall clock (``graph.simulator.mode: realtime``: 500 Hz tendon/state,
240 Hz mocap/markers, 30 Hz arm/shape) in a process of its own, the live_view node in another.
Measured over ``--seconds`` each: the live view's CPU (its process's user + system time per second
of wall time) with no viewer, with a viewer that reads everything, and with one subscribed that
reads nothing; the simulator's CPU beside it (its steps are what the graph does), and the simulated
seconds per wall second (1: it keeps the clock).

Then ``--first-scene`` short runs each (``soft-arm-experiment coiling --live``, one coiling
transition), on the simulator and on the emulated hardware, with a viewer trying to connect from the
command on: the time from the command to the live view's server accepting it, to the first scene,
and to the first scene that holds the mocap's markers and the one that holds the arm [s].
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time

from timing import process_cpu_seconds, results_path, write_results


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _viewer(port: int, read: bool, stop: threading.Event, counts: dict):
    """A Foxglove WebSocket client subscribed to every channel; ``read``: it takes every message.
    Ends when ``stop`` is set or the connection closes (``counts["closed"]``: the monotonic time)."""
    from websockets.exceptions import ConnectionClosed
    try:
        _view(port, read, stop, counts)
    except ConnectionClosed:                          # the run, and its live view, ended, or the server
        counts["closed"] = time.monotonic()           # dropped the viewer


def _view(port: int, read: bool, stop: threading.Event, counts: dict):
    from websockets.sync.client import connect
    # no keepalive pings: a client that does not read does not take their answers either, and would
    # end the connection itself after the ping's timeout
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=30,
                 ping_interval=None) as ws:
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


SHORT = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[1]",
         "tasks.coiling.phase.upward.window=4.0"]        # one coiling transition


def _scene_decoder(channel: dict):
    """bytes -> foxglove.SceneUpdate, from the schema (a FileDescriptorSet) the channel advertises."""
    import base64

    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"])).FromString


def first_scene(emulated: bool) -> dict:
    """One short coiling run with ``--live`` (on the emulated hardware if ``emulated``) and a viewer
    connecting from the command on: seconds from the command to the server accepting the viewer
    (``server_s``), to the first scene (``scene_s``), to the first with the mocap's markers
    (``markers_scene_s``) and to the first with the arm (``arm_scene_s``; on the emulated hardware
    only from ``estimate/shape``, which a run on the mocap's feedback does not have); the run's exit
    status."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect
    port = _free_port()
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "soft_arm_experiments.experiment", "coiling", "--quiet", "--live",
                   f"127.0.0.1:{port}", "--output", os.path.join(tmp, "run")] \
            + (["--emulated-hardware"] if emulated else []) + [a for s in SHORT for a in ("--set", s)]
        started = time.monotonic()
        proc = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            ws = None
            while ws is None and proc.poll() is None and time.monotonic() < started + 300.0:
                try:
                    ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=30)
                except OSError:
                    time.sleep(0.05)
            if ws is None:
                raise RuntimeError(f"no live view on port {port} (the run exited with {proc.poll()})")
            out["server_s"] = time.monotonic() - started
            with ws:
                channel = None
                while channel is None:
                    message = ws.recv(timeout=120)
                    if isinstance(message, str) and json.loads(message).get("op") == "advertise":
                        channel = next((c for c in json.loads(message)["channels"]
                                        if c["topic"] == "/view/scene"), None)
                decode = _scene_decoder(channel)
                ws.send(json.dumps({"op": "subscribe",
                                    "subscriptions": [{"id": 1, "channelId": channel["id"]}]}))
                while not {"markers_scene_s", "arm_scene_s"} <= set(out):
                    try:
                        message = ws.recv(timeout=120)
                    except ConnectionClosed:
                        break                         # the run ended
                    if isinstance(message, bytes) and message[0] == 0x01:     # message data
                        now = time.monotonic() - started
                        out.setdefault("scene_s", now)
                        shown = {e.id for e in decode(message[13:]).entities if e.cylinders or e.spheres}
                        if "mocap" in shown:
                            out.setdefault("markers_scene_s", now)
                        if "arm" in shown:
                            out.setdefault("arm_scene_s", now)
            out["status"] = proc.wait(timeout=600)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return out


def _phase(view, sim, seconds: float) -> dict:
    cpu_view, cpu_sim, wall = process_cpu_seconds(view.pid), process_cpu_seconds(sim.pid), time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - wall
    return {"live_view_cpu": (process_cpu_seconds(view.pid) - cpu_view) / wall,
            "simulator_cpu": (process_cpu_seconds(sim.pid) - cpu_sim) / wall}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--first-scene", type=int, default=3, metavar="N",
                        help="short runs each on the simulator and the emulated hardware for the time to "
                             "the first scene")
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
    for where, emulated in (("simulator", False), ("emulated_hardware", True)):
        runs = [first_scene(emulated) for _ in range(args.first_scene)]
        out.setdefault("first_scene", {})[where] = runs
        for r in runs:
            seconds = ", ".join(f"{what} {r[key]:.1f} s" for what, key in (
                ("server up", "server_s"), ("first scene", "scene_s"), ("first with the markers",
                                                                        "markers_scene_s"),
                ("first with the arm", "arm_scene_s")) if key in r)
            print(f"  --live on the {where.replace('_', ' ')}: {seconds} after the command (run exit "
                  f"status {r['status']})")
    write_results(args.output, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
