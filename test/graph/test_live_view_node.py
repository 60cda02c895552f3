"""The live_view node on real rclpy beside the simulator (wall-clock mode), read by a Foxglove
WebSocket client of the test's own (127.0.0.1 only; subprotocol foxglove.sdk.v1, the Foxglove
SDK's name for the WebSocket protocol that was foxglove.websocket.v1, which it refuses): the
channels are advertised with their schemas, the scene's arm ends at the simulator's tip, a client
that never reads costs the graph nothing, and a server beyond loopback must be asked for."""
import base64
import contextlib
import json
import struct
import threading
import time

import numpy as np
import pytest

from foxglove_wire import cylinder_ends, decoder

SUBPROTOCOL = "foxglove.sdk.v1"


@contextlib.contextmanager
def spinning(*makers):
    """The nodes ``makers`` make (each a function of the context) in a context of their own,
    spinning in a thread; on exit the live view's server closed and everything torn down."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    context = rclpy.Context()
    rclpy.init(context=context)
    nodes = [make(context) for make in makers]
    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.01)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield nodes
    finally:
        stop.set()
        thread.join(timeout=10)
        for node in nodes:
            if hasattr(node, "live"):                 # the live view: its server
                node.close()
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def live_view(context):
    from rclpy.parameter import Parameter

    from soft_arm_experiments.live_view_node import LiveViewNode
    return LiveViewNode(context=context, parameter_overrides=[Parameter("view.port", value=0)])


@pytest.fixture
def graph():
    """The simulator (wall clock) and the live view (a free port) spinning in a thread."""
    from rclpy.parameter import Parameter

    from soft_arm_drivers.sim.simulator_node import SimulatorNode

    def simulator(context):
        return SimulatorNode(context=context, parameter_overrides=[
            Parameter("graph.simulator.mode", value="realtime"), Parameter("graph.task", value="coiling")])
    with spinning(simulator, live_view) as (sim, view):
        yield sim, view


def connect(port: int):
    from websockets.sync.client import connect as ws_connect
    return ws_connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=10)


def advertised(ws, topics, timeout: float = 10.0) -> dict:
    """topic -> channel of the server's advertisements, once every one of ``topics`` is there."""
    channels, deadline = {}, time.monotonic() + timeout
    while not set(topics) <= set(channels):
        message = ws.recv(timeout=max(0.01, deadline - time.monotonic()))
        if isinstance(message, str):
            op = json.loads(message)
            if op.get("op") == "advertise":
                channels.update({c["topic"]: c for c in op["channels"]})
    return channels


def messages_of(ws, subscription: int, count: int, timeout: float = 10.0) -> list:
    """The payloads of the next ``count`` message-data frames of ``subscription``."""
    out, deadline = [], time.monotonic() + timeout
    while len(out) < count:
        message = ws.recv(timeout=max(0.01, deadline - time.monotonic()))
        if isinstance(message, bytes) and message[0] == 0x01:
            sub, _ = struct.unpack_from("<IQ", message, 1)
            if sub == subscription:
                out.append(message[13:])
    return out


def test_a_viewer_gets_the_channels_and_a_scene_whose_arm_ends_at_the_simulator_s_tip(graph):
    sim, view = graph
    with connect(view.live.port) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        channels = advertised(ws, ["/view/scene", "/view/tendons", "/view/task", "/view/diagnostics"])
        scene_channel = channels["/view/scene"]
        assert scene_channel["schemaName"] == "foxglove.SceneUpdate"
        assert scene_channel["encoding"] == "protobuf"
        assert channels["/view/tendons"]["encoding"] == "json"
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 1, "channelId": scene_channel["id"]},
            {"id": 2, "channelId": channels["/view/tendons"]["id"]}]}))
        decode = decoder(scene_channel["schemaName"], base64.b64decode(scene_channel["schema"]))
        for payload in messages_of(ws, 1, 5):
            scene = decode(payload)
            arm = [e for e in scene.entities if e.id == "arm"]
            if arm:
                break
        assert arm, [e.id for e in scene.entities]
        assert {kv.key: kv.value for kv in arm[0].metadata}["source"] == "simulator"
        _, end = cylinder_ends(arm[0].cylinders[-1])
        tip = sim.rig.plant.stepper.data.p[-1]          # the arm hangs still: its tip now
        assert np.linalg.norm(end - tip) < 1e-3, (end, tip)
        mocap = [e for e in scene.entities if e.id == "mocap"]
        unseen = [k for k in {kv.key: kv.value for kv in mocap[0].metadata}["unseen"].split(",") if k]
        assert len(mocap[0].spheres) + len(unseen) == 4
        tendons = json.loads(messages_of(ws, 2, 1)[0])
        assert len(tendons["tension"]) == 4 and tendons["tension"][0] == pytest.approx(0.05)


