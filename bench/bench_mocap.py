"""Benchmarks of the NatNet mocap bridge. Prints a table, writes JSON.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_mocap.py [--output bench/results/mocap.json]

Everything runs on 127.0.0.1 against the NatNet emulator (soft_arm_drivers/natnet_emulator.py)
streaming the four markers of the arm as rigid bodies and labelled markers (plus two of another
asset) in the mocap frame, with the package's calibration:

- frames parsed per second, per stream version: the codec alone (``parse_frame_of_data``) and the
  bridge's whole packet path (parse, frame filter, selection, calibration, stamp);
- the bridge's whole packet path on the worst frames of 64 KiB a sender can make (the most items
  NatNetTypes.h allows of every kind, the largest rigid-body and labelled-marker sets, and frames
  beyond those limits, which are refused) against a normal frame of the arm;
- end-to-end latency at 240 Hz with no emulated server latency: from the emulated mid-exposure to
  the bridge's output (``MocapBridge.poll`` returning the frame, same process, the emulator on a
  thread), and the error of the mapped mid-exposure stamp; then from the emulated mid-exposure to
  a received ``mocap/markers`` message (the ``mocap_bridge`` node and a subscriber in this process,
  real DDS): p50, p99, max.
"""
from __future__ import annotations

import argparse
import bisect
import os
import socket
import time
from dataclasses import replace

import numpy as np

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from soft_arm_drivers.mocap.bridge_config import load_mocap_config  # noqa: E402
from soft_arm_drivers.mocap.mocap_bridge import MocapBridge  # noqa: E402
from soft_arm_drivers.mocap.natnet import (ITEM_LIMITS, AnalogData, FrameOfData,  # noqa: E402
                                           LabeledMarker, MarkerSet, RigidBody, ServerInfo, Skeleton,
                                           Version, build_connect_request, build_frame_of_data,
                                           build_server_info, parse_frame_of_data)
from soft_arm_drivers.sim.natnet_emulator import NatNetEmulator  # noqa: E402
from soft_arm_ros.contract import QOS  # noqa: E402
from soft_arm_ros.conversions import stamp_to_seconds  # noqa: E402

from timing import results_path, write_results  # noqa: E402

MARKERS = np.array([[0.002, 0.001, -0.094], [0.008, 0.006, -0.187], [0.020, 0.027, -0.274],
                    [0.041, 0.092, -0.335]])
VERSIONS = ("3.1", "4.0", "4.1")
RATE = 240.0


def _percentiles(samples) -> dict:
    s = np.asarray(samples) * 1e3
    return {"p50_ms": float(np.percentile(s, 50)), "p99_ms": float(np.percentile(s, 99)),
            "max_ms": float(s.max()), "samples": int(s.size)}


def _recorded_frames(version: str, count: int) -> list:
    """``count`` consecutive frame datagrams of the emulator (caught on a loopback socket)."""
    calibration = load_mocap_config().calibration
    with NatNetEmulator(lambda t: MARKERS, version=version, layout="both",
                        calibration=calibration) as emulator, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:
        sink.bind(("127.0.0.1", 0))
        sink.settimeout(2.0)
        emulator.start(stream=False)
        sink.sendto(build_connect_request(), emulator.command_address)
        sink.recv(65535)                                            # server info
        packets = []
        for _ in range(count):
            emulator.send_frame()
            packets.append(sink.recv(65535))
    return packets


def bench_parse(count: int = 2000, repeats: int = 5) -> dict:
    config = load_mocap_config()
    out = {}
    for name in VERSIONS:
        version = Version(*map(int, name.split(".")))
        packets = _recorded_frames(name, count)
        best_codec = best_bridge = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            for packet in packets:
                parse_frame_of_data(packet, version)
            best_codec = min(best_codec, time.perf_counter() - t0)
            with MocapBridge(replace(config, data_port=0, natnet_version="")) as bridge:
                bridge.handle_packet(build_server_info(ServerInfo(
                    "bench", Version(3, 1), version, clock_frequency=10_000_000, data_port=0,
                    multicast=False, multicast_group="0.0.0.0")), time.time())
                t0 = time.perf_counter()
                for packet in packets:
                    bridge.handle_packet(packet, time.time())
                best_bridge = min(best_bridge, time.perf_counter() - t0)
                assert bridge.counters["delivered"] == count, bridge.counters
        out[name] = {"datagram_bytes": len(packets[0]), "codec_frames_per_s": count / best_codec,
                     "bridge_frames_per_s": count / best_bridge}
    return out


