"""The emulated motors and arm in a process of their own, on the project's cross-process CAN bus:
the motor driver drives them like the in-process emulation, and when their process is killed the
driver latches a fault on the silence and sends nothing but zero torque from then on. Their Motive
server runs in another process, under the normal policy, and ends with them."""
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_drivers.can.loopback_bus import INTERFACE, LoopbackBus, free_udp_ports
from soft_arm_drivers.can.motor_driver import MotorDriver
from soft_arm_experiments import realtime
from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_drivers.mocap.natnet import MessageId, build_connect_request, parse_packet
from soft_arm_drivers.sim.emulated_hardware import HardwareProcess, HardwareSpec
from soft_arm_drivers.sim.emulated_rig import load_emulator_config, read_emulated_motors
from soft_arm_drivers.sim.plant_config import load_plant_config
from soft_arm_model import load_arm_config
from soft_arm_model.parameters import ConfigError


def _spec(command_port=None) -> HardwareSpec:
    driver_port, motors_port, free = free_udp_ports(3)
    # the driver runs in this test's process under the normal policy: relaxed timeouts, as the node
    # tests use on a loaded machine (a 54 ms silence tripped the rig's 50 ms once in a suite), the
    # motors' firmware timeout longer than the driver's watchdog
    motors = {**read_emulated_motors(), "channel": f'"{driver_port}:{motors_port}"', "reply_timeout": 0.2,
              "watchdog_timeout": 0.2}
    driver = load_driver_config(overrides=motors)
    arm = load_arm_config()
    emulator = load_emulator_config(overrides={"command_timeout": 0.4})
    return HardwareSpec(driver, arm, load_plant_config(arm), emulator,
                        load_mocap_config(overrides={"mocap.command_port": command_port or free,
                                                     "mocap.data_port": 0}))


class RecordingBus(LoopbackBus):
    """The driver's end, keeping every frame it sends with the time it was sent."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.sent = []

    def send(self, msg, timeout=None):
        self.sent.append((time.monotonic(), bytes(msg.data)))
        super().send(msg, timeout)


def _run(driver, seconds, tension, rate=500.0):
    """Cycle the driver in real time for ``seconds`` commanding ``tension`` [N] on every motor."""
    end = time.monotonic() + seconds
    cycle = None
    while time.monotonic() < end:
        driver.command(np.full(len(driver.config.motors), tension))
        cycle = driver.cycle()
        time.sleep(1.0 / rate)
    return cycle


def test_the_driver_drives_the_motors_of_another_process_and_faults_when_it_dies():
    spec = _spec()
    assert spec.driver.interface == INTERFACE
    hardware = HardwareProcess(spec).start()
    bus = RecordingBus(spec.driver.channel)
    driver = MotorDriver(spec.driver, bus)
    try:
        assert hardware.pid != os.getpid() and hardware.error is None
        # the set-up is out of the garbage collector: no full collection walks it mid-run
        assert hardware.frozen_objects > 50_000
        driver.zero()
        driver.enable()
        cycle = _run(driver, 1.5, 0.5)
        assert driver.fault is None and cycle.diagnostics.mode == "enabled"
        # every motor answers the cycles (a reply from the other process may land just after the
        # last one: its freshness is a race, its age is not)
        answered = cycle.diagnostics.motors
        assert all(m.reply_age < spec.driver.reply_timeout and m.replies > 100 for m in answered), answered
        assert np.all(cycle.state.tension > 0.3), cycle.state.tension
        os.kill(hardware.pid, signal.SIGKILL)
        killed = time.monotonic()
        _run(driver, 0.5, 0.5)
        assert driver.fault is not None and "silent" in driver.fault, driver.fault
        assert hardware.error is not None
        # from the trip on, every frame is zero torque (the trip came within the reply timeout)
        zero = {bytes(f) for f in driver._zero_frames}
        tripped = min(t for t, data in bus.sent if t > killed and data in zero)
        assert tripped - killed < spec.driver.reply_timeout + 0.1
        assert all(data in zero for t, data in bus.sent if t >= tripped)
    finally:
        driver.close()
        bus.shutdown()
        hardware.stop()


def test_a_hardware_process_that_cannot_start_says_why():
    first = _spec()
    hardware = HardwareProcess(first).start()
    try:
        # the same Motive address and port: the second emulated server cannot bind it
        second = _spec(command_port=first.mocap.command_port)
        with pytest.raises(ConfigError, match="cannot bind"):
            HardwareProcess(second).start()
    finally:
        hardware.stop()


# the emulated hardware started by a process under SCHED_FIFO, as the emulated_rig node is
UNDER_FIFO = f"""
import sys
sys.path.insert(0, {os.path.dirname(__file__)!r})
from test_emulated_hardware import _spec
from soft_arm_drivers.sim.emulated_hardware import HardwareProcess
hardware = HardwareProcess(_spec()).start()
print(hardware.pid, hardware.command_port, flush=True)
sys.stdin.read()
hardware.stop()
"""


def _ended(pid):
    """Whether process ``pid`` is gone or a zombie (its parent killed, nobody may reap it here)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not realtime.permitted(realtime.HARDWARE_PRIORITY),
                    reason="SCHED_FIFO is not permitted here")
def test_the_motive_server_runs_apart_under_the_normal_policy_and_ends_with_the_hardware():
    def under_fifo():
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(realtime.HARDWARE_PRIORITY))

    proc = subprocess.Popen([sys.executable, "-c", UNDER_FIFO], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, preexec_fn=under_fifo)
    try:
        hardware, command_port = (int(v) for v in proc.stdout.readline().split())
        motive = [pid for pid in realtime.child_processes(hardware)
                  if b"soft_arm_drivers.sim.emulated_motive" in open(f"/proc/{pid}/cmdline", "rb").read()]
        assert len(motive) == 1, motive
        motive = motive[0]
        # the hardware inherits its creator's policy; its Motive server, a process of its own, not
        assert os.sched_getscheduler(hardware) == os.SCHED_FIFO
        assert {os.sched_getscheduler(tid) for tid in realtime.threads(motive)} == {os.SCHED_OTHER}
        assert len(realtime.threads(motive)) >= 2             # its main thread and the NatNet server's
        assert not any(t.startswith(b"natnet") for t in _thread_names(hardware))
        # the server answers a NatNet client on the reported port
        assert _answers(command_port)
        os.kill(hardware, signal.SIGKILL)
        deadline = time.monotonic() + 10.0
        while not _ended(motive) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _ended(motive)
    finally:
        proc.kill()
        proc.wait()


def _thread_names(pid):
    return [open(f"/proc/{pid}/task/{tid}/comm", "rb").read().strip() for tid in realtime.threads(pid)]


def _answers(command_port) -> bool:
    """Whether a NatNet connect request to 127.0.0.1:command_port gets the server's info."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(5.0)
        sock.sendto(build_connect_request(), ("127.0.0.1", command_port))
        message_id, _ = parse_packet(sock.recv(65536))
    return message_id == MessageId.NAT_SERVERINFO