def test_on_a_rig_that_publishes_no_shape_the_arm_is_the_model_at_the_clik_s_reference():
    """No arm/shape, no estimate/shape (the rig closed on the mocap alone): the scene's arm is where
    the model puts it at the reference's q_d, and says so."""
    import rclpy

    from soft_arm_interfaces.msg import ConfigurationReference
    from soft_arm_model import build_model, load_arm_config, solve_equilibrium, tip_frame
    from soft_arm_model.parameters import default_config_dir
    from soft_arm_ros.contract import QOS, TOPICS
    model = build_model(load_arm_config(f"{default_config_dir()}/arm.yaml"))
    q = solve_equilibrium(model, [1.0, 0.05, 0.6, 0.05]).q          # bent: not the hanging pose
    with spinning(live_view, lambda context: rclpy.create_node("clik", context=context)) as (view, clik):
        publisher = clik.create_publisher(ConfigurationReference, TOPICS["configuration"],
                                          QOS["arm/configuration_reference"])
        publisher.publish(ConfigurationReference(q_d=q.tolist(), labels=["marker4.x", "marker4.z"],
                                                 target=[0.0, -0.3], mode="online"))
        with connect(view.live.port) as ws:
            channel = advertised(ws, ["/view/scene"])["/view/scene"]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel["id"]}]}))
            decode = decoder(channel["schemaName"], base64.b64decode(channel["schema"]))
            arm = []
            for payload in messages_of(ws, 1, 30):
                arm = [e for e in decode(payload).entities if e.id == "arm"]
                if arm:
                    break
            assert arm, "no arm in 30 scenes"
            assert {kv.key: kv.value for kv in arm[0].metadata}["source"] == "model at the reference"
            _, end = cylinder_ends(arm[0].cylinders[-1])
            tip = tip_frame(model, q).p
            assert np.linalg.norm(end - tip) < 1e-3 and np.linalg.norm(tip - tip_frame(model, 0 * q).p) > 0.02


def test_a_viewer_that_never_reads_does_not_slow_the_graph(graph):
    """3 s with no viewer, then 3 s with one subscribed to everything that reads nothing: the
    simulator keeps as much of the wall clock, the node keeps publishing at its rate, and the
    process does not grow by the messages the viewer did not take (the server drops them). Each
    rate is the median of three 1 s windows: a stall of the machine in one window is not the
    viewer's, a viewer that slows the graph slows every window."""
    import resource
    sim, view = graph

    def window() -> tuple:
        t0, published0, wall0 = sim.rig.t, view.published, time.monotonic()
        time.sleep(1.0)
        wall = time.monotonic() - wall0
        return (sim.rig.t - t0) / wall, (view.published - published0) / wall

    def rates() -> tuple:
        return tuple(np.median([window() for _ in range(3)], axis=0))

    alone = rates()
    with connect(view.live.port) as ws:
        channels = advertised(ws, ["/view/scene", "/view/tendons"])
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": c["id"]} for k, c in enumerate(channels.values())]}))
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        watched = rates()
        grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert watched[0] > 0.85 * alone[0], (alone, watched)          # simulated s per wall s
    assert watched[1] > 0.85 * alone[1] and watched[1] > 20.0, (alone, watched)   # scenes per s
    assert grown < 50_000, grown                                     # kB