FREQUENCY = 10_000_000          # ticks/s of the server clock in the worst-frame bench


def _worst_frames() -> dict:
    """Frames of nearly 64 KiB, by name: what a sender can pack into one datagram."""
    body = RigidBody(1, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    marker = LabeledMarker(70000, (0.0, 0.0, 0.0))
    empty_analog = AnalogData(1, ((),) * ITEM_LIMITS["analog channel"])
    items = FrameOfData(
        frame_number=1, marker_sets=(MarkerSet(""),) * ITEM_LIMITS["marker set"],
        skeletons=(Skeleton(1),) * ITEM_LIMITS["skeleton"],
        force_plates=(empty_analog,) * ITEM_LIMITS["force plate"],
        devices=(empty_analog,) * ITEM_LIMITS["device"],
        labeled_markers=(marker,) * ITEM_LIMITS["labelled marker"],
        rigid_bodies=(body,) * 690)
    return {
        "every kind at its limit": items,
        "1000 rigid bodies + 1000 labelled markers": FrameOfData(
            frame_number=1, rigid_bodies=(body,) * 1000, labeled_markers=(marker,) * 1000),
        "16,000 empty channels of one device (refused)": FrameOfData(
            frame_number=1, devices=(AnalogData(1, ((),) * 16000),)),
        "one marker set of 5,400 markers (refused)": FrameOfData(
            frame_number=1, marker_sets=(MarkerSet("a", ((0.0, 0.0, 0.0),) * 5400),)),
    }


def _numbered(frame: FrameOfData, version: Version, count: int) -> list:
    """``count`` datagrams of ``frame`` numbered 1..count, stamped 1/240 s apart."""
    period = FREQUENCY // 240
    return [build_frame_of_data(version, replace(frame, frame_number=k, camera_mid_exposure=k * period,
                                                 transmit_timestamp=k * period + 100))
            for k in range(1, count + 1)]


def bench_worst_frames(count: int = 300, repeats: int = 5) -> dict:
    """Time [s] of the bridge's packet path per datagram: a normal frame of the arm against the
    frames of :func:`_worst_frames`, on NatNet 3.1 (walked item by item) and 4.1 (sized)."""
    config = replace(load_mocap_config(), data_port=0, natnet_version="")
    normal = FrameOfData(frame_number=1, rigid_bodies=tuple(
        RigidBody(k, tuple(float(v) for v in config.calibration.to_mocap(MARKERS[k - 1:k])[0]),
                  (0.0, 0.0, 0.0, 1.0)) for k in (1, 2, 3, 4)))
    out = {}
    for name in ("3.1", "4.1"):
        version = Version(*map(int, name.split(".")))
        rows = {}
        for label, frame in {"normal frame (4 markers)": normal, **_worst_frames()}.items():
            packets = _numbered(frame, version, count)
            best = np.inf
            for _ in range(repeats):
                with MocapBridge(config) as bridge:
                    bridge.handle_packet(build_server_info(ServerInfo(
                        "bench", Version(3, 1), version, clock_frequency=FREQUENCY, data_port=0,
                        multicast=False, multicast_group="0.0.0.0")), 0.0)
                    t0 = time.perf_counter()
                    for k, packet in enumerate(packets, 1):
                        bridge.handle_packet(packet, 1000.0 + k / 240.0 + 1e-3)
                    best = min(best, (time.perf_counter() - t0) / count)
                    counters = bridge.counters
            rows[label] = {"bytes": len(packets[0]), "seconds_per_frame": best,
                           "delivered": counters["delivered"], "malformed": counters["malformed"]}
        base = rows["normal frame (4 markers)"]["seconds_per_frame"]
        for row in rows.values():
            row["normal_frames"] = row["seconds_per_frame"] / base
        out[name] = rows
    return out


def bench_core_latency(duration: float = 5.0) -> dict:
    config = load_mocap_config()
    with NatNetEmulator(lambda t: MARKERS, version="4.1", rate=RATE, layout="both", latency=0.0,
                        calibration=config.calibration) as emulator:
        with MocapBridge(replace(config, command_port=emulator.command_port, data_port=0)) as bridge:
            emulator.start()
            bridge.connect()
            latency, stamp_error = [], []
            start = time.monotonic()
            while time.monotonic() - start < duration:
                frames = bridge.poll(0.1)
                now = time.time()
                for frame in frames:
                    exposure = emulator.exposure_time(frame.frame_number)
                    if time.monotonic() - start > 0.5:                # the clock map settled
                        latency.append(now - exposure)
                        stamp_error.append(frame.stamp - exposure)
            counters = bridge.counters
    return {"to_core_output": _percentiles(latency), "stamp_error": _percentiles(stamp_error),
            "delivered": counters["delivered"], "rate_hz": counters["delivered"] / duration}


def bench_ros_latency(duration: float = 5.0) -> dict:
    import rclpy
    from geometry_msgs.msg import PoseArray
    from rclpy.lifecycle import TransitionCallbackReturn
    from rclpy.parameter import Parameter

    from soft_arm_drivers.mocap.mocap_bridge_node import MocapBridgeNode
    from soft_arm_ros.runtime import make_executor

    SUCCESS = TransitionCallbackReturn.SUCCESS
    calibration = load_mocap_config().calibration
    with NatNetEmulator(lambda t: MARKERS, version="4.1", rate=RATE, layout="both", latency=0.0,
                        calibration=calibration) as emulator:
        rclpy.init()
        node = listener = None
        received, published = [], 0
        try:
            node = MocapBridgeNode(parameter_overrides=[
                Parameter("rig.mocap.command_port", value=emulator.command_port),
                Parameter("rig.mocap.data_port", value=0)])
            listener = rclpy.create_node("mocap_latency_probe")
            listener.create_subscription(
                PoseArray, "mocap/markers",
                lambda msg: received.append((time.time(), stamp_to_seconds(msg.header.stamp))),
                QOS["mocap/markers"])
            executor = make_executor()
            executor.add_node(node)
            executor.add_node(listener)
            emulator.start()
            # a managed node: configured (it connects), then activated (it publishes)
            if node.trigger_configure() != SUCCESS or node.trigger_activate() != SUCCESS:
                raise RuntimeError("the mocap bridge node did not come up (see its log)")
            start = time.monotonic()
            while time.monotonic() - start < duration + 1.0:
                executor.spin_once(timeout_sec=0.05)
            published = node.published
            executor.shutdown()
        finally:
            if node is not None:
                node.close()
                node.destroy_node()
            if listener is not None:
                listener.destroy_node()
            rclpy.try_shutdown()
        exposures = sorted(e for e in map(emulator.exposure_time, range(1, 4097)) if e is not None)
    if not received:
        raise RuntimeError("no mocap/markers message arrived from the bridge node")
    latency = []
    first = received[0][0] if received else 0.0
    for arrival, stamp in received:
        k = bisect.bisect_left(exposures, stamp - 1e-3)
        if arrival - first > 1.0 and k < len(exposures) and abs(exposures[k] - stamp) < 1e-3:
            latency.append(arrival - exposures[k])
    return {"to_mocap_markers": _percentiles(latency), "received": len(received), "published": published}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=results_path("mocap.json"))
    args = parser.parse_args()
    parse = bench_parse()
    print(f"{'version':8} {'bytes':>6} {'codec frames/s':>15} {'bridge frames/s':>16}")
    for name, row in parse.items():
        print(f"{name:8} {row['datagram_bytes']:6d} {row['codec_frames_per_s']:15.0f} "
              f"{row['bridge_frames_per_s']:16.0f}")
    worst = bench_worst_frames()
    print(f"\n{'bridge packet path':48} {'version':7} {'bytes':>6} {'us/frame':>9} {'x normal':>9}")
    for name, rows in worst.items():
        for label, row in rows.items():
            print(f"{label:48} {name:7} {row['bytes']:6d} {row['seconds_per_frame'] * 1e6:9.1f} "
                  f"{row['normal_frames']:9.1f}")
    core = bench_core_latency()
    ros = bench_ros_latency()
    print(f"\nlatency at {RATE:.0f} Hz, no emulated server latency        p50      p99      max")
    for label, row in (("mid-exposure -> MocapBridge.poll output", core["to_core_output"]),
                       ("mid-exposure stamp error (late if > 0)", core["stamp_error"]),
                       ("mid-exposure -> mocap/markers received", ros["to_mocap_markers"])):
        print(f"{label:46} {row['p50_ms']:7.3f}  {row['p99_ms']:7.3f}  {row['max_ms']:7.3f} ms")
    write_results(args.output, {"parse": parse, "worst_frames": worst, "core": core, "ros": ros})


if __name__ == "__main__":
    main()
