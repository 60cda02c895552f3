"""CAN motor driver core, without ROS: one MIT-protocol motor per tendon, tensions in, shortenings out.

Torque mode of the MIT mini-cheetah protocol (:mod:`.mit_protocol`): kp = kd = 0 and a feed-forward
torque, so each motor is a torque source. With the pulley radius r [m] and the mounting direction
d = +1 or -1 of a motor (the sign of the motor torque that pulls its tendon):

- tension T [N] -> motor torque ``tau = d r T`` [N m]; a measured torque gives ``T = d tau / r``;
- encoder angle a [rad], counted from the motor's zero (set by :meth:`MotorDriver.zero`) -> tendon
  shortening ``s = d r a + s0`` [m], ``s0`` the configured shortening of the zeroing pose
  (``zero_shortening``: the controller's model of the hanging arm, so that the shortenings count
  from the straight arm as the controller's do); the angular rate gives ``ds/dt = d r da/dt`` [m/s].

Commands are never on the pushing side: tensions are clipped to [0, max_tension] and the 12-bit torque
field is rounded to the nearest step that does not push (``tension_frame``), so a zero tension is the
smallest pulling torque the field holds (half a step, 4.4 mN m on an AK80-9).

Timing. :meth:`MotorDriver.cycle` is called at a fixed rate with the time ``now`` [s] of a monotonic
clock; the core never reads a clock, so a run with explicit times is reproducible. A cycle reads the
replies that arrived since the previous one (the answers to its commands: on a real bus a few hundred
microseconds after them), checks the safety conditions, then sends one frame to every motor. A reading
thus reaches the caller up to one period after it was taken; its time stamp is the bus's receive
stamp of the reply (socketcan: the kernel's CLOCK_REALTIME, i.e. ROS system time; a virtual bus: the
sender's stamp when that bus preserves time stamps, as the emulator's does).

Modes: ``disabled`` (at start and after :meth:`~MotorDriver.disable`: motors out of motor mode, polled
with zero-torque frames, which a motor in rest mode ignores but answers), ``enabled`` (the latest
command, rate limited, every cycle) and ``fault`` (latched: zero torque to every motor until
:meth:`~MotorDriver.enable`). A fault is latched, with its reason, when

- the latest command is older than ``watchdog_timeout`` (enabled only);
- a motor has not replied for ``reply_timeout``, reports a non-zero error code, or a temperature
  above ``max_temperature``;
- a frame cannot be sent or received (bus error);
- :meth:`~MotorDriver.estop` is called (which also takes the motors out of motor mode).

The constructor takes every motor out of motor mode, whatever a previous process left; :meth:`close`
(also on leaving a ``with`` block, exception or not) sends zero torque and exit-motor-mode. Not
thread-safe: one thread calls everything.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, replace
from typing import Any, Mapping, NamedTuple, Optional, Sequence

import can
import numpy as np

from soft_arm_model.parameters import (ConfigError, apply_overrides, default_config_dir, read_parameters,
                                       validate_tree)

from .mit_protocol import (ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, MOTOR_ERRORS, MOTOR_PRESETS, REPLY_LENGTHS,
                           SET_ZERO_POSITION, MotorLimits, decode_reply, torque_command)

__all__ = ["DriverConfig", "Cycle", "Diagnostics", "DriverState", "HOST_ID", "Motor", "MotorDiagnostics",
           "MotorDriver", "NAMESPACE", "SCHEMA", "bus_load", "load_driver_config", "open_bus",
           "parse_driver_config", "tension_frame"]

HOST_ID = 0                 # arbitration id of the replies (the motors' "master id")
SEND_TIMEOUT = 5e-4         # s a send may wait for room in the transmit queue before it is a fault
_TORQUE_TOP = (1 << 12) - 1  # the torque field of a command frame has 12 bits
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
    [N/s], watchdog and reply timeouts [s], temperature limit [deg C]."""
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
                          tuple(values["zero_shortening"]))
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
    rig = read_parameters(path).get("rig")
    tree = rig.get("motors") if isinstance(rig, dict) else None
    if not isinstance(tree, dict):
        raise ConfigError(f"{path}: no '{NAMESPACE}' parameters under /**.ros__parameters")
    try:
        values = validate_tree(apply_overrides(tree, overrides, SCHEMA, NAMESPACE), SCHEMA, NAMESPACE)
        return parse_driver_config(values, n_tendons)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def open_bus(config: DriverConfig) -> can.BusABC:
    """The python-can bus of ``config`` (socketcan ignores the bit rate: set it with ``ip link``)."""
    return can.Bus(interface=config.interface, channel=config.channel, bitrate=config.bitrate)


