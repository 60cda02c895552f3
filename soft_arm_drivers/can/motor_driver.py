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

Timing. Every safety decision is taken on the driver's own clock (``clock``, default
:func:`time.monotonic`; tests give it a simulated one), never on a time a caller or a message
carries: a command's age counts from its receipt on that clock, whatever stamp it bears, so that a
command stamped on another clock, in the future or with NaN cannot hold the watchdog off, and a
step of the wall clock (NTP) moves nothing. :meth:`MotorDriver.cycle` is called at a fixed rate. A
cycle reads the replies that arrived since the previous one (the answers to its commands: on a real
bus a few hundred microseconds after them), checks the safety conditions, then sends one frame to
every motor. A reading thus reaches the caller up to one period after it was taken; its time stamp
is the bus's receive stamp of the reply (socketcan: the kernel's CLOCK_REALTIME, i.e. ROS system
time; a virtual bus: the sender's stamp when that bus preserves time stamps, as the emulator's
does): it stamps the state for the graph and is never used for a safety decision.

Modes: ``disabled`` (at start and after :meth:`~MotorDriver.disable`: motors out of motor mode, polled
with zero-torque frames, which a motor in rest mode ignores but answers), ``enabled`` (the latest
command, rate limited, every cycle) and ``fault`` (latched: zero torque to every motor until
:meth:`~MotorDriver.enable`). A fault is latched, with its reason, when

- the latest command is older than ``watchdog_timeout``, or a cycle comes more than
  ``watchdog_timeout`` after the previous one: nothing watched the motors meanwhile (enabled only);
- a motor has not replied for ``reply_timeout``, reports a non-zero error code, or a temperature
  above ``max_temperature``;
- a motor's reported velocity disagrees with the rate of its reported position by a factor that
  says the preset of ``rig.motors.models`` is not its firmware's (:mod:`.velocity_scale`);
- a frame cannot be sent or received (bus error);
- :meth:`~MotorDriver.estop` is called (which also takes the motors out of motor mode).

The constructor takes every motor out of motor mode, whatever a previous process left; :meth:`close`
(also on leaving a ``with`` block, exception or not) sends zero torque and exit-motor-mode. Not
thread-safe: one thread calls everything.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional, Sequence

import can
import numpy as np

from .driver_config import DriverConfig, Motor, open_bus
from .mit_protocol import (ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, MOTOR_ERRORS, REPLY_LENGTHS, SET_ZERO_POSITION,
                           decode_reply, torque_frame)
from .order_statistics import percentile
from .velocity_scale import VelocityScaleCheck

__all__ = ["Cycle", "Diagnostics", "DriverState", "HOST_ID", "MotorDiagnostics", "MotorDriver",
           "tension_frame"]

HOST_ID = 0                 # arbitration id of the replies (the motors' "master id")
SEND_TIMEOUT = 5e-4         # s a send may wait for room in the transmit queue before it is a fault
_TORQUE_TOP = (1 << 12) - 1  # the torque field of a command frame has 12 bits


