"""``emulated_rig`` node: the ``motor_driver`` node with emulated hardware behind it, and an emulated
Motive server, so that the rig's graph runs without the rig.

- the ``motor_driver`` node, unchanged, on the bus of ``rig.motors`` (``config/emulator.yaml``);
- behind that bus, the CAN motor emulator (:mod:`.can_emulator`): MIT-protocol motors with the plant
  of ``plant.yaml`` (model error, rotors' reflected inertia, encoder resolution) driven by their
  torques through the pulleys, stepped in real time, replying after ``rig.emulator.reply_delay``;
  its motors start out of motor mode with arbitrary zeros, the arm hanging with slack tendons;
- a NatNet server emulator (:mod:`.natnet_emulator`) streaming the same plant's markers, with the
  noise, rate and latency of ``plant.mocap``, to 127.0.0.1 where ``rig.mocap`` says the Motive
  server is (``server_address``, which must be a loopback address, and ``command_port``).

With ``rig.motors.interface`` ``soft_arm_loopback`` (the default) the motors and the arm run in a
process of their own, as on the rig (:class:`.emulated_hardware.HardwareProcess`), on the project's
cross-process bus (channel ``"LOCAL:PEER"``: the driver's UDP port and the motors'), and the Motive
server in another, under the normal scheduling policy (:mod:`.emulated_motive`); with
``virtual`` they run on threads of this process (python-can's in-process bus), where the driver's
cycle competes with the plant for the interpreter lock. A hardware process that dies is hardware
gone: the driver faults on the motors' silence.

Run the ``mocap_bridge`` node against it and the controller nodes as on the rig; configure, zero
(``/motor_driver/zero``) and activate the motor driver as on the rig (it is a managed node). The
emulated hardware is up from the node's start, as a rig is powered before its driver configures.
``soft-arm-experiment <task> --emulated-hardware`` does all of that.

Parameters: ``config/emulator.yaml`` holds ``rig.emulator.*`` (validated, see ``SCHEMA``) and the
``rig.motors`` values of the emulated motors (interface, channel, their firmware torque range),
laid over ``rig.yaml`` beneath the node's own ``rig.motors.*``; ``rig.mocap.*`` as the bridge reads
them; ``plant.*`` and ``arm.*``. A bad value names the key and what is allowed (exit status 2).
"""
from __future__ import annotations

import ipaddress
import json
import os
import sys

import can

from soft_arm_drivers.can.loopback_bus import INTERFACE as LOOPBACK
from soft_arm_drivers.can.loopback_bus import parse_channel
from soft_arm_drivers.can.motor_driver_node import MotorDriverNode
from soft_arm_drivers.mocap.mocap_bridge_node import load_node_config
from soft_arm_drivers.can.mit_protocol import MOTOR_PRESETS
from soft_arm_drivers.mocap.natnet import SUPPORTED_VERSIONS
from soft_arm_model.parameters import (ConfigError, default_config_dir, flatten_tree, load_section,
                                       read_parameters)
from soft_arm_ros.parameters import NodeParameters, parameter_overrides
from soft_arm_ros.runtime import run_node

from .emulated_hardware import HardwareProcess, HardwareSpec, start_hardware
from .plant_config import plant_of

NAMESPACE = "rig.emulator"
INTERFACES = (LOOPBACK, "virtual")
_VERSIONS = [f"{v.major}.{v.minor}" for v in SUPPORTED_VERSIONS]
SCHEMA = {
    "reply_delay": ("float", lambda v: 0 <= v <= 0.01, "a delay in [0, 0.01] s from a frame to its reply"),
    "command_timeout": ("float", lambda v: 0 <= v <= 2,
                        "a time in [0, 2] s: a motor that hears no frame this long zeroes its command "
                        "(the firmware's CAN timeout; 0: none)"),
    "zero_spread": ("float", lambda v: 0 <= v <= 10,
                    "an angle in [0, 10] rad: the motors' zeros at power-up are uniform in +-zero_spread"),
    "natnet_version": ("str", lambda v: v in _VERSIONS, f"a NatNet stream version among {_VERSIONS}"),
    "seed": ("int", lambda v: v >= 0, "an integer >= 0"),
    "firmware": ("str", lambda v: v == "" or v in MOTOR_PRESETS,
                 f"the motor preset the emulated motors' firmware scales are, among {sorted(MOTOR_PRESETS)}, "
                 "or \"\" for those of rig.motors.models"),
}


def read_emulated_motors(path: str | None = None) -> dict:
    """The ``rig.motors`` values of ``config/emulator.yaml`` (or ``path``): dotted, relative to
    rig.motors, validated when laid over rig.yaml."""
    path = path or os.path.join(default_config_dir(), "emulator.yaml")
    rig = read_parameters(path).get("rig")
    motors = rig.get("motors", {}) if isinstance(rig, dict) else None
    if not isinstance(motors, dict):
        raise ConfigError(f"{path}: expected 'rig.motors' parameters under /**.ros__parameters")
    # strings quoted: an override's string value is read as YAML
    return {k: json.dumps(v) if isinstance(v, str) else v
            for k, v in flatten_tree(motors).items()}


