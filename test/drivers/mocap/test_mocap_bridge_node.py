"""The mocap_bridge node on real rclpy, in this process, against the NatNet emulator on 127.0.0.1
streaming the simulated arm: its lifecycle (configure finds the server, only an active bridge
publishes), mocap/markers and mocap/tip as the simulator publishes them, /diagnostics with the
counters, and bad parameters stopping it with the key and status 2."""
import gc
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy

from conftest import change_state, killed_on_exit, spin_until, stop
from soft_arm_drivers.can.loopback_bus import free_udp_ports
from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_drivers.mocap.mocap_bridge_node import DIAGNOSTICS_TOPIC, MocapBridgeNode, main
from soft_arm_drivers.sim.natnet_emulator import NatNetEmulator, plant_markers
from soft_arm_drivers.sim.simulated_rig import Plant
from soft_arm_model import build_model
from soft_arm_model.parameters import ConfigError, default_config_dir
from soft_arm_ros.contract import FRAME, QOS
from soft_arm_ros.conversions import markers_of, stamp_to_seconds

# a listener that counts every frame: the stream's depth of 1 drops all but the latest when the
# test's spin falls behind by a frame, which a loaded machine does
RECEIVE_ALL = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)


@pytest.fixture
def ros():
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture(scope="module")
def plant():
    """The arm bent by tendons 1 and 3, its markers sensed."""
    model = build_model()
    plant = Plant(model, 1e-3)
    plant.settle([2.0, 0.0, 2.0, 0.0])
    plant.sense(markers=True)
    return plant


def test_node_publishes_the_arms_markers_in_arm_base(ros, plant):
    truth = plant.markers()[0]
    calibration = load_mocap_config().calibration             # the package's config/mocap.yaml
    with NatNetEmulator(plant_markers(plant), version="4.1", rate=240.0, layout="both",
                        calibration=calibration, latency=0.003) as emulator:
        emulator.start()
        bridge = MocapBridgeNode(parameter_overrides=[
            Parameter("rig.mocap.command_port", value=emulator.command_port),
            Parameter("rig.mocap.data_port", value=0)])
        # every value is declared read-only with what is allowed; the overrides keep their values
        port = bridge.describe_parameter("rig.mocap.command_port")
        assert port.read_only
        assert port.description.startswith("expected the server's command port in [1, 65535]")
        assert (port.integer_range[0].from_value, port.integer_range[0].to_value) == (1, 65535)
        assert bridge.get_parameter("rig.mocap.command_port").value == emulator.command_port
        assert bridge.describe_parameter("rig.mocap.calibration.translation").read_only
        listener = rclpy.create_node("mocap_listener")
        got = {"markers": [], "tip": [], "diagnostics": []}

        def on(key):
            return lambda msg: got[key].append((time.time(), msg))

        listener.create_subscription(PoseArray, "mocap/markers", on("markers"), QOS["mocap/markers"])
        listener.create_subscription(PoseStamped, "mocap/tip", on("tip"), QOS["mocap/tip"])
        listener.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on("diagnostics"), 10)
        executor = SingleThreadedExecutor()
        for node in (bridge, listener):
            executor.add_node(node)
        try:
            # configured: the stream is received and counted, nothing is published
            assert bridge.trigger_configure() == TransitionCallbackReturn.SUCCESS
            # what the set-up allocated is out of the collector's generations (frozen)
            assert not any(o is bridge.bridge for o in gc.get_objects())
            spin_until(executor, lambda: bridge.received >= 20)
            assert not got["markers"] and bridge.published == 0
            spin_until(executor, lambda: got["diagnostics"])
            inactive = got["diagnostics"][-1][1].status[0]
            assert inactive.message.endswith("(inactive: not published)")
            assert bridge.trigger_activate() == TransitionCallbackReturn.SUCCESS
            deadline = time.monotonic() + 15.0
            while (len(got["markers"]) < 50 or len(got["tip"]) < 50 or not got["diagnostics"]) \
                    and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            status = bridge.status(1)
        finally:
            executor.shutdown()
            bridge.close()
            bridge.destroy_node()
            listener.destroy_node()
    assert len(got["markers"]) >= 50 and len(got["tip"]) >= 50 and got["diagnostics"]
    stamps, ages = [], []
    for received, msg in got["markers"]:
        assert msg.header.frame_id == FRAME and len(msg.poses) == len(truth)
        np.testing.assert_allclose(markers_of(msg), truth, atol=1e-6)   # base to tip, arm_base
        assert all(p.orientation.w == 1.0 for p in msg.poses)
        stamp = stamp_to_seconds(msg.header.stamp)
        assert 0.003 <= received - stamp                  # mid-exposure, before the message arrived
        stamps.append(stamp)
        ages.append(received - stamp)
    # and not long before: the typical age (this process's own stalls on a loaded machine queue a
    # burst of frames, each as late as the stall, whatever the bridge stamped)
    assert np.median(ages) < 0.1, np.percentile(ages, [50, 90, 100])
    assert np.all(np.diff(stamps) > 0)
    assert np.median(np.diff(stamps)) == pytest.approx(1 / 240, rel=0.2)
    tips = {stamp_to_seconds(m.header.stamp): m for _, m in got["tip"]}
    common = [s for s in stamps if s in tips]
    assert common
    tip = tips[common[-1]].pose.position
    np.testing.assert_allclose([tip.x, tip.y, tip.z], truth[-1], atol=1e-6)
    assert tips[common[-1]].header.frame_id == FRAME
    diagnostics = got["diagnostics"][-1][1].status[0]
    values = {kv.key: kv.value for kv in diagnostics.values}
    assert diagnostics.name == "mocap_bridge: NatNet" and values["state"] == "streaming"
    assert int(values["delivered"]) > 0 and values["natnet_version"] == "4.1"
    assert {"occluded", "missing", "malformed", "duplicates", "out_of_order", "lost"} <= set(values)
    assert status.level == DiagnosticStatus.OK