def tension_frame(motor: Motor, pulley_radius: float, tension: float) -> bytes:
    """Torque-mode command frame pulling the tendon with ``tension`` >= 0 [N] through the pulley
    ``pulley_radius`` [m]: torque ``direction * r * T`` rounded to the nearest step of the 12-bit
    field, or one step further when the nearest would push (decodes with ``direction * torque >= 0``)."""
    lim = motor.limits
    span = lim.t_max - lim.t_min
    raw = min(max(round((motor.direction * pulley_radius * tension - lim.t_min) * _TORQUE_TOP / span), 0),
              _TORQUE_TOP)
    if motor.direction * (raw * span / _TORQUE_TOP + lim.t_min) < 0:
        raw += motor.direction
    # a quarter step above the level, so that the codec's truncation lands on ``raw`` exactly
    return torque_command(lim, lim.t_min + (raw + 0.25) * span / _TORQUE_TOP)


@dataclass(frozen=True)
class DriverState:
    """The latest reading of every motor, in tendon order: shortening [m], its rate [m/s], measured
    tension [N] (from the reply torque), sensor time stamps [s] of the replies (NaN before the
    first), which motors replied in this cycle, and the tensions sent in this cycle [N]."""
    shortening: np.ndarray
    rate: np.ndarray
    tension: np.ndarray
    stamps: np.ndarray
    fresh: np.ndarray
    command: np.ndarray

    @property
    def complete(self) -> bool:
        """Every motor replied in this cycle."""
        return bool(self.fresh.all())

    @property
    def stamp(self) -> float:
        """The oldest of the motors' sensor time stamps [s] (NaN until every motor has replied)."""
        return float(self.stamps.min())


@dataclass(frozen=True)
class MotorDiagnostics:
    """One motor: temperature [deg C] and error code of its latest 8-byte reply (None if it sends 6
    bytes or has not replied), the error's text, time since its latest reply [s], replies read."""
    can_id: int
    temperature: Optional[int]
    error: Optional[int]
    error_text: Optional[str]
    reply_age: float
    replies: int


@dataclass(frozen=True)
class Diagnostics:
    """Mode, latched fault reason (None without), age of the latest command [s] (inf without), and
    counters: watchdog trips, rejected commands, frames that are no reply of a motor of ours, CAN
    error frames, cycles later than 1.5 periods, cycles; whether zero() was called; per motor."""
    mode: str
    fault: Optional[str]
    command_age: float
    stale_commands: int
    rejected_commands: int
    foreign_frames: int
    error_frames: int
    late_cycles: int
    cycles: int
    zeroed: bool
    motors: tuple


class Cycle(NamedTuple):
    """What one :meth:`MotorDriver.cycle` returns."""
    state: DriverState
    diagnostics: Diagnostics


