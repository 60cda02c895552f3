"""The motor driver's configuration (``rig.motors`` of ``config/rig.yaml``): bus, motors (CAN ids,
mounting directions, models and firmware torque ranges), pulley, limits and timeouts, validated on
load (a bad value names ``rig.motors.<key>``, the value and what is allowed).
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass, replace
from typing import Any, Mapping, Optional

import can

from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

from .mit_protocol import MOTOR_PRESETS, MotorLimits

# Bits on the wire of a classic standard-id frame with 8 data bytes: 111 without stuffing, at most
# 135 with worst-case bit stuffing (24 stuff bits in the 98 stuffed bits).
FRAME_BITS, FRAME_BITS_STUFFED = 111, 135

NAMESPACE = "rig.motors"
SCHEMA = {
    "interface": ("str", lambda v: v in can.interfaces.VALID_INTERFACES,
                  "a python-can interface (socketcan on the rig, virtual in tests)"),
    "channel": ("str", lambda v: bool(v), "a non-empty channel name (socketcan: e.g. can0)"),
    "bitrate": ("int", lambda v: 10_000 <= v <= 1_000_000, "a bit rate in [10000, 1000000] bit/s"),
    "rate": ("float", lambda v: 1 <= v <= 2000, "a rate in [1, 2000] Hz"),
    "ids": ("ints", lambda v: len(v) >= 1 and len(set(v)) == len(v) and all(1 <= a <= 255 for a in v),
            "distinct CAN ids in [1, 255], one per tendon"),
    "directions": ("ints", lambda v: all(a in (1, -1) for a in v), "1 or -1, one per tendon"),
    "models": ("strs", lambda v: all(a in MOTOR_PRESETS for a in v),
               f"motor models among {sorted(MOTOR_PRESETS)}, one per tendon"),
    "torque_ranges": ("floats", lambda v: all(0 <= a <= 1000 for a in v),
                      "torque ranges T [N m] in [0, 1000] the firmware was flashed with (+-T on the "
                      "wire), one per tendon; 0 keeps the model's preset"),
    "zero_shortening": ("floats", lambda v: all(abs(a) <= 1 for a in v),
                        "shortenings [m] in [-1, 1] of the pose the motors are zeroed in (from the "
                        "straight arm), one per tendon"),
    "pulley_radius": ("float", lambda v: 0 < v <= 0.5, "a radius in (0, 0.5] m"),
    "max_tension": ("float", lambda v: 0 < v <= 1000, "a tension in (0, 1000] N"),
    "tension_rate_limit": ("float", lambda v: 0 < v <= 1e6, "a rate in (0, 1e6] N/s"),
    "watchdog_timeout": ("float", lambda v: 0 < v <= 1, "a time in (0, 1] s"),
    "reply_timeout": ("float", lambda v: 0 < v <= 1, "a time in (0, 1] s"),
    "max_temperature": ("float", lambda v: 0 < v <= 150, "a temperature in (0, 150] deg C"),
    "command_publisher": ("str", lambda v: v.startswith("/") and len(v) > 1 and " " not in v,
                          "the fully qualified name of the one node whose tendon/command may drive "
                          "the motors (the inner loop's: /inner_loop)"),
}


@dataclass(frozen=True)
class Motor:
    """One tendon's motor: CAN id (1..255, also byte 0 of its replies), mounting direction (+1 or -1:
    the sign of the torque that pulls the tendon), model (a ``MOTOR_PRESETS`` name) and the torque
    range T [N m] its firmware encodes as +-T (0: the model's preset). The 12-bit torque field makes
    one step 2T/4095: a narrower range is a finer tension resolution."""
    can_id: int
    direction: int
    model: str
    torque_range: float = 0.0

    def __post_init__(self):
        if isinstance(self.can_id, bool) or not isinstance(self.can_id, int) or not 1 <= self.can_id <= 255:
            raise ValueError(f"Motor.can_id must be an integer in 1..255, got {self.can_id!r}")
        if self.direction not in (1, -1):
            raise ValueError(f"Motor.direction must be 1 or -1, got {self.direction!r}")
        MotorLimits.preset(self.model)

    @functools.cached_property
    def limits(self) -> MotorLimits:
        """The model's preset with the torque range, built once (it is read for every frame)."""
        preset = MOTOR_PRESETS[self.model]
        if not self.torque_range:
            return preset
        return replace(preset, t_min=-self.torque_range, t_max=self.torque_range)


@dataclass(frozen=True)
class DriverConfig:
    """Validated ``rig.motors`` parameters: bus (python-can interface, channel, bit rate [bit/s]),
    cycle rate [Hz], the motors in tendon order, pulley radius [m], tension limit [N] and rate limit
    [N/s], watchdog and reply timeouts [s], temperature limit [deg C], the shortenings of the
    zeroing pose [m] and the node allowed to command the motors."""
    interface: str
    channel: str
    bitrate: int
    rate: float
    motors: tuple
    pulley_radius: float
    max_tension: float
    tension_rate_limit: float
    watchdog_timeout: float
    reply_timeout: float
    max_temperature: float
    zero_shortening: tuple = ()
    command_publisher: str = "/inner_loop"


def bus_load(config: DriverConfig) -> tuple[float, float]:
    """Fraction of the bus one cycle takes (a command and a reply per motor at ``rate``): without bit
    stuffing and with worst-case stuffing. Replies are counted at 8 bytes."""
    frames_per_second = 2 * len(config.motors) * config.rate
    return (frames_per_second * FRAME_BITS / config.bitrate,
            frames_per_second * FRAME_BITS_STUFFED / config.bitrate)


def parse_driver_config(values: Mapping[str, Any], n_tendons: Optional[int] = None) -> DriverConfig:
    """Cross-checks of validated ``rig.motors`` values (dotted key -> value, as ``validate_tree``
    returns them); ``n_tendons``: the arm's tendon count the motors must match. Raises ConfigError
    naming ``rig.motors.<key>``, the value and what is allowed."""
    def bad(key, allowed):
        return ConfigError(f"{NAMESPACE}.{key} = {_show(values[key])} is not valid: expected {allowed}")

    n = len(values["ids"])
    if n_tendons is not None and n != n_tendons:
        raise bad("ids", f"{n_tendons} CAN ids, one per tendon of the arm")
    for key in ("directions", "models", "torque_ranges", "zero_shortening"):
        if len(values[key]) != n:
            raise bad(key, f"{n} values, one per motor in {NAMESPACE}.ids")
    motors = tuple(Motor(i, d, m, t) for i, d, m, t in zip(values["ids"], values["directions"],
                                                           values["models"], values["torque_ranges"]))
    torque = min(m.limits.t_max for m in motors)
    most = torque / values["pulley_radius"]
    if values["max_tension"] > most:
        raise bad("max_tension", f"a tension in (0, {most:g}] N: the smallest torque range of the motors "
                                 f"({torque:g} N m) over pulley_radius ({values['pulley_radius']:g} m)")
    shortest = 2.0 / values["rate"]
    for key in ("watchdog_timeout", "reply_timeout"):
        if values[key] < shortest:
            raise bad(key, f"a time of at least two cycles, {shortest:g} s at rate {values['rate']:g} Hz")
    config = DriverConfig(values["interface"], values["channel"], values["bitrate"], values["rate"], motors,
                          values["pulley_radius"], values["max_tension"], values["tension_rate_limit"],
                          values["watchdog_timeout"], values["reply_timeout"], values["max_temperature"],
                          tuple(values["zero_shortening"]), values["command_publisher"])
    if bus_load(config)[0] > 1.0:
        most_rate = config.bitrate / (2 * n * FRAME_BITS)
        raise bad("rate", f"a rate in [1, {most_rate:.0f}] Hz: {n} motors exchange two frames of "
                          f"{FRAME_BITS} bits each per cycle on a {config.bitrate} bit/s bus")
    return config


def _show(value):
    return repr(list(value) if isinstance(value, tuple) else value)


def load_driver_config(path: Optional[str] = None, overrides: Optional[Mapping[str, Any]] = None,
                       n_tendons: Optional[int] = None) -> DriverConfig:
    """Load ``rig.motors`` from a ROS 2 parameter file (default: the package's ``rig.yaml``) with
    dotted-key overrides relative to ``rig.motors``, validate and cross-check it."""
    path = path or os.path.join(default_config_dir(), "rig.yaml")
    values = load_section(path, NAMESPACE, SCHEMA, overrides)
    try:
        return parse_driver_config(values, n_tendons)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def open_bus(config: DriverConfig) -> can.BusABC:
    """The python-can bus of ``config`` (socketcan ignores the bit rate: set it with ``ip link``)."""
    return can.Bus(interface=config.interface, channel=config.channel, bitrate=config.bitrate)