@pytest.mark.parametrize("parameter, value, message", [
    ("rig.mocap.command_port", 70000, "rig.mocap.command_port = 70000 is not valid: expected the "
                                      "server's command port in [1, 65535]"),
    ("rig.mocap.natnet_version", "4.2", "rig.mocap.natnet_version = '4.2' is not valid"),
    ("rig.mocap.markers.ids", [1, 2, 3], "rig.mocap.markers.ids = [1, 2, 3] is not valid: expected "
                                         "4 ids, one per marker of arm.markers.positions"),
])
def test_bad_parameter_raises_config_error(ros, parameter, value, message):
    with pytest.raises(ConfigError) as error:
        MocapBridgeNode(parameter_overrides=[Parameter(parameter, value=value),
                                             Parameter("rig.mocap.data_port", value=0)])
    assert message in str(error.value)


def test_configure_fails_on_a_data_port_in_use_and_without_a_server(ros, plant):
    """Configure opens the sockets and waits for the server's answer: a port in use, or no server
    at the command port within rig.mocap.timeout, is refused with the reason; the node stays
    unconfigured, and configures once the server is there."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        bridge = MocapBridgeNode(parameter_overrides=[Parameter("rig.mocap.data_port", value=port)])
        try:
            assert bridge.trigger_configure() == TransitionCallbackReturn.FAILURE
            assert bridge.lifecycle_state == "unconfigured" and bridge.bridge is None
        finally:
            bridge.destroy_node()
    nobody = free_udp_ports(1)[0]
    bridge = MocapBridgeNode(parameter_overrides=[Parameter("rig.mocap.command_port", value=nobody),
                                                  Parameter("rig.mocap.data_port", value=0),
                                                  Parameter("rig.mocap.timeout", value=0.3)])
    try:
        started = time.monotonic()
        assert bridge.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert 0.3 <= time.monotonic() - started < 2.0
        assert bridge.lifecycle_state == "unconfigured" and bridge.bridge is None
        with NatNetEmulator(plant_markers(plant), command_port=nobody) as emulator:
            emulator.start()
            assert bridge.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert bridge.lifecycle_state == "inactive"
            assert bridge.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
            assert bridge.bridge is None
    finally:
        bridge.close()
        bridge.destroy_node()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")   # raised by design
def test_a_receive_thread_that_raises_or_does_not_stop_is_the_nodes_failure(ros, plant, monkeypatch):
    """The receive thread ends on an error: the node's failure names it (the process exits with
    status 1, a run it served is no result) and /diagnostics say ERROR. A receive thread that does not
    stop within its bound when released: a failure too, and no second one is started beside it."""
    port = free_udp_ports(1)[0]
    overrides = [Parameter("rig.mocap.command_port", value=port), Parameter("rig.mocap.data_port", value=0)]
    with NatNetEmulator(plant_markers(plant), command_port=port) as emulator:
        emulator.start()
        bridge = MocapBridgeNode(parameter_overrides=overrides)
        try:
            assert bridge.trigger_configure() == TransitionCallbackReturn.SUCCESS

            def broken(timeout):
                raise OSError("socket gone")
            bridge.bridge.poll = broken
            bridge._thread.join(timeout=2.0)
            assert not bridge._thread.is_alive()
            assert "the receive thread stopped: OSError: socket gone" in str(bridge.failure)
            assert bridge.status(0).level == DiagnosticStatus.ERROR
            assert bridge.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
        finally:
            bridge.close()
            bridge.destroy_node()
        bridge = MocapBridgeNode(parameter_overrides=overrides)
        try:
            assert bridge.trigger_configure() == TransitionCallbackReturn.SUCCESS and bridge.failure is None
            receive = bridge._thread              # held (in the middleware, say): it does not end
            monkeypatch.setattr(receive, "join", lambda timeout=None: None)
            monkeypatch.setattr(receive, "is_alive", lambda: True)
            assert bridge.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
            assert "did not stop within 2 s" in str(bridge.failure) and bridge._thread is receive
            assert bridge.trigger_configure() == TransitionCallbackReturn.FAILURE
        finally:
            bridge.close()
            bridge.destroy_node()


def test_bad_parameter_exits_with_status_2(capfd):
    params = os.path.join(default_config_dir(), "mocap.yaml")
    code = main(["mocap_bridge", "--ros-args", "--params-file", params,
                 "-p", "rig.mocap.markers.source:=points"])
    assert code == 2
    assert "rig.mocap.markers.source = 'points' is not valid" in capfd.readouterr().err


def test_node_process_streams_and_stops_cleanly_on_sigint(plant, context):
    """As its own process (``ros2 run soft_arm mocap_bridge`` with the config file), brought up
    through its change_state service (as ``ros2 lifecycle set``; one transition its state does not
    have is refused, and the node lives on): Ctrl-C while frames are being published ends it with
    status 0 and no traceback from the receive thread."""
    params = os.path.join(default_config_dir(), "mocap.yaml")
    with NatNetEmulator(plant_markers(plant), calibration=load_mocap_config().calibration) as emulator:
        emulator.start()
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "soft_arm_drivers.mocap.mocap_bridge_node", "--ros-args", "--params-file",
             params, "-r", "__node:=sigint_bridge",     # the services of earlier tests' bridges may linger
             "-p", f"rig.mocap.command_port:={emulator.command_port}",
             "-p", "rig.mocap.data_port:=0"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        with killed_on_exit(proc):
            assert "mocap_bridge unconfigured" in proc.stdout.readline()
            operator = rclpy.create_node("operator", context=context)
            markers = []
            operator.create_subscription(PoseArray, "mocap/markers", markers.append, QOS["mocap/markers"])
            client = operator.create_client(ChangeState, "/sigint_bridge/change_state")
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(operator)
            try:
                assert not change_state(executor, client, "activate")
                assert change_state(executor, client, "configure")
                assert change_state(executor, client, "activate")
                spin_until(executor, lambda: len(markers) >= 50)
            finally:
                executor.shutdown()
                operator.destroy_node()
            out = stop(proc, signal.SIGINT, 20)
    assert len(markers) >= 50
    assert proc.returncode == 0 and "Traceback" not in out, out


def test_one_frame_with_impossible_server_stamps_does_not_move_the_next_frames(ros, plant):
    """A frame whose transmit ticks are 1000 s off (it would have set the minimum-delay offset and
    stamped the next 2 s of frames 1000 s early): it is counted invalid, and every frame after it
    is published within 1 ms of its true mid-exposure."""
    with NatNetEmulator(plant_markers(plant), version="4.1", rate=240.0, layout="both",
                        calibration=load_mocap_config().calibration, latency=0.003) as emulator:
        emulator.start(stream=False)
        bridge = MocapBridgeNode(parameter_overrides=[
            Parameter("rig.mocap.command_port", value=emulator.command_port),
            Parameter("rig.mocap.data_port", value=0)])
        listener = rclpy.create_node("mocap_listener")
        stamps = []
        listener.create_subscription(PoseArray, "mocap/markers",
                                     lambda msg: stamps.append(stamp_to_seconds(msg.header.stamp)),
                                     RECEIVE_ALL)
        executor = SingleThreadedExecutor()
        for node in (bridge, listener):
            executor.add_node(node)
        exposures = []
        try:
            assert bridge.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert bridge.trigger_activate() == TransitionCallbackReturn.SUCCESS
            spin_until(executor, lambda: bridge.bridge.server_info is not None)
            for k in range(360):                                     # 1.5 s at 240 Hz
                number = emulator.send_frame(transmit_offset=1000.0 if k == 120 else 0.0)
                exposures.append((k, emulator.exposure_time(number)))
                end = time.monotonic() + 1 / 240
                while time.monotonic() < end:
                    executor.spin_once(timeout_sec=max(0.0, end - time.monotonic()))
            spin_until(executor, lambda: bridge.published >= 359, timeout=5.0)
            spin_until(executor, lambda: len(stamps) >= 359, timeout=1.0)
            invalid, published = bridge.bridge.counters["invalid"], bridge.published
        finally:
            executor.shutdown()
            bridge.close()
            bridge.destroy_node()
            listener.destroy_node()
    assert invalid == 1 and published == 359 and len(stamps) == 359
    after = np.array([t for k, t in exposures if k > 120])
    assert np.max(np.abs(np.array(stamps[-len(after):]) - after)) < 1e-3