class MotorDriver:
    """The motors of ``config`` on ``bus`` (default: opened from ``config``, and shut down by
    :meth:`close`). Replies are the standard frames to arbitration id ``host_id``, matched to their
    motor by the id in their first byte; any other frame is counted as foreign (filtered here, not
    by the bus, whose software filters would end a non-blocking read early). See the module
    docstring for modes, timing and safety."""

    def __init__(self, config: DriverConfig, bus: Optional[can.BusABC] = None, host_id: int = HOST_ID):
        self.config = c = config
        self._owns_bus = bus is None
        self.bus = open_bus(c) if bus is None else bus
        self.host_id = host_id
        n = len(c.motors)
        self._index = {m.can_id: i for i, m in enumerate(c.motors)}
        self._zero_frames = [tension_frame(m, c.pulley_radius, 0.0) for m in c.motors]
        self.mode, self.fault, self.zeroed = "disabled", None, False
        self._target, self._applied = np.zeros(n), np.zeros(n)
        self._command_time: Optional[float] = None
        self._last_cycle: Optional[float] = None
        self._watch_from: Optional[float] = None     # silence counts from here (first cycle, enable)
        self._reply_time = np.full(n, -math.inf)      # ``now`` of the cycle that read the last reply
        self._shortening, self._rate, self._tension = np.zeros(n), np.zeros(n), np.zeros(n)
        self._zero_offset = np.array(config.zero_shortening or (0.0,) * n, dtype=float)
        self._stamps = np.full(n, math.nan)
        self._temperature: list = [None] * n
        self._error: list = [None] * n
        self._replies = [0] * n
        self.stale_commands = self.rejected_commands = self.foreign_frames = self.error_frames = 0
        self.late_cycles = self.cycles = 0
        self._closed = False
        self._send_all(EXIT_MOTOR_MODE)

    # -- commands and modes --------------------------------------------------------------------
    def command(self, tensions: Sequence[float], now: float):
        """Set the tensions [N] to apply from the next cycle on, received at ``now`` [s] (the watchdog
        counts from there). Clipped to [0, max_tension]; a wrong length, NaN or infinity raises
        ValueError and leaves the previous command (and its age) in place."""
        u = np.asarray(tensions, dtype=float)
        if u.shape != self._target.shape:
            self.rejected_commands += 1
            raise ValueError(f"expected {self._target.size} tensions, got shape {u.shape}")
        if not np.all(np.isfinite(u)):
            self.rejected_commands += 1
            raise ValueError(f"tensions must be finite, got {u.tolist()}")
        self._target = np.clip(u, 0.0, self.config.max_tension)
        self._command_time = float(now)

    def enable(self, now: float):
        """Clear a latched fault, enter motor mode on every motor and start from zero tension: the
        watchdog expects a command within ``watchdog_timeout`` of ``now`` [s], every motor a reply
        within ``reply_timeout``."""
        self.mode, self.fault = "enabled", None
        self._target, self._applied = np.zeros_like(self._target), np.zeros_like(self._applied)
        self._command_time = self._watch_from = float(now)
        self._send_all(ENTER_MOTOR_MODE)

    def disable(self):
        """Zero torque and exit motor mode on every motor. A latched fault stays latched."""
        if self.mode == "enabled":
            self.mode = "disabled"
        self._applied = np.zeros_like(self._applied)
        self._send_zero()
        self._send_all(EXIT_MOTOR_MODE)

    def estop(self):
        """Emergency stop: latch the fault ``e-stop`` (unless one is latched already), zero torque and
        exit motor mode on every motor at once."""
        self._trip("e-stop")
        self._send_zero()
        self._send_all(EXIT_MOTOR_MODE)

    def zero(self):
        """Set every motor's current angle as its zero: the shortenings read ``zero_shortening`` there
        from then on. Only with the tendons slack: RuntimeError while enabled."""
        if self.mode == "enabled":
            raise RuntimeError("zeroing needs slack tendons: disable the motors first")
        self._send_all(SET_ZERO_POSITION)
        self.zeroed = True

    def close(self):
        """Zero torque and exit motor mode on every motor; shut the bus down if the driver opened it.
        Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._send_zero()
            self._send_all(EXIT_MOTOR_MODE)
        finally:
            if self._owns_bus:
                self.bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- the cycle -----------------------------------------------------------------------------
    def cycle(self, now: float) -> Cycle:
        """One period at ``now`` [s] (never earlier than the previous cycle's): read the replies,
        check the safety conditions, send a frame to every motor; the state and diagnostics."""
        if self._closed:
            raise RuntimeError("the driver is closed")
        now = float(now)
        if self._last_cycle is not None and now < self._last_cycle:
            raise ValueError(f"cycle time went backwards: {now} after {self._last_cycle}")
        dt = 0.0 if self._last_cycle is None else now - self._last_cycle
        if dt > 1.5 / self.config.rate:
            self.late_cycles += 1
        if self._watch_from is None:
            self._watch_from = now
        fresh = self._read(now)
        self._check(now)
        if self.mode == "enabled":
            step = self.config.tension_rate_limit * dt
            self._applied = self._applied + np.clip(self._target - self._applied, -step, step)
            for i, motor in enumerate(self.config.motors):
                self._send(motor.can_id, tension_frame(motor, self.config.pulley_radius, self._applied[i]))
        else:
            self._send_zero()
        self._last_cycle = now
        self.cycles += 1
        sent = self._applied.copy() if self.mode == "enabled" else np.zeros_like(self._applied)
        state = DriverState(self._shortening.copy(), self._rate.copy(), self._tension.copy(),
                            self._stamps.copy(), fresh, sent)
        return Cycle(state, self.diagnostics(now))

    def diagnostics(self, now: float) -> Diagnostics:
        """Mode, fault, counters and per-motor status at ``now`` [s]."""
        motors = tuple(
            MotorDiagnostics(m.can_id, self._temperature[i], self._error[i],
                             None if self._error[i] is None else
                             MOTOR_ERRORS.get(self._error[i], f"unknown error code {self._error[i]}"),
                             now - self._reply_time[i], self._replies[i])
            for i, m in enumerate(self.config.motors))
        age = math.inf if self._command_time is None else now - self._command_time
        return Diagnostics(self.mode, self.fault, age, self.stale_commands, self.rejected_commands,
                           self.foreign_frames, self.error_frames, self.late_cycles, self.cycles,
                           self.zeroed, motors)

    def _read(self, now: float) -> np.ndarray:
        """Take every frame waiting on the bus; update the readings of the motors that replied."""
        fresh = np.zeros(len(self.config.motors), dtype=bool)
        c = self.config
        while True:
            try:
                msg = self.bus.recv(timeout=0.0)
            except can.CanError as exc:
                self._trip(f"CAN receive failed: {exc}")
                break
            if msg is None:
                break
            if msg.is_error_frame:
                self.error_frames += 1
                continue
            ours = msg.arbitration_id == self.host_id and not msg.is_extended_id \
                and not msg.is_remote_frame and len(msg.data) in REPLY_LENGTHS
            i = self._index.get(msg.data[0]) if ours else None
            if i is None:
                self.foreign_frames += 1
                continue
            motor = c.motors[i]
            reply = decode_reply(motor.limits, msg.data)
            d = motor.direction
            self._shortening[i] = d * c.pulley_radius * reply.position + self._zero_offset[i]
            self._rate[i] = d * c.pulley_radius * reply.velocity
            self._tension[i] = d * reply.torque / c.pulley_radius
            self._stamps[i] = msg.timestamp
            self._reply_time[i] = now
            self._replies[i] += 1
            self._temperature[i], self._error[i] = reply.temperature, reply.error
            fresh[i] = True
            if reply.error:
                self._trip(f"motor {motor.can_id} reports error {reply.error} ({reply.error_text})")
            if reply.temperature is not None and reply.temperature > c.max_temperature:
                self._trip(f"motor {motor.can_id} at {reply.temperature} deg C, above max_temperature "
                           f"{c.max_temperature:g}")
        return fresh

    def _check(self, now: float):
        """Reply timeouts (every mode) and the command watchdog (enabled)."""
        c = self.config
        silence = now - np.maximum(self._reply_time, self._watch_from)
        for i in np.flatnonzero(silence > c.reply_timeout):
            self._trip(f"motor {c.motors[i].can_id} silent for {silence[i]:.4f} s "
                       f"(reply_timeout {c.reply_timeout:g} s)")
        if self.mode == "enabled" and now - self._command_time > c.watchdog_timeout:
            self.stale_commands += 1
            self._trip(f"stale command: the latest is {now - self._command_time:.4f} s old "
                       f"(watchdog_timeout {c.watchdog_timeout:g} s)")

    def _trip(self, reason: str):
        """Latch a fault (the first reason is kept until enable()); the cycle sends zero torque."""
        if self.mode != "fault":
            self.mode, self.fault = "fault", reason
        self._applied = np.zeros_like(self._applied)

    def _send(self, can_id: int, data: bytes):
        try:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False),
                          timeout=SEND_TIMEOUT)
        except can.CanError as exc:
            self._trip(f"CAN send to motor {can_id} failed: {exc}")

    def _send_all(self, data: bytes):
        for motor in self.config.motors:
            self._send(motor.can_id, data)

    def _send_zero(self):
        for motor, frame in zip(self.config.motors, self._zero_frames):
            self._send(motor.can_id, frame)