def load_emulator_config(path: str | None = None, overrides: dict | None = None) -> dict:
    """``rig.emulator`` of ``config/emulator.yaml`` (or ``path``) with dotted overrides relative to
    it: validated values by key. Raises ConfigError naming ``rig.emulator.<key>``."""
    return load_section(path or os.path.join(default_config_dir(), "emulator.yaml"), NAMESPACE, SCHEMA,
                        overrides)


class EmulatedRigNode(MotorDriverNode):
    """The ``motor_driver`` node (same name, topics, services and parameters) with the emulated
    motors on its bus and the NatNet server emulator of the same plant. :meth:`close` closes the
    driver first (its zero-torque and exit-motor-mode frames reach the emulated motors), then the
    emulators."""

    def __init__(self, config_dir: str | None = None, **node_options):
        self._dir = config_dir or default_config_dir()
        motors = read_emulated_motors(os.path.join(self._dir, "emulator.yaml"))
        self._hardware = self._bus = None
        self._reported_error = False
        super().__init__(self._dir, defaults=motors, **node_options)
        try:
            self._start_emulators()
        except BaseException:
            self.close()
            raise
        self.create_timer(1.0, self._check_emulators)

    def check_config(self, config):
        """Everything the emulation needs is checked before the driver opens its bus."""
        if config.interface not in INTERFACES:
            raise ConfigError(f"rig.motors.interface = {config.interface!r} is not valid for the "
                              f"emulated rig: expected one of {list(INTERFACES)} (a bus the emulated "
                              "motors can share: across processes, or in this one)")
        if config.interface == LOOPBACK:
            try:
                parse_channel(config.channel)
            except can.CanInitializationError as exc:
                raise ConfigError(f"rig.motors.channel = {config.channel!r} is not valid: {exc}") from None
        self.emulator_config = load_emulator_config(os.path.join(self._dir, "emulator.yaml"),
                                                    parameter_overrides(self, NAMESPACE))
        timeout = self.emulator_config["command_timeout"]
        if 0 < timeout <= config.watchdog_timeout:
            raise ConfigError(f"rig.emulator.command_timeout = {timeout:g} is not valid: expected 0 or a "
                              "time longer than rig.motors.watchdog_timeout "
                              f"({config.watchdog_timeout:g} s): the driver's watchdog acts first, the "
                              "firmware's timeout when the driver cannot")
        self.mocap_config = load_node_config(self, self._dir)
        if not ipaddress.IPv4Address(self.mocap_config.server_address).is_loopback:
            raise ConfigError(f"rig.mocap.server_address = {self.mocap_config.server_address!r} is "
                              f"not valid for the emulated rig: expected a loopback address (127.0.0.1)")
        params = NodeParameters(self, self._dir)
        self.arm = params.arm
        self.plant_config = plant_of(params, self.arm)

    def _start_emulators(self):
        c = self.config
        spec = HardwareSpec(c, self.arm, self.plant_config, self.emulator_config, self.mocap_config)
        if c.interface == LOOPBACK:
            self._hardware = HardwareProcess(spec).start()
            where, port = f"process {self._hardware.pid}, bus {c.channel}", self._hardware.command_port
        else:
            self._bus = can.Bus(interface="virtual", channel=c.channel, preserve_timestamps=True)
            self._hardware = start_hardware(spec, self._bus)
            where, port = f"virtual bus {c.channel!r}", self._hardware.motive.command_port
        self.get_logger().info(
            f"emulated rig: motors ({where}) with the plant of plant.yaml, NatNet server on "
            f"{self.mocap_config.server_address}:{port} at {self.plant_config.mocap_rate:g} Hz")

    def _check_emulators(self):
        """Emulated hardware that stopped is hardware gone: the driver faults on the silence; say why."""
        error = self._hardware.error if self._hardware is not None else None
        if error is not None and not self._reported_error:
            self._reported_error = True
            self.get_logger().fatal(f"the emulated motors stopped: {error!r}")

    def close(self):
        """The driver's close (zero torque, exit motor mode), then the emulators; idempotent."""
        hardware, bus = self._hardware, self._bus
        self._hardware = self._bus = None
        try:
            super().close()
        finally:
            try:
                if isinstance(hardware, HardwareProcess):
                    hardware.stop()
                elif hardware is not None:
                    hardware.close()
            finally:
                if bus is not None:
                    bus.shutdown()


def main(args=None) -> int:
    # three threads share the interpreter (driver, motors, Motive): hand it over every 0.5 ms
    # rather than every 5 ms, so that a waiting thread is not held for a whole driver period
    sys.setswitchinterval(5e-4)
    return run_node(EmulatedRigNode, "emulated_rig", args)


if __name__ == "__main__":
    sys.exit(main())
