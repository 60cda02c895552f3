"""The CAN tests' rig: the driver core and the motor emulator on one in-process ``virtual`` bus, in
lockstep on a simulated clock (the ``make_rig`` fixture of test/conftest.py builds and closes them)."""
import itertools
import os

import can
import numpy as np

from soft_arm_drivers.can.driver_config import load_driver_config
from soft_arm_drivers.can.motor_driver import MotorDriver
from soft_arm_drivers.sim.can_emulator import CanMotorEmulator

_CHANNELS = itertools.count()
R = 0.01                                    # m, pulley radius of rig.yaml
T_STEP = 36.0 / 4095                        # N m, torque LSB of the AK80-9 (+-18 N m over 12 bits)
V_STEP = 100.0 / 4095                       # rad/s, velocity LSB (+-50 rad/s)
P_STEP = 25.0 / 65535                       # rad, position LSB (+-12.5 rad)


def driver_config(**overrides):
    channel = f"motor_driver_{os.getpid()}_{next(_CHANNELS)}"
    # shortenings counted from the zeroing pose here (rig.yaml counts them from the straight arm)
    return load_driver_config(overrides={"interface": "virtual", "channel": channel,
                                         "zero_shortening": [0.0] * 4, **overrides})


class Rig:
    """Driver and emulator on one virtual channel, stepped in lockstep: a driver cycle at t_k, then
    the emulator runs to t_k+1 (the replies to cycle k are read by cycle k + 1)."""

    def __init__(self, cfg, plant=None, **options):
        self.config, self.period, self.k = cfg, 1.0 / cfg.rate, 0
        self.bus = can.Bus(interface="virtual", channel=cfg.channel)
        self.emulator_bus = can.Bus(interface="virtual", channel=cfg.channel, preserve_timestamps=True)
        options.setdefault("reply_delay", 3e-4)
        self.emulator = CanMotorEmulator.for_config(cfg, self.emulator_bus, plant, **options)
        self.now = 0.0                          # the driver's clock [s]: the cycle's time k T in step()
        self.driver = MotorDriver(cfg, self.bus, clock=lambda: self.now)

    @property
    def t(self):
        return self.k * self.period

    def step(self, n=1, tensions=None):
        for _ in range(n):
            self.now = self.t
            if tensions is not None:
                self.driver.command(tensions)
            result = self.driver.cycle()
            self.emulator.advance_to(self.t + self.period)
            self.k += 1
            self.now = self.t                   # between steps the clock reads the next cycle's time
        return result

    def close(self):
        self.driver.close()
        self.bus.shutdown()
        self.emulator_bus.shutdown()


def pull(emulator):
    """direction * torque [N m] each emulated motor applies now (>= 0: pulling)."""
    return np.array([m.motor.direction * emulator.torque(i) for i, m in enumerate(emulator.motors)])