def tension_frame(motor: Motor, pulley_radius: float, tension: float) -> bytes:
    """Torque-mode command frame pulling the tendon with ``tension`` [N] through the pulley
    ``pulley_radius`` [m] (> 0): the tension clipped to [0, what the motor's torque range pulls],
    its torque ``direction * r * T`` rounded to the nearest step of the 12-bit field, or one step
    further when the nearest would push. Whatever the tension, the frame decodes with
    ``direction * torque >= 0``: a tendon can only be pulled. NaN or infinity raises ValueError."""
    tension = float(tension)
    if not math.isfinite(tension):
        raise ValueError(f"tension must be finite, got {tension!r}")
    if not (math.isfinite(pulley_radius) and pulley_radius > 0):
        raise ValueError(f"pulley_radius must be a finite radius > 0 m, got {pulley_radius!r}")
    lim = motor.limits
    span = lim.t_max - lim.t_min
    most = (lim.t_max if motor.direction > 0 else -lim.t_min) / pulley_radius
    tension = min(max(tension, 0.0), most)
    raw = min(max(round((motor.direction * pulley_radius * tension - lim.t_min) * _TORQUE_TOP / span), 0),
              _TORQUE_TOP)
    if motor.direction * (raw * span / _TORQUE_TOP + lim.t_min) < 0:
        raw += motor.direction
    return torque_frame(lim, raw)


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
    bytes or has not replied), the error's text, time since its latest reply [s], replies read, and
    the rate of its position over its reported velocity in the last window it moved through
    (:mod:`.velocity_scale`; 1 when the preset fits its firmware, NaN before it has moved)."""
    can_id: int
    temperature: Optional[int]
    error: Optional[int]
    error_text: Optional[str]
    reply_age: float
    replies: int
    velocity_ratio: float = math.nan


@dataclass(frozen=True)
class Diagnostics:
    """Mode, latched fault reason (None without), age of the latest command [s] on the driver's
    clock (inf without), and counters: watchdog trips, rejected commands, frames that are no reply of
    a motor of ours, CAN error frames, cycles later than 1.5 periods, cycles; whether zero() was
    called; per motor; replies refused for a receive time that is no number (their motor's silence
    counts on); commands with a tension above ``max_tension``, clipped to it."""
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
    unstamped_frames: int = 0
    clipped_commands: int = 0


@dataclass(frozen=True)
class CycleStatistics:
    """The driver's timing over its last ``cycles`` periods (at most :data:`PERIOD_WINDOW`): the
    period between cycle starts [s] (median, 99th percentile, maximum; nan before two cycles), the
    99th percentile of its error from the nominal 1/rate [s], and the deadline misses (cycles later
    than 1.5 periods) since the driver started."""
    cycles: int
    period_p50: float
    period_p99: float
    period_max: float
    period_error_p99: float
    deadline_misses: int


PERIOD_WINDOW = 1000            # cycles the statistics look back over (2 s at 500 Hz)
LATE = 1.5                      # periods: a cycle further from the last is late (counted)
FIELD_END = 4                   # steps of the 16-bit position field: a reading this near its end saturates


class Cycle(NamedTuple):
    """What one :meth:`MotorDriver.cycle` returns."""
    state: DriverState
    diagnostics: Diagnostics


class MotorDriver:
    """The motors of ``config`` on ``bus`` (default: opened from ``config``, and shut down by
    :meth:`close`). Replies are the standard frames to arbitration id ``host_id``, matched to their
    motor by the id in their first byte; any other frame is counted as foreign (filtered here, not
    by the bus, whose software filters would end a non-blocking read early). ``clock()`` [s] is the
    driver's time, monotonic (default :func:`time.monotonic`). See the module docstring for modes,
    timing and safety."""

    def __init__(self, config: DriverConfig, bus: Optional[can.BusABC] = None, host_id: int = HOST_ID,
                 clock: Callable[[], float] = time.monotonic):
        self.config = c = config
        self.clock = clock
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
        self._position = np.full(n, math.nan)       # each motor's last reported angle [rad]
        self._stamps = np.full(n, math.nan)
        self._temperature: list = [None] * n
        self._error: list = [None] * n
        self._replies = [0] * n
        self._velocity = VelocityScaleCheck([m.model for m in c.motors], [m.limits for m in c.motors])
        self.stale_commands = self.rejected_commands = self.foreign_frames = self.error_frames = 0
        self.unstamped_frames = self.clipped_commands = 0
        self.late_cycles = self.cycles = 0
        self._periods = np.zeros(PERIOD_WINDOW)       # ring buffer of the last periods [s]
        self._closed = False
        self._send_all(EXIT_MOTOR_MODE)

    # -- commands and modes --------------------------------------------------------------------
    def command(self, tensions: Sequence[float], stamp: Optional[float] = None):
        """Set the tensions [N] to apply from the next cycle on. The watchdog counts the command's
        age from now on the driver's clock; ``stamp`` [s], the time the command carries (any clock),
        is only checked: NaN or infinity is refused. Tensions are clipped to [0, max_tension] (a
        command above it counted in ``clipped_commands``: a controller that believes it can pull
        harder winds up against the clip); a wrong length, a non-finite tension or stamp raises
        ValueError, counted in ``rejected_commands``, and leaves the previous command (and its age)
        in place."""
        u = np.asarray(tensions, dtype=float)
        if u.shape != self._target.shape:
            self.rejected_commands += 1
            raise ValueError(f"expected {self._target.size} tensions, got shape {u.shape}")
        if not np.all(np.isfinite(u)):
            self.rejected_commands += 1
            raise ValueError(f"tensions must be finite, got {u.tolist()}")
        if stamp is not None and not math.isfinite(stamp):
            self.rejected_commands += 1
            raise ValueError(f"a command's time stamp must be finite, got {stamp!r}")
        if np.any(u > self.config.max_tension):
            self.clipped_commands += 1
        self._target = np.clip(u, 0.0, self.config.max_tension)
        self._command_time = self.clock()

    def enable(self):
        """Clear a latched fault, enter motor mode on every motor and start from zero tension: the
        watchdog expects a command within ``watchdog_timeout``, every motor a reply within
        ``reply_timeout``, from now."""
        self.mode, self.fault = "enabled", None
        self._target, self._applied = np.zeros_like(self._target), np.zeros_like(self._applied)
        self._command_time = self._watch_from = self.clock()
        self._send_all(ENTER_MOTOR_MODE)

    def disable(self) -> list:
        """Zero torque and exit motor mode on every motor. A latched fault stays latched. Returns the
        frames that did not leave (``motor <id>: <error>``; empty when every one did)."""
        if self.mode == "enabled":
            self.mode = "disabled"
        self._applied = np.zeros_like(self._applied)
        return self._send_zero() + self._send_all(EXIT_MOTOR_MODE)

    def estop(self) -> list:
        """Emergency stop: latch the fault ``e-stop`` (unless one is latched already), zero torque and
        exit motor mode on every motor at once. Returns the frames that did not leave (the latched
        fault names the first reason only, so a caller that reports the stop reports these)."""
        self._trip("e-stop")
        return self._send_zero() + self._send_all(EXIT_MOTOR_MODE)

    def trip(self, reason: str):
        """Latch the fault ``reason`` (unless one is latched already): zero torque from the next
        cycle until :meth:`enable`."""
        self._trip(reason)

    def zero(self) -> list:
        """Set every motor's current angle as its zero: the shortenings read ``zero_shortening`` there
        from then on. Only with the tendons slack: RuntimeError while enabled. Returns the frames
        that did not leave (``motor <id>: <error>``; empty when every one did): those motors keep
        their old zero, the driver is not ``zeroed``, and the fault each latched is cleared by the
        next :meth:`enable`, so the caller must refuse to go on."""
        if self.mode == "enabled":
            raise RuntimeError("zeroing needs slack tendons: disable the motors first")
        unsent = self._send_all(SET_ZERO_POSITION)
        self.zeroed = not unsent
        return unsent

    def close(self) -> list:
        """Zero torque and exit motor mode on every motor; shut the bus down if the driver opened it.
        Idempotent. Returns the frames that did not leave (empty when every one did, or closed
        already)."""
        if self._closed:
            return []
        self._closed = True
        try:
            return self._send_zero() + self._send_all(EXIT_MOTOR_MODE)
        finally:
            if self._owns_bus:
                self.bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def probe(self) -> np.ndarray:
        """Before the cycle starts: read the replies waiting, then poll every motor with zero torque
        (answered in and out of motor mode); which motors answered since the previous probe. No
        silence or watchdog check, no cycle counted: a motor's first answer may take a while
        (configure waits for it), a silence counts once the cycle runs. A reply's error code or
        temperature latches its fault as in the cycle."""
        if self._closed:
            raise RuntimeError("the driver is closed")
        fresh = self._read(self.clock())
        self._send_zero()
        return fresh

    # -- the cycle -----------------------------------------------------------------------------
    def cycle(self, held: Sequence[tuple] = ()) -> Cycle:
        """One period, now on the driver's clock: read the replies, check the safety conditions,
        send a frame to every motor; the state and diagnostics. A clock that runs backwards is not
        monotonic: RuntimeError (the node's cycle thread ends on it, the motors at zero torque).

        ``held``: (seconds, where) of what the caller knows held the cycle since the previous one
        (its publishing of the state, diagnostics and logs; its wait for a lock that another thread
        held), so that a ``cycle held`` fault names each that took half the hold or more: the
        middleware can hold a publish, and with it every thread of the Python process
        (docs/decisions/0005)."""
        if self._closed:
            raise RuntimeError("the driver is closed")
        now = float(self.clock())
        if self._last_cycle is not None and not now >= self._last_cycle:
            raise RuntimeError(f"the driver's clock is not monotonic: {now} after {self._last_cycle}")
        dt = 0.0 if self._last_cycle is None else now - self._last_cycle
        if self._last_cycle is not None:
            self._periods[(self.cycles - 1) % PERIOD_WINDOW] = dt
        if dt > LATE / self.config.rate:
            self.late_cycles += 1
        if self._watch_from is None:
            self._watch_from = now
        fresh = self._read(now)
        # unwatched since the previous cycle or since enable(), whichever came later
        self._check(now, 0.0 if self._last_cycle is None else now - max(self._last_cycle, self._watch_from),
                    held)
        if self.mode == "enabled":
            # the motors take a frame's tension at once: the limit bounds one frame's step, so a late
            # cycle, or the first after enable(), moves by at most LATE periods' worth
            since = now - max(self._last_cycle if self._last_cycle is not None else now, self._watch_from)
            step = self.config.tension_rate_limit * min(since, LATE / self.config.rate)
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
        return Cycle(state, self._diagnostics(now))

    def diagnostics(self) -> Diagnostics:
        """Mode, fault, counters and per-motor status now."""
        return self._diagnostics(self.clock())

    def _diagnostics(self, now: float) -> Diagnostics:
        ratios = self._velocity.ratios()
        motors = tuple(
            MotorDiagnostics(m.can_id, self._temperature[i], self._error[i],
                             None if self._error[i] is None else
                             MOTOR_ERRORS.get(self._error[i], f"unknown error code {self._error[i]}"),
                             now - self._reply_time[i], self._replies[i], ratios[i])
            for i, m in enumerate(self.config.motors))
        age = math.inf if self._command_time is None else now - self._command_time
        return Diagnostics(self.mode, self.fault, age, self.stale_commands, self.rejected_commands,
                           self.foreign_frames, self.error_frames, self.late_cycles, self.cycles,
                           self.zeroed, motors, self.unstamped_frames, self.clipped_commands)

    def cycle_statistics(self) -> CycleStatistics:
        """The timing of the last cycles (not computed per cycle: call it when reporting)."""
        periods = self._periods[:min(max(self.cycles - 1, 0), PERIOD_WINDOW)]
        if periods.size == 0:
            return CycleStatistics(0, math.nan, math.nan, math.nan, math.nan, self.late_cycles)
        ordered = np.sort(periods)
        error = np.sort(np.abs(periods - 1.0 / self.config.rate))
        return CycleStatistics(int(periods.size), percentile(ordered, 50), percentile(ordered, 99),
                               float(ordered[-1]), percentile(error, 99), self.late_cycles)

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
            if not math.isfinite(msg.timestamp):    # a reply needs its receive time: the state's stamp
                self.unstamped_frames += 1
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
            self._check_position(i, reply.position)
            if reply.error:
                self._trip(f"motor {motor.can_id} reports error {reply.error} ({reply.error_text})")
            if reply.temperature is not None and reply.temperature > c.max_temperature:
                self._trip(f"motor {motor.can_id} at {reply.temperature} deg C, above max_temperature "
                           f"{c.max_temperature:g}")
            mismatch = self._velocity.add(i, msg.timestamp, reply.position, reply.velocity)
            if mismatch is not None:
                self._trip(f"motor {motor.can_id}: {mismatch} (rig.motors.models)")
        return fresh

    def _check_position(self, i: int, position: float):
        """A motor's angle [rad] at the end of the reply's field, or one that jumped by more than half
        the field since its last reply, is no measurement: the field saturates there (or wraps, in
        firmware that does not clamp), so a tendon run off its spool, the motor spinning free at its
        torque, reads as a tendon held still. Either latches a fault."""
        lim, can_id = self.config.motors[i].limits, self.config.motors[i].can_id
        span = lim.p_max - lim.p_min
        end = FIELD_END * span / 65535
        if not lim.p_min + end < position < lim.p_max - end:
            self._trip(f"motor {can_id}: angle {position:+.3f} rad at the end of its field [{lim.p_min:g}, "
                       f"{lim.p_max:g}] rad: the reading saturates there, the shortening is no measurement")
        elif abs(position - self._position[i]) > 0.5 * span:
            self._trip(f"motor {can_id}: angle jumped from {self._position[i]:+.3f} to {position:+.3f} rad "
                       "between two replies: it wrapped at the end of its field")
        self._position[i] = position

    def _check(self, now: float, gap: float, held: Sequence[tuple]):
        """Reply timeouts (every mode), the command watchdog and the watchdog's own deadline
        (enabled): ``gap`` [s] since the previous cycle (or since enable(), if later) longer than
        ``watchdog_timeout`` means nothing watched the enabled motors that long (the cycle held:
        its process stopped, swapped out or stuck in the middleware, or the hardware lock held),
        whatever the command's age reads now; the motors' firmware timeout may have zeroed them
        meanwhile. The fault names each of ``held`` (seconds, where) that took half the gap or
        more."""
        c = self.config
        if self.mode == "enabled" and gap > c.watchdog_timeout:
            where = "".join(f"; {seconds:.4f} s of it {place}" for seconds, place in held
                            if seconds >= 0.5 * gap)
            self._trip(f"cycle held: {gap:.4f} s since the previous cycle, the motors unwatched "
                       f"(watchdog_timeout {c.watchdog_timeout:g} s){where}")
        silence = now - np.maximum(self._reply_time, self._watch_from)
        for i in np.flatnonzero(silence > c.reply_timeout):
            refused = (f"; {self.unstamped_frames} replies refused so far for a receive time that is no "
                       "number" if self.unstamped_frames else "")
            self._trip(f"motor {c.motors[i].can_id} silent for {silence[i]:.4f} s "
                       f"(reply_timeout {c.reply_timeout:g} s){refused}")
        if self.mode == "enabled" and now - self._command_time > c.watchdog_timeout:
            self.stale_commands += 1
            self._trip(f"stale command: the latest is {now - self._command_time:.4f} s old "
                       f"(watchdog_timeout {c.watchdog_timeout:g} s)")

    def _trip(self, reason: str):
        """Latch a fault (the first reason is kept until enable()); the cycle sends zero torque."""
        if self.mode != "fault":
            self.mode, self.fault = "fault", reason
        self._applied = np.zeros_like(self._applied)

    def _send(self, can_id: int, data: bytes) -> list:
        """Send one frame; a failure latches a fault and is returned (``motor <id>: <error>``)."""
        try:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False),
                          timeout=SEND_TIMEOUT)
        except can.CanError as exc:
            self._trip(f"CAN send to motor {can_id} failed: {exc}")
            return [f"motor {can_id}: {exc}"]
        return []

    def _send_all(self, data: bytes) -> list:
        return [f for motor in self.config.motors for f in self._send(motor.can_id, data)]

    def _send_zero(self) -> list:
        return [f for motor, frame in zip(self.config.motors, self._zero_frames)
                for f in self._send(motor.can_id, frame)]
