"""The emulated motors and arm in a process of their own, on the project's cross-process CAN bus:
the motor driver drives them like the in-process emulation, and when their process is killed the
driver latches a fault on the silence and sends nothing but zero torque from then on."""
import os
import signal
import time

import numpy as np
import pytest

from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_drivers.can.loopback_bus import INTERFACE, LoopbackBus, free_udp_ports
from soft_arm_drivers.can.motor_driver import MotorDriver
from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_drivers.sim.emulated_hardware import HardwareProcess, HardwareSpec
from soft_arm_drivers.sim.emulated_rig import load_emulator_config, read_emulated_motors
from soft_arm_drivers.sim.plant_config import load_plant_config
from soft_arm_model import load_arm_config
from soft_arm_model.parameters import ConfigError


def _spec(command_port=None) -> HardwareSpec:
    driver_port, motors_port, free = free_udp_ports(3)
    motors = {**read_emulated_motors(), "channel": f'"{driver_port}:{motors_port}"'}
    driver = load_driver_config(overrides=motors)
    arm = load_arm_config()
    return HardwareSpec(driver, arm, load_plant_config(arm), load_emulator_config(),
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
        now = time.time()
        driver.command(np.full(len(driver.config.motors), tension), now)
        cycle = driver.cycle(now)
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
        driver.enable(time.time())
        cycle = _run(driver, 1.5, 0.5)
        assert driver.fault is None and cycle.diagnostics.mode == "enabled"
        assert np.all(cycle.state.fresh) and np.all(cycle.state.tension > 0.3), cycle.state.tension
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
