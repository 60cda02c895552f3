"""The project's cross-process CAN bus (python-can plugin ``soft_arm_loopback``, UDP on 127.0.0.1):
frames whole, in order, with their time stamps, between two processes; losses counted; bad
channels refused; opened through python-can's plugin registry like any interface."""
import subprocess
import sys
import threading
import time

import can
import pytest

from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_drivers.can import loopback_bus
from soft_arm_drivers.can.loopback_bus import INTERFACE, LoopbackBus, free_udp_ports


def test_free_ports_are_drawn_below_the_ephemeral_range_and_clear_of_dds():
    low = loopback_bus._ephemeral_low()
    if low - loopback_bus._LOWEST_DRAWN < 1000:
        pytest.skip(f"the ephemeral range starts at {low}, leaving no room below it: the kernel's ports")
    for _ in range(20):
        ports = free_udp_ports(3)
        assert len(set(ports)) == 3
        assert all(loopback_bus._LOWEST_DRAWN <= p < low for p in ports)
        assert all((p - 7400) % 250 >= 130 for p in ports)         # no domain's first 60 participants
        assert all(loopback_bus._bindable(p) for p in ports)


def test_the_ephemeral_range_is_read_and_defaults_to_linux_s(tmp_path):
    assert loopback_bus._ephemeral_low(str(tmp_path / "nothing")) == 32768
    (tmp_path / "range").write_text("40000\t60999\n")
    assert loopback_bus._ephemeral_low(str(tmp_path / "range")) == 40000


def test_a_range_that_leaves_no_room_below_it_gives_the_kernels_ports(monkeypatch):
    monkeypatch.setattr(loopback_bus, "_ephemeral_low", lambda: loopback_bus._LOWEST_DRAWN + 10)
    ports = free_udp_ports(2)
    assert len(set(ports)) == 2 and all(p >= loopback_bus._LOWEST_DRAWN + 10 for p in ports)


def test_frames_cross_whole_both_ways_with_their_stamps():
    a, b = free_udp_ports()
    left, right = LoopbackBus(f"{a}:{b}", preserve_timestamps=True), LoopbackBus(f"{b}:{a}")
    try:
        sent = [can.Message(timestamp=123.25, arbitration_id=0x7, is_extended_id=False, data=[1, 2, 3]),
                can.Message(timestamp=124.5, arbitration_id=0x1ABCDE, is_extended_id=True,
                            data=bytes(range(8))),
                can.Message(timestamp=125.0, arbitration_id=0x3, is_extended_id=False, is_remote_frame=True,
                            dlc=4)]
        for m in sent:
            left.send(m)
        for m in sent:
            got = right.recv(timeout=1.0)
            assert got is not None
            fields = ("arbitration_id", "is_extended_id", "is_remote_frame", "dlc", "data", "timestamp")
            assert [getattr(got, f) for f in fields] == [getattr(m, f) for f in fields]
        before = time.time()
        right.send(can.Message(arbitration_id=0x9, is_extended_id=False, data=[9]))   # stamped when sent
        got = left.recv(timeout=1.0)
        assert got.data == bytearray([9]) and before <= got.timestamp <= time.time()
        assert right.recv(timeout=0.05) is None
        with pytest.raises(can.CanOperationError, match="at most 8"):
            left.send(can.Message(arbitration_id=1, is_fd=True, data=bytes(12)))
    finally:
        left.shutdown()
        right.shutdown()


def _poll(bus):
    """``bus.recv(timeout=0.0)`` on a thread, failing (not hanging) the test if it blocks."""
    result = []
    thread = threading.Thread(target=lambda: result.append(bus.recv(timeout=0.0)), daemon=True)
    thread.start()
    thread.join(1.0)
    assert not thread.is_alive(), "recv(timeout=0) blocked"
    return result[0]


def test_a_poll_takes_what_is_waiting_and_never_blocks():
    """recv(timeout=0), the driver's read each cycle: the frames already there, in order, then None
    at once."""
    a, b = free_udp_ports()
    left, right = LoopbackBus(f"{a}:{b}"), LoopbackBus(f"{b}:{a}")
    try:
        assert _poll(right) is None
        for i in range(3):
            left.send(can.Message(arbitration_id=0x10 + i, is_extended_id=False, data=[i]))
        deadline = time.monotonic() + 1.0
        got = []
        while len(got) < 3 and time.monotonic() < deadline:
            msg = _poll(right)
            if msg is not None:
                got.append(msg.arbitration_id)
        assert got == [0x10, 0x11, 0x12]
        assert _poll(right) is None
        assert right.lost == 0
    finally:
        left.shutdown()
        right.shutdown()


def test_lost_frames_are_counted():
    a, b = free_udp_ports()
    left, right = LoopbackBus(f"{a}:{b}"), LoopbackBus(f"{b}:{a}")
    try:
        left.send(can.Message(arbitration_id=1, is_extended_id=False))
        left._sent += 5                                 # five frames that never left
        left.send(can.Message(arbitration_id=2, is_extended_id=False))
        assert [right.recv(timeout=1.0).arbitration_id for _ in range(2)] == [1, 2]
        assert right.lost == 5 and right.reordered == 0
    finally:
        left.shutdown()
        right.shutdown()


SENDER = """
import sys, time, can
from soft_arm_drivers.can.loopback_bus import LoopbackBus
bus = LoopbackBus(sys.argv[1])
time.sleep(0.3)                                         # the receiver is listening by now
for k in range(int(sys.argv[2])):
    bus.send(can.Message(arbitration_id=0x10, is_extended_id=False, data=k.to_bytes(4, "little")))
    if k % 10 == 0:                                     # at most 10000 frames/s, 5x the rig's
        time.sleep(0.001)
bus.shutdown()
"""


def test_frames_cross_processes_in_order():
    a, b = free_udp_ports()
    n = 3000
    receiver = LoopbackBus(f"{a}:{b}")
    try:
        proc = subprocess.Popen([sys.executable, "-c", SENDER, f"{b}:{a}", str(n)])
        got = []
        end = time.monotonic() + 30
        while len(got) < n and time.monotonic() < end:
            m = receiver.recv(timeout=1.0)
            if m is not None:
                got.append(m)
        assert proc.wait(timeout=30) == 0
        assert [int.from_bytes(m.data, "little") for m in got] == list(range(n))
        stamps = [m.timestamp for m in got]
        assert all(s1 <= s2 for s1, s2 in zip(stamps, stamps[1:])) and time.time() - stamps[-1] < 30
        assert receiver.lost == 0 and receiver.reordered == 0
    finally:
        receiver.shutdown()


@pytest.mark.parametrize("channel", ["29500", "a:b", "29500:29500", "80:29501"])
def test_a_bad_channel_is_refused_naming_the_format(channel):
    with pytest.raises(can.CanInitializationError, match="LOCAL:PEER"):
        LoopbackBus(channel)


def test_python_can_and_the_driver_config_take_it_as_an_interface():
    a, b = free_udp_ports()
    bus = can.Bus(interface=INTERFACE, channel=f"{a}:{b}")
    try:
        assert isinstance(bus, LoopbackBus)
    finally:
        bus.shutdown()
    config = load_driver_config(overrides={"interface": json_str(INTERFACE), "channel": json_str(f"{a}:{b}")})
    assert config.interface == INTERFACE


def json_str(value: str) -> str:
    return f'"{value}"'
