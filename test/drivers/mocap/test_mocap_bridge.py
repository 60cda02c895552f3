"""NatNet mocap bridge core against the emulator over real UDP on 127.0.0.1 (ephemeral ports):
handshake and version request, frames of every stream version, marker selection and ordering,
calibration, mid-exposure stamps, occlusion, packet faults, foreign and random packets, config."""
import contextlib
import math
import random
import socket
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings, strategies as st

from soft_arm_drivers.mocap.bridge_config import BridgeConfig, Calibration, load_mocap_config, rotation_matrix
from soft_arm_drivers.mocap.clock_map import MAX_DELAY, PACE, ClockMap
from soft_arm_drivers.mocap.mocap_bridge import PACKET_OUTCOMES, MocapBridge
from soft_arm_drivers.mocap.natnet import (FrameOfData, LabeledMarker, MessageId, RigidBody, ServerInfo,
                                           Version, build_frame_of_data, build_packet, build_server_info)
from soft_arm_drivers.sim.natnet_emulator import Faults, NatNetEmulator, plant_markers
from soft_arm_drivers.sim.simulated_rig import Plant
from soft_arm_model import build_model
from soft_arm_model.parameters import ConfigError

# markers of a hanging, slightly bent arm in arm_base [m], base to tip
TRUE = np.array([[0.002, 0.001, -0.094], [0.008, 0.006, -0.187], [0.020, 0.027, -0.274],
                 [0.041, 0.092, -0.335]])
Y_UP = (0.7071067811865476, 0.0, 0.0, 0.7071067811865476)     # Motive's y up -> arm_base z up
SHIFT = (0.1, -0.2, -1.2)
VERSIONS = ["3.1", "4.0", "4.1"]

SERVER_INFO = build_server_info(ServerInfo("Motive", Version(3, 1), Version(4, 1),
                                           clock_frequency=10_000_000, data_port=1511,
                                           multicast=False, multicast_group="233.252.0.1"))