def test_the_node_refuses_an_address_beyond_loopback_by_default():
    import rclpy
    from rclpy.parameter import Parameter

    from soft_arm_experiments.live_view_node import LiveViewNode
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        with pytest.raises(ValueError, match="view.remote"):     # refused before anything binds
            LiveViewNode(context=context, parameter_overrides=[
                Parameter("view.host", value="0.0.0.0"), Parameter("view.port", value=0)])
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("module", ["soft_arm_experiments.experiment", "soft_arm_experiments.harness_cli"])
def test_a_run_with_live_serves_itself_to_a_viewer(tmp_path, module):
    """``soft-arm-experiment coiling --live 127.0.0.1:PORT`` (and ``soft-arm-harness``): a viewer
    connecting while it runs gets a scene with the arm and the markers; the run ends as without it,
    and the experiment's view.mcap holds the scene and the series for the layout to open after."""
    import os
    import socket
    import subprocess
    import sys

    from mcap.reader import make_reader

    with socket.socket() as s:                    # a TCP port of 127.0.0.1 free a moment ago
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run = tmp_path / "run"
    sets = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[1]",
            "tasks.coiling.phase.upward.window=4.0"]
    experiment = module.endswith("experiment")
    command = [sys.executable, "-m", module, "coiling", "--quiet", "--json", "--live", f"127.0.0.1:{port}"] \
        + (["--output", str(run)] if experiment else []) + [a for s in sets for a in ("--set", s)]
    started = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=dict(os.environ))
    try:
        deadline, ws = time.monotonic() + 120.0, None
        while ws is None and time.monotonic() < deadline and process.poll() is None:
            try:
                ws = connect(port)
            except OSError:
                time.sleep(0.2)
        assert ws is not None, process.communicate(timeout=120)
        with ws:
            channels = advertised(ws, ["/view/scene"], timeout=60.0)
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 7, "channelId": channels["/view/scene"]["id"]}]}))
            decode = decoder("foxglove.SceneUpdate", base64.b64decode(channels["/view/scene"]["schema"]))
            ids, first = set(), None
            while not {"arm", "mocap"} <= ids:
                scene = decode(messages_of(ws, 7, 1, timeout=60.0)[0])
                ids |= {e.id for e in scene.entities if e.cylinders or e.spheres}
                first = first or time.monotonic() - started
        out, err = process.communicate(timeout=600)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, err[-3000:]
    assert "live view on ws://127.0.0.1:" in err
    assert json.loads(out)["summary"]["transitions"] == 1
    print(f"first scene with the arm {first:.1f} s after the command")
    if not experiment:
        return
    with open(run / "view.mcap", "rb") as fh:
        topics = {channel.topic for _, channel, _ in make_reader(fh).iter_messages()}
    assert {"/view/scene", "/view/tendons"} <= topics, topics


def test_a_run_whose_live_view_cannot_serve_stops_before_anything_moves(tmp_path):
    """``soft-arm-experiment --live`` on a port another program holds: the live view's own error,
    the run's refusal naming the address, exit status 2 and no run (no bag)."""
    import socket
    import subprocess
    import sys

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = subprocess.run([sys.executable, "-m", "soft_arm_experiments.experiment", "coiling", "--quiet",
                               "--live", f"127.0.0.1:{port}", "--output", str(tmp_path / "run")],
                              capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr[-3000:]
    assert f"--live 127.0.0.1:{port}: the live view on 127.0.0.1:{port} ended before it was set up" \
        in done.stderr
    assert "Address already in use" in done.stderr
    assert not (tmp_path / "run" / "bag").exists()


def test_the_live_view_process_takes_only_the_cpu_the_graph_leaves():
    """The live_view process ``--live`` starts, as soon as it says it is set up: every thread under
    SCHED_IDLE but the middleware's (``dds.*``), which run under SCHED_FIFO like those of the
    graph's other processes outside the loop; where SCHED_FIFO is not permitted, every thread at
    niceness 19."""
    import os
    import socket

    from soft_arm_experiments import realtime
    from soft_arm_experiments.live_launch import live_view

    def scheduling(pid: int) -> dict:
        """(thread id, name) -> (policy, FIFO priority, niceness) of each thread of ``pid``."""
        out = {}
        for tid in realtime.threads(pid):
            try:
                out[(tid, realtime.thread_name(pid, tid))] = (
                    os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority,
                    os.getpriority(os.PRIO_PROCESS, tid))
            except OSError:
                continue                              # ended meanwhile
        return out

    with socket.socket() as s:                        # a TCP port of 127.0.0.1 free a moment ago
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    permitted = realtime.permitted(realtime.MIDDLEWARE_PRIORITY)
    with live_view(f"127.0.0.1:{port}", []) as address:         # once the node is set up
        assert address == f"ws://127.0.0.1:{port}"
        pid = next(p for p in realtime.child_processes(os.getpid())
                   if "live_view_node" in open(f"/proc/{p}/cmdline", encoding="utf-8").read())
        seen = scheduling(pid)
        middleware = [s for (_, name), s in seen.items() if name.startswith("dds.")]
    others = [s for (_, name), s in seen.items() if not name.startswith("dds.")]
    assert middleware and others, seen
    if permitted:
        assert all(s[0] == os.SCHED_IDLE for s in others), seen
        assert all(s[:2] == (os.SCHED_FIFO, realtime.MIDDLEWARE_PRIORITY) for s in middleware), seen
    else:
        assert all(s[2] == 19 for s in others + middleware), seen