VALID_41 = build_frame_of_data(Version(4, 1), FrameOfData(
    frame_number=1, rigid_bodies=tuple(RigidBody(k, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
                                       for k in (1, 2, 3, 4)),
    camera_mid_exposure=10, transmit_timestamp=20))
OTHERS = [SERVER_INFO, build_packet(MessageId.NAT_RESPONSE, bytes(4)),
          build_packet(MessageId.NAT_UNRECOGNIZED_REQUEST), build_packet(MessageId.NAT_KEEPALIVE)]


def static(t):
    return TRUE


def config(emulator, **kw):
    """Bridge settings for ``emulator``: its port, any data port, its ids of the chosen source."""
    source = kw.pop("source", "rigid_bodies")
    ids = emulator.rigid_body_ids if source == "rigid_bodies" else emulator.labeled_marker_ids
    values = dict(command_port=emulator.command_port, data_port=0, source=source, ids=ids,
                  rotation=Y_UP, translation=SHIFT, keepalive_period=0.05)
    values.update(kw)
    return BridgeConfig(**values)


def pump(bridge, until, timeout=3.0):
    """Poll until ``until()`` holds; the frames delivered meanwhile."""
    frames = []
    deadline = time.monotonic() + timeout
    while not until():
        assert time.monotonic() < deadline, f"timed out: {bridge.state} {bridge.note} {bridge.counters}"
        frames += bridge.poll(0.01)
    return frames


def frame_packets(bridge):
    return sum(bridge.counters[k] for k in PACKET_OUTCOMES if k != "control")


@contextlib.contextmanager
def connected(stream=False, source="rigid_bodies", bridge_kw=None, **emulator_kw):
    """A started emulator and a bridge that finished its handshake with it."""
    emulator_kw.setdefault("calibration", Calibration(rotation_matrix(Y_UP), SHIFT))
    with NatNetEmulator(static, **emulator_kw) as emulator:
        with MocapBridge(config(emulator, source=source, **(bridge_kw or {}))) as bridge:
            emulator.start(stream=stream)
            bridge.connect()
            pump(bridge, lambda: bridge.state == "streaming")
            yield emulator, bridge


def step(emulator, bridge, count):
    """Send ``count`` frames one by one; the frames the bridge delivered once all arrived."""
    frames = []
    backlog = emulator.counters["sent"] - frame_packets(bridge)
    for _ in range(count):
        emulator.send_frame()
        frames += bridge.poll(0.0)
    frames += pump(bridge, lambda: emulator.counters["sent"] - frame_packets(bridge) == backlog)
    return frames


def step_with(emulator, bridge, markers):
    """Send one frame of ``markers`` (n, 3) [m, arm_base]; the frames the bridge delivered."""
    backlog = emulator.counters["sent"] - frame_packets(bridge)
    emulator.send_frame(markers)
    return pump(bridge, lambda: emulator.counters["sent"] - frame_packets(bridge) == backlog)


# --- handshake, versions, streaming --------------------------------------------------------------

def test_handshake_keepalives_and_streaming_at_240_hz():
    with connected(stream=True, version="4.1", rate=240.0) as (emulator, bridge):
        assert bridge.version == Version(4, 1) and bridge.server_info.clock_frequency == 10_000_000
        assert bridge.server_info.app_name == "soft_arm NatNet emulator"
        assert emulator.clients == [bridge.command_address]
        start = time.monotonic()
        frames = pump(bridge, lambda: time.monotonic() - start > 0.5)
        requests = emulator.counters["requests"]
        bridge.close()                                     # says goodbye: the server forgets it
        deadline = time.monotonic() + 2.0
        while emulator.clients and time.monotonic() < deadline:
            time.sleep(0.01)
        assert emulator.clients == []
    assert 0.5 * 240 * 0.8 < len(frames) < 0.5 * 240 * 1.2
    assert requests >= 5                                   # the connect and unicast keep-alives
    numbers = [f.frame_number for f in frames]
    assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
    for frame in frames:
        np.testing.assert_allclose(frame.markers, TRUE, atol=1e-6)   # float32 on the wire


@pytest.mark.parametrize("source", ["rigid_bodies", "labeled_markers"])
@pytest.mark.parametrize("version", VERSIONS)
def test_frames_of_every_version_and_source(version, source):
    with connected(version=version, layout="both", source=source) as (emulator, bridge):
        frames = step(emulator, bridge, 20)
    assert bridge.version == Version(*map(int, version.split(".")))
    assert [f.frame_number for f in frames] == list(range(1, 21))
    assert bridge.counters["delivered"] == 20 and bridge.counters["malformed"] == 0
    for frame in frames:
        np.testing.assert_allclose(frame.markers, TRUE, atol=1e-6)


def test_version_request_switches_a_4x_server():
    with connected(version="4.1", bridge_kw={"natnet_version": "4.0"}) as (emulator, bridge):
        frames = step(emulator, bridge, 5)
        assert emulator.version == Version(4, 0)
    assert bridge.version == Version(4, 0) and len(frames) == 5 and bridge.note == ""


def test_refused_version_request_keeps_the_servers_version():
    with connected(version="4.1", accept_bitstream=False,
                   bridge_kw={"natnet_version": "4.0"}) as (emulator, bridge):
        assert len(step(emulator, bridge, 5)) == 5
    assert bridge.version == Version(4, 1) and "refused NatNet 4.0" in bridge.note


def test_no_version_request_to_a_3x_server():
    with connected(version="3.1", bridge_kw={"natnet_version": "4.1"}) as (emulator, bridge):
        assert len(step(emulator, bridge, 3)) == 3
        assert emulator.version == Version(3, 1)             # a Bitstream request would switch it
    assert bridge.version == Version(3, 1) and "cannot switch to 4.1" in bridge.note


def test_unanswered_version_request_times_out():
    now = [0.0]
    with NatNetEmulator(static) as silent:                    # bound, never answers
        with MocapBridge(config(silent, natnet_version="4.0", timeout=0.5),
                         clock=lambda: now[0]) as bridge:
            bridge.connect()
            bridge.handle_packet(SERVER_INFO, 0.1)            # NatNet 4.1
            bridge.poll()                                     # sends the version request
            assert bridge.state == "negotiating" and bridge.version == Version(4, 1)
            assert bridge.handle_packet(VALID_41, 0.5) is not None   # frames go on meanwhile
            now[0] = 0.7
            bridge.poll()
    assert bridge.state == "streaming" and bridge.version == Version(4, 1)
    assert "did not answer the request for NatNet 4.0" in bridge.note


@pytest.mark.parametrize("version, frequency, note", [
    (Version(2, 9), None, "unsupported NatNet version 2.9"),
    (Version(4, 2), 10_000_000, "unsupported NatNet version 4.2"),
])
def test_unsupported_servers_are_reported_and_their_frames_not_parsed(version, frequency, note):
    fields = dict(clock_frequency=frequency, data_port=1511, multicast=False,
                  multicast_group="233.252.0.1") if frequency else {}
    info = build_server_info(ServerInfo("Motive", Version(3, 1), version, **fields))
    with NatNetEmulator(static) as silent:
        with MocapBridge(config(silent)) as bridge:
            bridge.handle_packet(info, 0.0)
            assert bridge.handle_packet(VALID_41, 0.1) is None
    assert bridge.state == "unsupported" and note in bridge.note and bridge.version is None
    assert bridge.counters["before_handshake"] == 1


def test_frames_sent_to_the_data_socket():
    """Servers that send frames to the client's data port (not its command socket) work too."""
    with NatNetEmulator(static, version="4.1") as emulator:
        with MocapBridge(config(emulator, rotation=(0, 0, 0, 1), translation=(0, 0, 0))) as bridge:
            emulator.data_port = bridge.data_address[1]
            emulator.start(stream=False)
            bridge.connect()
            pump(bridge, lambda: bridge.state == "streaming")
            frames = step(emulator, bridge, 5)
    assert len(frames) == 5
    np.testing.assert_allclose(frames[-1].markers, TRUE, atol=1e-6)


def test_reconnects_when_the_server_goes_silent_and_follows_its_restart():
    with NatNetEmulator(static, calibration=Calibration(rotation_matrix(Y_UP), SHIFT)) as first:
        port = first.command_port
        bridge = MocapBridge(config(first, timeout=0.1))
        first.start(stream=False)
        bridge.connect()
        pump(bridge, lambda: bridge.state == "streaming")
        step(first, bridge, 5)
    with bridge:                                              # the server is gone
        requests = bridge.counters["connect_requests"]
        pump(bridge, lambda: bridge.state == "stale")
        pump(bridge, lambda: bridge.counters["connect_requests"] >= requests + 2)
        with NatNetEmulator(static, command_port=port,
                            calibration=Calibration(rotation_matrix(Y_UP), SHIFT)) as second:
            second.start(stream=False)
            pump(bridge, lambda: bridge.state == "streaming")
            frames = step(second, bridge, 3)                  # numbered from 1 again: a new stream
    assert [f.frame_number for f in frames] == [1, 2, 3]
    np.testing.assert_allclose(frames[-1].markers, TRUE, atol=1e-6)


def test_a_take_looped_within_the_restart_gap_is_followed_as_a_new_stream():
    """Motive plays a recorded take of 500 frames in a loop: the frame numbers count up from 1
    again, 499 below the newest (within the gap of late datagrams). The first two frames of the loop
    are refused as late, the third on are delivered as a new stream (its clock map rebuilt), and
    the jump back is not counted as frames lost."""
    now = [0.0]

    def packet(number, k):
        """The frame ``number``, exposed at the k-th period of 240 Hz on the 10 MHz server clock,
        sent 2 ms later."""
        ticks = 1_000_000 + k * 10_000_000 // 240
        return build_frame_of_data(Version(4, 1), FrameOfData(
            frame_number=number, rigid_bodies=tuple(RigidBody(i, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
                                                    for i in (1, 2, 3, 4)),
            camera_mid_exposure=ticks, transmit_timestamp=ticks + 20_000))
    with NatNetEmulator(static) as server:
        with MocapBridge(config(server), clock=lambda: now[0]) as bridge:
            bridge.connect()
            bridge.handle_packet(SERVER_INFO, 0.0)
            take = list(range(1, 501))
            delivered = []
            for k, number in enumerate(take + take[:10]):
                now[0] = 0.1 + k / 240 + 0.003
                frame = bridge.handle_packet(packet(number, k), now[0])
                if frame is not None:
                    delivered.append(frame.frame_number)
            assert delivered == take + take[2:10]
            counters = bridge.counters
            assert (counters["restarts"], counters["out_of_order"], counters["lost"]) == (1, 2, 0), counters


def test_a_stream_the_bridge_cannot_read_goes_stale_and_reconnects():
    """Only datagrams that parse are the server heard: a stream in another version than the one
    agreed (the answer to a version switch lost) is malformed frame after frame, and after
    ``timeout`` the bridge reconnects, where every datagram kept it streaming for ever."""
    now = [0.0]
    with NatNetEmulator(static) as silent:
        with MocapBridge(config(silent, timeout=0.5), clock=lambda: now[0]) as bridge:
            bridge.connect()
            bridge.handle_packet(SERVER_INFO, 0.0)
            assert bridge.handle_packet(VALID_41, 0.1) is not None and bridge.state == "streaming"
            requests = bridge.counters["connect_requests"]
            for k in range(2, 11):                          # 0.2 ... 1.0 s: unreadable frames
                now[0] = 0.1 * k
                assert bridge.handle_packet(VALID_41[:-7], now[0]) is None
                bridge.poll()
            assert bridge.counters["malformed"] == 9
            assert bridge.state == "stale" and bridge.counters["connect_requests"] > requests


def test_the_timeouts_run_on_their_own_clock_through_a_step_of_the_stamps_clock():
    """The stamps' clock (the node's: the wall clock on the rig) steps back an hour while the server
    goes silent: the reconnect comes after ``timeout`` of the timeouts' own clock (the node passes
    the monotonic one), where on the stamps' clock it would have waited the hour."""
    wall, steady = [1000.0], [5.0]
    with NatNetEmulator(static) as silent:
        with MocapBridge(config(silent, timeout=0.5), clock=lambda: wall[0],
                         timer=lambda: steady[0]) as bridge:
            bridge.connect()
            bridge.handle_packet(SERVER_INFO, wall[0])
            assert bridge.handle_packet(VALID_41, wall[0]) is not None
            requests = bridge.counters["connect_requests"]
            wall[0] -= 3600.0                               # NTP steps the wall clock back
            steady[0] += 0.3
            bridge.poll()
            assert bridge.state == "streaming"
            steady[0] += 0.3                                # 0.6 s of silence
            bridge.poll()
            assert bridge.state == "stale" and bridge.counters["connect_requests"] == requests + 1


def test_server_silence_before_the_handshake_retries_the_connect():
    with NatNetEmulator(static) as emulator:                      # bound but not serving yet
        with MocapBridge(config(emulator, timeout=0.1)) as bridge:
            bridge.connect()
            pump(bridge, lambda: bridge.counters["connect_requests"] >= 3)
            assert bridge.state == "connecting"
            emulator.start(stream=False)
            pump(bridge, lambda: bridge.state == "streaming")


def test_stepped_without_threads_follows_a_moving_simulated_arm():
    """The lockstep wiring: the stepping loop serves the emulator's requests and sends one frame per
    exposure of the simulated plant; the bridge returns the plant's true markers of that step."""
    plant = Plant(build_model(), 1e-3)
    plant.settle([1.0, 0.0, 1.0, 0.0])
    calibration = Calibration(rotation_matrix(Y_UP), SHIFT)
    with NatNetEmulator(plant_markers(plant), layout="both", calibration=calibration) as emulator:
        with MocapBridge(config(emulator, source="labeled_markers")) as bridge:
            bridge.connect()
            emulator.serve_requests()
            pump(bridge, lambda: bridge.state == "streaming")
            emulator.serve_requests()                         # the first keep-alive
            # the clock map's first samples: were the first frame read a millisecond later than the
            # next (a loaded machine), the next would be stamped after it came and skipped
            for _ in range(5):
                emulator.send_frame(exposure_time=time.time())
                pump(bridge, lambda: frame_packets(bridge) == emulator.counters["sent"])
            before = bridge.counters["delivered"]
            truth, delivered = [], []
            for k in range(40):
                plant.sense(markers=True)
                if k % 4 == 0:                                # a 250 Hz camera on a 1 kHz plant
                    truth.append(plant.markers()[0])
                    emulator.send_frame(exposure_time=time.time())
                    delivered += pump(bridge, lambda: bridge.counters["delivered"] > before + len(delivered))
                plant.step([3.0, 0.0, 0.0, 0.0])
    assert len(delivered) == 10
    for frame, markers in zip(delivered, truth):
        np.testing.assert_allclose(frame.markers, markers, atol=1e-6)
    assert np.linalg.norm(truth[-1][-1] - truth[0][-1]) > 1e-4         # the tip moved


# --- selection, calibration, stamps --------------------------------------------------------------

def test_marker_selection_and_ordering_by_id():
    """Ids in any order, shuffled in every frame among markers of another asset: the bridge returns
    the ones it was given, in its order."""
    ids = (7 << 16 | 9, 7 << 16 | 2, 3, 7 << 16 | 12)
    with connected(layout="labeled_markers", labeled_marker_ids=ids, extra_markers=5,
                   source="labeled_markers") as (emulator, bridge):
        frames = step(emulator, bridge, 5)
    for frame in frames:
        np.testing.assert_allclose(frame.markers, TRUE, atol=1e-6)
    order = [2, 0, 3, 1]
    with connected(source="labeled_markers", layout="labeled_markers", labeled_marker_ids=ids,
                   bridge_kw={"ids": tuple(ids[k] for k in order)}) as (emulator, bridge):
        frames = step(emulator, bridge, 3)
    np.testing.assert_allclose(frames[-1].markers, TRUE[order], atol=1e-6)


def test_calibration_round_trip_and_conventions():
    rng = np.random.default_rng(5)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    calibration = Calibration(rotation_matrix(q), rng.normal(size=3))
    points = rng.normal(size=(10, 3))
    np.testing.assert_allclose(calibration.to_arm(calibration.to_mocap(points)), points, atol=1e-12)
    np.testing.assert_allclose(calibration.to_mocap(calibration.to_arm(points)), points, atol=1e-12)
    matrix = rotation_matrix(q)
    np.testing.assert_allclose(rotation_matrix(matrix.ravel()), matrix)
    np.testing.assert_allclose(matrix.T @ matrix, np.eye(3), atol=1e-12)
    assert np.linalg.det(matrix) == pytest.approx(1.0)
    y_up = Calibration(rotation_matrix(Y_UP), (0.0, 0.0, -1.2))
    np.testing.assert_allclose(y_up.to_arm([[0.0, 1.2, 0.0]]), [[0.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(y_up.to_arm([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                               [[1.0, 0.0, -1.2], [0.0, -1.0, -1.2]], atol=1e-12)


@pytest.mark.parametrize("rotation, match", [
    ((0, 0, 0, 2), "norm"), ((1, 0, 0, 0, 1, 0, 0, 0, -1), "not a rotation"),
    ((1, 0, 0, 0, 2, 0, 0, 0, 1), "not a rotation"), ((0, 0, 1), "4 values"),
    ((0, 0, float("nan"), 1), "non-finite"),
])
def test_bad_rotations_are_rejected(rotation, match):
    with pytest.raises(ValueError, match=match):
        rotation_matrix(rotation)


def test_calibration_is_applied_end_to_end():
    """The emulator streams in its frame; a bridge without the calibration sees those coordinates
    (some 1.2 m from the mocap's origin: within the bridge's max_distance of 5 m here)."""
    calibration = Calibration(rotation_matrix(Y_UP), SHIFT)
    with connected(bridge_kw={"rotation": (0, 0, 0, 1), "translation": (0, 0, 0),
                              "max_distance": 5.0}) as (emulator, bridge):
        frames = step(emulator, bridge, 2)
    np.testing.assert_allclose(frames[-1].markers, calibration.to_mocap(TRUE), atol=1e-6)
    assert not np.allclose(calibration.to_mocap(TRUE), TRUE, atol=0.1)


def test_stamps_are_mid_exposure_on_the_local_clock():
    """Once the clock map has seen its first frames, each stamp is the frame's exposure on the local
    clock, late by the smallest delay only; a frame that arrives late (a stall of this process)
    keeps its stamp: its latency, not its stamp, grows. The second half of 0.4 s of frames is
    judged: a stall at the start biases the map until a frame comes through on time."""
    with connected(stream=True, latency=0.004) as (emulator, bridge):
        start = time.monotonic()
        frames = pump(bridge, lambda: time.monotonic() - start > 0.4)
        settled = frames[len(frames) // 2:]
        errors = [f.stamp - emulator.exposure_time(f.frame_number) for f in settled]
    assert len(errors) > 40
    assert 0.0 <= np.median(errors) < 2e-3                     # late by the smallest delay only
    assert max(abs(e) for e in errors) < 5e-3
    # never stamped on arrival; judged on the same half: while a stall at the start biases the map,
    # the frames that come through on time are held as outliers for a few frames and stamped on the
    # stalled offset, their latency short by the stall
    assert all(f.latency >= 0.0039 for f in settled)
    assert np.median([f.latency for f in frames]) < 0.05


class HeldArm:
    """An arm moving at SPEED along x in real time from its start, that the machine holds still
    ``hold`` [s] after :meth:`begin` for ``length`` [s] and that then catches up at once: the
    emulated hardware's plant on a loaded machine. ``markers(t)``, ``reached(t)`` [s, system time]
    as the emulated Motive reads its plant (the latest configuration at or before t)."""
    SPEED = 1.0                                                # m/s

    def __init__(self, hold: float, length: float):
        self.start = time.time()
        self.hold, self._after, self.length = math.inf, hold, length

    def begin(self):
        """Count the hold from now."""
        self.hold = time.time() + self._after

    def now(self) -> float:
        """The time [s] the arm has reached."""
        t = time.time()
        return self.hold if self.hold <= t < self.hold + self.length else t

    def markers(self, t: float) -> np.ndarray:
        return TRUE + [self.SPEED * (min(t, self.now()) - self.start), 0.0, 0.0]

    def reached(self, t: float) -> bool:
        return self.now() >= t


def lost_as_left_out(bridge, emulator) -> tuple:
    """Poll until the bridge has counted as many frames lost as the emulator's stream left out
    (missed or unreached), at most 2 s: one left out after the last frame received shows only
    with the next (a loaded machine's stream thread may sleep through an exposure at any time).
    Returns the (emulator's, bridge's) counters that matched, copied together."""
    deadline = time.monotonic() + 2.0
    while True:
        left_out, counted = dict(emulator.counters), dict(bridge.counters)
        if counted["lost"] == left_out["missed"] + left_out["unreached"]:
            return left_out, counted
        assert time.monotonic() < deadline, ("the frames lost never matched those the stream left out",
                                             counted, left_out)
        bridge.poll(0.01)


def _streamed_from(arm, seconds, **emulator_kw):
    """(frames, their exposure times [s], the emulator's counters, the bridge's) of ``seconds`` of
    streaming the moving ``arm``, the counters read once the bridge has counted as lost every frame
    the stream left out (:func:`lost_as_left_out`)."""
    calibration = Calibration(rotation_matrix(Y_UP), SHIFT)
    with NatNetEmulator(arm.markers, calibration=calibration, latency=0.004, **emulator_kw) as emulator:
        with MocapBridge(config(emulator)) as bridge:
            emulator.start()
            bridge.connect()
            pump(bridge, lambda: bridge.state == "streaming")
            arm.begin()
            end = time.monotonic() + seconds
            frames = pump(bridge, lambda: time.monotonic() > end)
            exposures = np.array([emulator.exposure_time(f.frame_number) for f in frames])
            return (frames, exposures) + lost_as_left_out(bridge, emulator)


def _moved(frames) -> np.ndarray:
    """How far [m] each frame shows the arm moved along x."""
    return np.array([f.markers[0, 0] - TRUE[0, 0] for f in frames])


def test_an_arm_held_behind_its_cameras_is_seen_where_it_is_at_each_frames_exposure():
    """A simulated arm that the machine holds for 0.15 s is seen at each frame's exposure time, its
    frames of the hold sent once it has caught up, never the held arm under a later stamp: that
    would be a jump of 0.15 m between two frames (9 m/s at 240 Hz), a speed the arm never had;
    without ``reached`` the stream shows it."""
    arm = HeldArm(hold=0.2, length=0.15)
    frames, exposures, counters, _ = _streamed_from(arm, 0.8, reached=arm.reached)
    np.testing.assert_allclose(_moved(frames), HeldArm.SPEED * (exposures - arm.start), atol=1e-5)
    during = (exposures >= arm.hold) & (exposures < arm.hold + arm.length)
    assert np.count_nonzero(during) >= 0.8 * arm.length * 240       # delayed, not lost
    assert all(f.received_at >= arm.hold + arm.length for f, d in zip(frames, during) if d)
    assert counters["unreached"] == 0

    blind = HeldArm(hold=0.2, length=0.15)
    frames, exposures, _, _ = _streamed_from(blind, 0.8)
    assert np.max(np.abs(_moved(frames) - HeldArm.SPEED * (exposures - blind.start))) > 0.1


def test_frames_the_arm_reaches_too_late_are_not_sent_and_the_bridge_counts_them_lost():
    """Held for 0.4 s against a reach timeout of 0.1 s, the frames exposed in the hold's first 0.3 s
    wait 0.1 s each and are dropped, counted; they take their frame numbers, so that the bridge
    counts them lost; every frame sent shows the arm at its exposure."""
    arm = HeldArm(hold=0.2, length=0.4)
    frames, exposures, counters, bridge = _streamed_from(arm, 1.0, reached=arm.reached,
                                                         reach_timeout=0.1)
    np.testing.assert_allclose(_moved(frames), HeldArm.SPEED * (exposures - arm.start), atol=1e-5)
    assert 0.2 * 240 < counters["unreached"] < 0.4 * 240, counters
    assert bridge["lost"] == counters["unreached"] + counters["missed"], (bridge, counters)
    with pytest.raises(ValueError, match="reach_timeout"):
        NatNetEmulator(static, reach_timeout=0.0)


def test_exposures_the_stream_slept_through_take_their_frame_numbers():
    """The stream's thread held for 0.1 s (here by a markers function that blocks once): the
    exposures it slept through are counted missed and the bridge counts as many frames lost (once
    a frame after the last of them has come: :func:`lost_as_left_out`)."""
    held = []

    def slow(t):
        if held == [True]:
            held.append(True)
            time.sleep(0.1)
        return TRUE

    calibration = Calibration(rotation_matrix(Y_UP), SHIFT)
    with NatNetEmulator(slow, calibration=calibration) as emulator:
        with MocapBridge(config(emulator)) as bridge:
            emulator.start()
            bridge.connect()
            pump(bridge, lambda: bridge.state == "streaming")
            held.append(True)
            end = time.monotonic() + 0.5
            frames = pump(bridge, lambda: time.monotonic() > end)
            counters, _ = lost_as_left_out(bridge, emulator)
    assert counters["missed"] >= 0.05 * 240 and frames and counters["unreached"] == 0


def test_clock_map_takes_the_smallest_delay_in_its_window():
    rng = random.Random(1)
    clock = ClockMap(frequency=1_000_000, window=1.0)
    offset, local = 1000.0, 1000.0
    for k in range(500):                                      # 500 Hz, 2 ms apart
        local = offset + 0.002 * k + 50e-6 + rng.expovariate(1 / 300e-6)
        clock.observe(2000 * k, local)
    clock.observe(2000 * 500, offset + 1.0 + 50e-6)           # one frame with the smallest delay
    assert clock.offset == pytest.approx(offset + 50e-6, abs=1e-9)
    assert clock.to_local(1000) == pytest.approx(offset + 1e-3 + 50e-6, abs=1e-9)
    for k in range(501, 1200):                                # the server clock now runs 1 ms late
        clock.observe(2000 * k, offset + 0.002 * k + 1e-3 + 50e-6 + rng.expovariate(1 / 300e-6))
    assert clock.offset > offset + 1e-3                       # the old minimum left the window
    with pytest.raises(ValueError):
        ClockMap(frequency=0, window=1.0)


OUTLIER = st.one_of(st.floats(-1e6, -0.0011), st.floats(0.51, 1e6))       # s from the true offset


def _samples(draw_delay, outliers: dict, n: int, offset: float = 1000.0, f: int = 1_000_000):
    """n (ticks, local) samples at 500 Hz with the given delays; ``outliers``: index -> an offset
    error [s] that sample carries (its ticks wrong by it)."""
    out = []
    for k in range(n):
        ticks = 2000 * k
        local = offset + ticks / f + draw_delay(k) - outliers.get(k, 0.0)
        out.append((ticks, local))
    return out


def test_one_sample_far_below_the_offset_is_not_believed():
    """One frame whose transmit ticks are 1000 s ahead (its offset 1000 s low): the minimum would
    have taken it for the whole window; it is held, dropped when the next sample disagrees."""
    clock = ClockMap(frequency=1_000_000, window=2.0)
    for ticks, local in _samples(lambda k: 1e-4, {50: 1000.0}, 200):
        clock.observe(ticks, local)
        assert clock.offset == pytest.approx(1000.0 + 1e-4, abs=1e-9)
    assert clock.outliers == 1 and clock.jumps == 0


@settings(max_examples=200, deadline=None)
@given(delays=st.lists(st.floats(50e-6, 2e-3), min_size=60, max_size=60),
       spots=st.lists(st.tuples(st.integers(1, 59), OUTLIER), max_size=12))
# an outlier held just before three samples that agree on a lower delay: the re-anchoring once took
# the outlier with them
@example(delays=[0.001953125] * 2 + [0.0004169, 0.000413, 0.0001] + [0.001953125] * 55, spots=[(1, 1.0)])
def test_isolated_outliers_never_move_the_offset(delays, spots):
    """Random transport delays (50 us to 2 ms) and outliers, never three in a row: the offset stays
    between the true offset plus the smallest delay so far (an outlier's, when it looks like a
    delay) and plus 2 ms, at every sample (a drop of the delay by more than a millisecond is taken
    once three samples agree on it: a re-anchoring, which may come where an outlier hid the drop's
    first sample, and lands on the agreeing samples, never on an outlier held before them)."""
    outliers = {}
    for k, error in spots:
        if not {k - 2, k - 1}.issubset(outliers) and not {k + 1, k + 2}.issubset(outliers) \
                and not {k - 1, k + 1}.issubset(outliers):
            outliers[k] = error
    clock = ClockMap(frequency=1_000_000, window=10.0)
    smallest = np.inf
    for k, (ticks, local) in enumerate(_samples(lambda k: delays[k], outliers, 60)):
        clock.observe(ticks, local)
        # an outlier that looks like a transport delay (0 to 2 ms) is one: nothing can tell it apart
        apparent = delays[k] - outliers.get(k, 0.0)
        if k not in outliers or 0.0 <= apparent <= 2e-3:
            smallest = min(smallest, apparent)
        assert 1000.0 + smallest - 1e-9 <= clock.offset <= 1000.0 + 2e-3 + 1e-9, (k, outliers)


@settings(max_examples=100, deadline=None)
@given(jump=st.one_of(st.floats(-1e4, -0.51), st.floats(0.002, 1e4)), at=st.integers(0, 40))
def test_a_server_clock_that_really_jumps_re_anchors_after_three_frames(jump, at):
    """The server's clock jumps by ``jump`` [s] at sample ``at`` (the first sample, too): ahead by
    any amount, or back by more than any transport delay, three agreeing samples re-anchor the map,
    whatever the window still holds."""
    clock = ClockMap(frequency=1_000_000, window=2.0)
    samples = _samples(lambda k: 1e-4, {k: jump for k in range(at, 80)}, 80)
    for k, (ticks, local) in enumerate(samples):
        clock.observe(ticks, local)
        if k >= at + 2:
            assert clock.offset == pytest.approx(1000.0 + 1e-4 - jump, abs=1e-6), k
    assert clock.jumps == (1 if at > 0 else 0)


def test_a_server_clock_that_jumps_back_less_than_a_delay_re_anchors_within_a_window():
    """Back by 0.2 s: indistinguishable from 0.2 s of transport delay until the window forgets the
    samples before it (2 s)."""
    clock = ClockMap(frequency=1_000_000, window=2.0)
    for k, (ticks, local) in enumerate(_samples(lambda k: 1e-4, {k: -0.2 for k in range(100, 1200)}, 1200)):
        clock.observe(ticks, local)
    assert clock.offset == pytest.approx(1000.2001, abs=1e-6)


def _stalled(stall: float, pace: float = PACE) -> tuple:
    """500 Hz frames read 0.1 ms after they were sent, this process not reading for ``stall`` [s]
    from 1 s on and then reading the frames queued meanwhile at once: the map, each frame's stamp
    minus its exposure [s], and which frames were queued."""
    clock = ClockMap(frequency=1_000_000, window=2.0, pace=pace)
    errors, queued = [], []
    for k in range(3000):
        ticks = 2000 * k
        exposure = 1000.0 + ticks / 1e6
        waited = 1001.0 <= exposure < 1001.0 + stall
        clock.observe(ticks, (1001.0 + stall if waited else exposure) + 1e-4)
        errors.append(clock.to_local(ticks) - exposure)
        queued.append(waited)
    return clock, np.array(errors), np.array(queued)


def test_frames_read_at_once_after_a_stall_keep_their_stamps_and_are_no_clock_jump():
    """This process starved for 1.5 s reads the 750 frames queued meanwhile at once: their offsets
    fall frame by frame as the server's clock runs, three in a row agreeing within 0.05 s, but read
    at once they confirm no jump: every frame is stamped at its exposure (late by its 0.1 ms delay),
    so that the bridge sees how old the queued ones are. Taken for jumps (pace 0), the queue
    re-anchored the map on its reads every three frames and stamped frames 1.5 s old as just
    exposed."""
    clock, errors, _ = _stalled(1.5)
    assert clock.jumps == 0
    np.testing.assert_allclose(errors, 1e-4, atol=1e-9)
    loose, errors, queued = _stalled(1.5, pace=0.0)
    assert loose.jumps > 100 and errors[queued].max() > 1.4


def test_a_stall_longer_than_the_window_leaves_stamps_late_by_at_most_the_largest_delay():
    """Starved for 2.5 s, longer than the 2 s window: the window holds late reads only, and the map
    takes the first within the largest transport delay (0.5 s) as its offset; no frame's stamp is
    later than that after its exposure, none is early, and three frames on time after the queue
    re-anchor the map (one jump)."""
    clock, errors, queued = _stalled(2.5)
    assert clock.jumps == 1
    assert errors.min() >= 1e-4 - 1e-9 and errors.max() <= MAX_DELAY + 1e-4 + 1e-9
    after = np.flatnonzero(~queued & (np.arange(queued.size) > np.flatnonzero(queued)[-1]))
    np.testing.assert_allclose(errors[after[3:]], 1e-4, atol=1e-9)


@pytest.mark.parametrize("step", [0.3, -0.3, 0.0])
def test_a_step_of_the_local_clock_restarts_the_clock_map_at_once(step):
    """NTP steps the local clock (the stamps' clock) by 0.3 s, forward or back, under a 240 Hz
    stream: the bridge sees the step against the steady clock and starts its clock map again, so
    the frames after it are stamped at their exposure on the stepped clock (within 1 ms), where
    the window kept the offset from before and stamped them 0.3 s late for the window's length (or
    refused them as exposed after they came); the step is counted."""
    wall, steady = [1000.0], [5.0]
    with NatNetEmulator(static) as emulator:
        with MocapBridge(config(emulator, ids=(1, 2), natnet_version=""), clock=lambda: wall[0],
                         timer=lambda: steady[0]) as bridge:
            bridge.handle_packet(SERVER_INFO, wall[0], steady[0])
            f = 10_000_000                                     # SERVER_INFO's ticks per second
            errors = []
            for k in range(1, 480):                           # 2 s at 240 Hz, the step at 1 s
                exposure = k / 240.0
                offset = 1000.0 + (step if exposure >= 1.0 else 0.0)      # the local clock at tick 0
                packet = build_frame_of_data(Version(4, 1), FrameOfData(
                    frame_number=k, rigid_bodies=tuple(RigidBody(i, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
                                                       for i in (1, 2)),
                    camera_mid_exposure=round(exposure * f),
                    transmit_timestamp=round((exposure + 0.004) * f)))
                frame = bridge.handle_packet(packet, offset + exposure + 0.0041, 5.0 + exposure + 0.0041)
                errors.append(math.inf if frame is None else frame.stamp - (offset + exposure))
            errors = np.array(errors)
            assert bridge.counters["local_clock_steps"] == (1 if step else 0)
            assert np.all(np.abs(errors) < 1e-3), (np.abs(errors).max(), np.argmax(np.abs(errors)))


def test_a_marker_beyond_the_arms_reach_is_no_position():
    """A marker 316 m from arm_base (Motive streaming millimetres: 0.1 m read as 100) is unseen,
    not a position the CLIK would step towards; counted (implausible). A frame whose markers are
    all that far is refused, and the bridge says why."""
    f = 10_000_000

    def packet(k, positions):
        return build_frame_of_data(Version(4, 1), FrameOfData(
            frame_number=k, rigid_bodies=tuple(RigidBody(i + 1, p, (0.0, 0.0, 0.0, 1.0))
                                               for i, p in enumerate(positions)),
            camera_mid_exposure=round(k / 240 * f), transmit_timestamp=round((k / 240 + 0.004) * f)))
    with NatNetEmulator(static) as emulator:
        with MocapBridge(config(emulator, ids=(1, 2), natnet_version="", rotation=(0, 0, 0, 1),
                                translation=(0, 0, 0))) as bridge:
            bridge.handle_packet(SERVER_INFO, 100.0)
            frame = bridge.handle_packet(packet(1, [(0.01, 0.02, -0.3), (100.0, 0.0, -300.0)]),
                                         100.0 + 1 / 240 + 0.0041)
            np.testing.assert_allclose(frame.markers[0], (0.01, 0.02, -0.3))
            assert np.all(np.isnan(frame.markers[1])) and bridge.counters["implausible"] == 1
            assert bridge.handle_packet(packet(2, [(10.0, 20.0, -300.0), (20.0, 10.0, -380.0)]),
                                        100.0 + 2 / 240 + 0.0041) is None
            assert bridge.counters["implausible"] == 3 and "streaming units" in bridge.note


def test_frames_queued_through_a_stall_are_refused_as_stale_by_the_bridge():
    """The bridge on a 240 Hz stream, not reading for 1.5 s: the frames queued meanwhile, read at
    once, are stamped at their exposure, and those older than the bridge takes (twice the largest
    transport delay) are refused as invalid, never delivered as new; every frame delivered is
    stamped within 1 ms of its exposure on the local clock."""
    with NatNetEmulator(static) as emulator:
        with MocapBridge(config(emulator, ids=(1, 2), natnet_version="")) as bridge:
            bridge.handle_packet(SERVER_INFO, 0.0)
            f = 10_000_000                                     # SERVER_INFO's ticks per second
            delivered, refused, too_old = [], 0, 0
            for k in range(1, 960):                           # 4 s at 240 Hz
                exposure = k / 240.0
                mid, sent = round(exposure * f), round((exposure + 0.004) * f)
                waited = 1.0 <= exposure < 2.5
                read = 100.0 + (2.5 + 0.0041 if waited else exposure + 0.0041)
                packet = build_frame_of_data(Version(4, 1), FrameOfData(
                    frame_number=k, rigid_bodies=tuple(RigidBody(i, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
                                                       for i in (1, 2)),
                    camera_mid_exposure=mid, transmit_timestamp=sent))
                before = bridge.counters["invalid"]
                frame = bridge.handle_packet(packet, read)
                refused += bridge.counters["invalid"] - before
                too_old += read - (100.0 + exposure) > 2 * MAX_DELAY + 1e-4
                if frame is not None:
                    delivered.append((frame.stamp - (100.0 + exposure), waited, read - (100.0 + exposure)))
    assert bridge.clock_map.jumps == 0
    errors = np.array([e for e, _, _ in delivered])
    assert np.abs(errors - 1e-4).max() < 1e-3, errors
    ages = [age for _, waited, age in delivered if waited]
    assert ages and max(ages) <= 2 * MAX_DELAY + 1e-4          # none older than the bridge takes
    assert refused == too_old > 100                             # and all those, refused


# --- occlusion and packet faults -----------------------------------------------------------------

@pytest.mark.parametrize("source", ["rigid_bodies", "labeled_markers"])
@pytest.mark.parametrize("fault", ["occlusion", "absence"])
def test_an_occluded_or_missing_marker_is_delivered_unseen_never_filled_in(source, fault):
    """The frame goes out with the marker's row NaN (the others as measured), counted ``partial``
    and in that marker's ``unseen`` count."""
    with connected(layout="both", source=source) as (emulator, bridge):
        good = step(emulator, bridge, 5)
        emulator.faults = Faults(**{fault: 1.0})
        partial = step(emulator, bridge, 5)
        emulator.faults = Faults()
        good += step(emulator, bridge, 5)
    assert len(good) == 10 and len(partial) == 5
    assert bridge.counters["partial"] == 5 and bridge.counters["delivered"] == 15
    assert sum(bridge.unseen) == 5
    for frame in partial:
        unseen = ~np.all(np.isfinite(frame.markers), axis=1)
        assert unseen.sum() == 1
        np.testing.assert_allclose(frame.markers[~unseen], TRUE[~unseen], atol=1e-6)
    for frame in good:
        np.testing.assert_allclose(frame.markers, TRUE, atol=1e-6)


@pytest.mark.parametrize("source", ["rigid_bodies", "labeled_markers"])
def test_the_cameras_occlusion_travels_in_motives_bits_and_a_frame_with_nothing_seen_is_skipped(source):
    """Markers the simulated cameras missed (NaN from ``markers(t)``) go out with Motive's bits (no
    tracking-valid bit, the occluded bit) and come out of the bridge as the same NaN rows; a frame
    in which no marker was seen is skipped as ``occluded``."""
    with connected(layout="both", source=source) as (emulator, bridge):
        hidden = TRUE.copy()
        hidden[[1, 3]] = np.nan
        frames = [f for _ in range(3) for f in step_with(emulator, bridge, hidden)]
        nothing = step_with(emulator, bridge, np.full_like(TRUE, np.nan))
    assert len(frames) == 3 and nothing == []
    for frame in frames:
        assert np.isnan(frame.markers[[1, 3]]).all()
        np.testing.assert_allclose(frame.markers[[0, 2]], TRUE[[0, 2]], atol=1e-6)
    assert bridge.counters["occluded"] == 1 and bridge.last_skipped.reason == "occluded"
    assert bridge.unseen == [0, 3, 0, 3]


@pytest.mark.parametrize("fault", ["drop", "duplicate", "reorder"])
def test_dropped_duplicated_and_reordered_frames_are_counted(fault):
    n = 200
    with connected(faults=Faults(seed=7)) as (emulator, bridge):
        frames = step(emulator, bridge, 1)                  # gaps count from the first frame seen
        emulator.faults = Faults(**{fault: 0.15})
        frames += step(emulator, bridge, n)
        emulator.faults = Faults()                          # a clean last frame releases a held one
        frames += step(emulator, bridge, 1)
    c, e = bridge.counters, emulator.counters
    numbers = [f.frame_number for f in frames]
    assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
    assert c["packets"] - c["control"] == e["sent"]
    if fault == "drop":
        assert e["dropped"] > 10 and c["lost"] == e["dropped"] and len(frames) == n + 2 - e["dropped"]
    elif fault == "duplicate":
        assert e["duplicated"] > 10 and c["duplicates"] == e["duplicated"] and len(frames) == n + 2
    else:
        assert e["reordered"] > 10 and c["out_of_order"] == c["lost"] == e["reordered"]
        assert len(frames) == n + 2 - e["reordered"]


def test_datagrams_from_other_hosts_are_dropped():
    with connected() as (emulator, bridge):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
            stranger.bind(("127.0.0.2", 0))
            stranger.sendto(b"\x07\x00\x00\x00", bridge.command_address)
            pump(bridge, lambda: bridge.counters["foreign"] == 1)
        assert len(step(emulator, bridge, 2)) == 2
    assert bridge.counters["malformed"] == 0


# --- the packet handler never raises --------------------------------------------------------------

float32s = st.floats(width=32, allow_nan=True, allow_infinity=True)
vectors = st.tuples(float32s, float32s, float32s)


@st.composite
def frames(draw):
    """A frame of the bridge's markers (ids 1 and 2, tracked or not, present or not) and others."""
    ids = draw(st.permutations([1, 2, 3, 1 << 16 | 1]))[:draw(st.integers(0, 4))]
    bodies = tuple(RigidBody(i, draw(vectors), (0.0, 0.0, 0.0, 1.0),
                             params=draw(st.sampled_from([1, 1, 1, 0, 3]))) for i in ids)
    markers = tuple(LabeledMarker(i, draw(vectors), 0.01, draw(st.sampled_from([0, 0, 1, 6])))
                    for i in ids)
    mid = draw(st.integers(0, 2**40))
    transmit = max(0, mid + draw(st.integers(-10, 10**6)))
    return FrameOfData(frame_number=draw(st.integers(-2**31, 2**31 - 1)), rigid_bodies=bodies,
                       labeled_markers=markers, camera_mid_exposure=mid,
                       camera_data_received=transmit, transmit_timestamp=transmit)


@pytest.fixture(scope="module")
def handler_bridge():
    with NatNetEmulator(static) as emulator:
        with MocapBridge(config(emulator, ids=(1, 2), natnet_version="")) as bridge:
            yield bridge


def _mutate(data, packet):
    raw = bytearray(packet)
    for _ in range(data.draw(st.integers(1, 6))):
        kind = data.draw(st.sampled_from(["flip", "truncate", "insert", "size"]))
        if kind == "flip" and raw:
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
        elif kind == "truncate":
            del raw[data.draw(st.integers(0, len(raw))):]
        elif kind == "insert":
            at = data.draw(st.integers(0, len(raw)))
            raw[at:at] = data.draw(st.binary(min_size=1, max_size=8))
        elif len(raw) >= 4:
            raw[2:4] = data.draw(st.integers(0, 0xFFFF)).to_bytes(2, "little")
    return bytes(raw)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_random_and_mutated_packets_never_raise_and_are_counted(handler_bridge, data):
    """Any datagram, fed once or twice to a bridge on a fresh NatNet 4.1 stream: no exception, one
    outcome counted per datagram, and only frames whose markers are finite or NaN rows (unseen),
    at least one seen, delivered."""
    bridge = handler_bridge
    bridge.handle_packet(SERVER_INFO, 0.0)
    kind = data.draw(st.sampled_from(["random", "frame", "mutated frame", "mutated other"]))
    if kind == "random":
        packet = data.draw(st.binary(max_size=200))
    elif kind == "mutated other":
        packet = _mutate(data, data.draw(st.sampled_from(OTHERS)))
    else:
        version = data.draw(st.sampled_from([Version(4, 1), Version(4, 1), Version(4, 0)]))
        packet = build_frame_of_data(version, data.draw(frames()))
        packet = _mutate(data, packet) if kind == "mutated frame" else packet
    for _ in range(data.draw(st.integers(1, 2))):
        before = bridge.counters
        frame = bridge.handle_packet(packet, data.draw(st.floats(0, 1e9)))
        after = bridge.counters
        assert after["packets"] == before["packets"] + 1
        assert sum(after[k] != before[k] for k in PACKET_OUTCOMES) == 1
        assert (frame is not None) == (after["delivered"] == before["delivered"] + 1)
        if frame is not None:
            finite = np.isfinite(frame.markers)
            assert frame.markers.shape == (2, 3) and finite.all(axis=1).any()
            assert np.array_equal(finite.all(axis=1), finite.any(axis=1))


# --- configuration -------------------------------------------------------------------------------

def test_the_package_config_loads():
    c = load_mocap_config()
    assert (c.command_port, c.data_port, c.source, c.ids) == (1510, 1511, "rigid_bodies", (1, 2, 3, 4))
    assert c.requested_version == Version(4, 1) and not c.multicast
    np.testing.assert_allclose(c.calibration.to_arm([[0.0, 1.2, 0.0]]), [[0.0, 0.0, 0.0]], atol=1e-12)


@pytest.mark.parametrize("key, value, message", [
    ("mocap.command_port", 70000, "rig.mocap.command_port = 70000 is not valid: expected the "
                                  "server's command port in [1, 65535]"),
    ("mocap.server_address", "233.252.0.1", "rig.mocap.server_address = '233.252.0.1' is not valid"),
    ("mocap.multicast_group", "10.0.0.1", "rig.mocap.multicast_group = '10.0.0.1' is not valid"),
    ("mocap.natnet_version", '"2.9"', "rig.mocap.natnet_version = '2.9' is not valid: expected empty"),
    ("mocap.markers.source", "points", "rig.mocap.markers.source = 'points' is not valid: expected "
                                       "rigid_bodies or labeled_markers"),
    ("mocap.markers.ids", [1, 1], "rig.mocap.markers.ids = [1, 1] is not valid: expected one or more "
                                  "distinct ids"),
    ("mocap.calibration.rotation", [1.0, 1.0, 0.0, 0.0], "rig.mocap.calibration.rotation = "
                                                         "[1.0, 1.0, 0.0, 0.0] is not valid"),
    ("mocap.calibration.translation", [0.0, 0.0], "expected three coordinates [m] within 100 m"),
    ("mocap.timeout", 0.0, "rig.mocap.timeout = 0.0 is not valid: expected a time in (0, 60] s"),
    # shorter than a bridge stall the clock map tells from a jump: the queue would be stamped as new
    ("mocap.max_distance", 0.0,
     "rig.mocap.max_distance = 0.0 is not valid: expected a distance in (0, 100] m"),
    ("mocap.clock_window", 1.0,
     "rig.mocap.clock_window = 1.0 is not valid: expected a window in [2, 3600] s"),
    ("mocap.port", 1, "unknown key rig.mocap.port"),
])
def test_bad_config_values_name_the_key_value_and_range(key, value, message):
    with pytest.raises(ConfigError) as error:
        load_mocap_config(overrides={key: value})
    assert message in str(error.value)


def test_bridge_config_checks_its_fields():
    with pytest.raises(ConfigError, match=r"rig.mocap.data_port = -1 is not valid"):
        BridgeConfig(data_port=-1)
    with pytest.raises(ConfigError, match=r"rig.mocap.calibration.rotation = \[1, 2, 3\] is not valid"):
        BridgeConfig(rotation=(1, 2, 3))
    assert BridgeConfig(rotation=tuple(np.eye(3).ravel())).calibration.rotation.shape == (3, 3)


def test_emulator_serves_loopback_only():
    with pytest.raises(ValueError, match="loopback"):
        NatNetEmulator(static, address="0.0.0.0")


def test_a_burst_of_frames_is_handled_a_budget_at_a_time(monkeypatch):
    """100 frames queued at once, each taking at least 1 ms to handle (a large frame on a loaded
    machine): a poll hands on what it read within its 5 ms budget and leaves the rest in the
    socket for the next poll; none is lost."""
    with NatNetEmulator(static) as emulator:
        settings = config(emulator, poll_budget=0.005, natnet_version="", ids=(1, 2, 3, 4))
        with MocapBridge(settings) as bridge, \
                socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            bridge.handle_packet(SERVER_INFO, time.time())
            handle = bridge.handle_packet

            def slow(data, received_at, steady=None):
                time.sleep(0.001)
                return handle(data, received_at, steady)
            monkeypatch.setattr(bridge, "handle_packet", slow)
            for k in range(1, 101):
                sender.sendto(build_frame_of_data(Version(4, 1), FrameOfData(
                    frame_number=k, rigid_bodies=tuple(RigidBody(i, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
                                                       for i in (1, 2, 3, 4)),
                    camera_mid_exposure=10 * k, transmit_timestamp=10 * k + 5)), bridge.data_address)
            time.sleep(0.2)
            first = bridge.poll(0.1)
            assert 1 <= frame_packets(bridge) <= 6 and len(first) == frame_packets(bridge)
            pump(bridge, lambda: frame_packets(bridge) == 100)
    assert bridge.counters["delivered"] == 100
