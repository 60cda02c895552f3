"""CAN motor emulator: MIT-protocol motors on a python-can bus, with the tendon plant behind them.

Each emulated motor answers every frame addressed to its CAN id (enter/exit motor mode, set zero, a
command) with a reply to ``host_id`` after ``reply_delay``: position (16 bit), velocity (12 bit),
torque (12 bit) and, with ``extended_replies``, temperature and error code. In motor mode it applies
the MIT law ``tau = kp (p_des - p) + kd (v_des - v) + t_ff`` clipped to its torque range; in rest
mode no torque; entering or leaving motor mode clears the command.

Behind the motors, the tendons: a :class:`~.simulated_rig.Plant` (the Variable-Strain arm with
the rotors' reflected inertia) under the tensions ``max(0, direction * tau / pulley_radius)`` (a
tendon cannot push). The raw motor angle is ``direction * shortening / pulley_radius`` [rad], the
shortening counted from the straight arm; each motor reads it relative to its stored zero, which
starts somewhere in ``+-zero_spread`` rad (seeded) and is moved by set-zero. Without a plant the
tendons stay where :meth:`CanMotorEmulator.set_tendons` puts them.

Time is explicit: :meth:`~CanMotorEmulator.advance_to` takes the frames waiting on the bus as
arriving at the emulator's current time, then runs the clock to ``t_end``: replies go out when due
(stamped with their due time and the latest plant state), the plant steps every ``timestep``.
Given a seed and the same calls, the replies are identical. Give the emulator a bus that preserves
time stamps (``can.Bus(interface="virtual", channel=..., preserve_timestamps=True)``) so that its
replies carry its clock. :class:`EmulatorThread` serves it in real time instead.

The firmware's CAN timeout (``command_timeout``): a motor in motor mode that receives no frame for
that long zeroes its command (stiffness, damping and torque), as the MIT firmware does, and applies
no torque until the next command frame. It is the motors' own safety, apart from the driver's
watchdog: it holds when the driver's process stops sending altogether (stopped, hung, killed), where
the watchdog, a part of that process, cannot act.

Fault injection (:meth:`~CanMotorEmulator.inject`): a motor stops replying (it still obeys), reports
an error code, or reports a temperature.
"""
from __future__ import annotations

import os
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Callable, Optional, Sequence

import can
import numpy as np

from soft_arm_drivers.can.driver_config import DriverConfig, Motor
from soft_arm_drivers.can.mit_protocol import (COMMAND_LENGTH, ENTER_MOTOR_MODE, EXIT_MOTOR_MODE,
                                               SET_ZERO_POSITION, MotorCommand, decode_command, encode_reply)
from soft_arm_drivers.can.motor_driver import HOST_ID
from soft_arm_model import load_arm_config

from .configuration_history import ConfigurationHistory
from .plant_config import load_plant_config
from .simulated_rig import Plant

__all__ = ["CanMotorEmulator", "EmulatedMotor", "EmulatorThread", "arm_plant"]

_EPS = 1e-9                     # s, tolerance of time comparisons
HISTORY = 500                   # plant steps kept in the history (0.5 s at 1 ms)
_NO_COMMAND = MotorCommand(0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass
class EmulatedMotor:
    """State of one emulated motor: motor mode, stored zero (raw angle [rad] that reads 0), latest
    command, temperature [deg C] and error code it reports, whether it replies, frames received,
    set-zero frames obeyed, the arrival of its latest frame [s, the emulator's clock] and the times
    its CAN timeout zeroed its command."""
    motor: Motor
    zero: float
    temperature: int
    motor_mode: bool = False
    command: MotorCommand = _NO_COMMAND
    error: int = 0
    silent: bool = False
    frames: int = 0
    zero_count: int = 0
    last_frame: float = -float("inf")
    timeouts: int = 0


class CanMotorEmulator:
    """The ``motors`` (tendon order) on ``bus`` with pulley radius ``pulley_radius`` [m].

    ``plant``: a :class:`~.simulated_rig.Plant` (None: static tendons). ``timestep`` [s]: the clock's
    step (default: the plant's, else 1 ms). ``reply_delay`` [s] from a frame to its reply;
    ``encoder_resolution`` [rad] quantises the angle before the protocol's 16 bits (0: off);
    ``encoder_noise`` [rad] standard deviation added to each reading (seeded); ``temperature`` [deg C]
    reported while none is injected; ``zero_spread`` [rad]: the stored zeros are uniform in
    ``+-zero_spread`` (seeded); ``start_time`` [s]: the clock's start (a real-time server: now).
    ``command_timeout`` [s]: the firmware's CAN timeout (0: none); ``on_timeout(can_id, silence)``
    is called, from the emulator's thread, each time it zeroes a motor's command, with the time
    [s] since that motor's latest frame.
    """

    def __init__(self, bus: can.BusABC, motors: Sequence[Motor], pulley_radius: float,
                 plant: Optional[Plant] = None, *,
                 timestep: Optional[float] = None, reply_delay: float = 0.0,
                 encoder_resolution: float = 0.0, encoder_noise: float = 0.0,
                 extended_replies: bool = True, temperature: int = 30, zero_spread: float = 1.0,
                 seed: int = 0, start_time: float = 0.0, host_id: int = HOST_ID,
                 history: Optional[ConfigurationHistory] = None, command_timeout: float = 0.0,
                 on_timeout: Optional[Callable[[int, float], None]] = None):
        if plant is not None and timestep is not None and abs(timestep - plant.stepper.dt) > _EPS:
            raise ValueError(f"timestep {timestep} s differs from the plant's {plant.stepper.dt} s")
        dt = plant.stepper.dt if plant is not None else (1e-3 if timestep is None else timestep)
        for name, value in (("pulley_radius", pulley_radius), ("timestep", dt)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        for name, value in (("reply_delay", reply_delay), ("encoder_resolution", encoder_resolution),
                            ("encoder_noise", encoder_noise), ("zero_spread", zero_spread),
                            ("command_timeout", command_timeout)):
            if not value >= 0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        self.bus, self.plant, self.r, self.dt = bus, plant, float(pulley_radius), float(dt)
        self.reply_delay, self.resolution, self.noise = reply_delay, encoder_resolution, encoder_noise
        self.extended_replies, self.host_id = extended_replies, host_id
        self.command_timeout, self.on_timeout = float(command_timeout), on_timeout
        self.rng = np.random.default_rng(seed)
        zeros = self.rng.uniform(-zero_spread, zero_spread, len(motors))
        self.motors = [EmulatedMotor(m, float(z), temperature) for m, z in zip(motors, zeros)]
        self._by_id = {m.can_id: i for i, m in enumerate(motors)}
        self._direction = np.array([m.direction for m in motors], dtype=float)
        self._base, self._k, self._now = float(start_time), 0, float(start_time)
        self._replies: deque = deque()              # (due time [s], motor index), due times ascending
        self._last_arrival = float(start_time)
        n = None if plant is None else len(plant.q)
        if history is not None and (history.n != n or abs(history.dt - dt) > _EPS):
            raise ValueError(f"the history holds {history.n} coordinates every {history.dt} s, the "
                             f"plant has {n} every {dt} s")
        self.history = None if plant is None else history or ConfigurationHistory(n, HISTORY, dt)
        self.tensions = np.zeros(len(motors))       # applied to the plant in the latest step [N]
        self.replies_sent = 0
        if plant is not None:
            plant.sense()
            self._s, self._sd = plant.tendons()
            self.history.append(self._now, plant.q)
        else:
            self._s, self._sd = np.zeros(len(motors)), np.zeros(len(motors))

    @classmethod
    def for_config(cls, config: DriverConfig, bus: can.BusABC, plant: Optional[Plant] = None,
                   firmware: str = "", **options) -> "CanMotorEmulator":
        """The motors and pulley radius of a driver configuration (``options``: see the class).
        ``firmware``: the ``MOTOR_PRESETS`` scales the emulated motors are flashed with, their torque
        ranges kept ("": those of ``rig.motors.models``, the presets the driver reads them with);
        another firmware of the same model emulates a wrong preset in ``rig.yaml``."""
        motors = config.motors if not firmware else tuple(replace(m, model=firmware) for m in config.motors)
        return cls(bus, motors, config.pulley_radius, plant, **options)

    # -- inspection and fault injection ----------------------------------------------------------
    @property
    def t(self) -> float:
        """The emulator's clock [s]."""
        return self._now

    def motor(self, can_id: int) -> EmulatedMotor:
        return self.motors[self._by_id[can_id]]

    def tendons(self) -> tuple[np.ndarray, np.ndarray]:
        """True shortenings [m] (from the straight arm) and rates [m/s] at the current plant state."""
        return self._s.copy(), self._sd.copy()

    def set_tendons(self, shortening, rate=None):
        """Without a plant: put the tendons at ``shortening`` [m] moving at ``rate`` [m/s]."""
        if self.plant is not None:
            raise RuntimeError("the tendons follow the plant; set_tendons is for an emulator without one")
        self._s = np.array(shortening, dtype=float).reshape(len(self.motors))
        self._sd = np.zeros(len(self.motors)) if rate is None else \
            np.array(rate, dtype=float).reshape(len(self.motors))

    def inject(self, can_id: int, *, silent: Optional[bool] = None, error: Optional[int] = None,
               temperature: Optional[int] = None):
        """Fault injection on one motor: stop (or resume) replying, report an error code (0: none) or a
        temperature [deg C]; arguments left None are unchanged."""
        m = self.motor(can_id)
        if silent is not None:
            m.silent = silent
        if error is not None:
            m.error = error
        if temperature is not None:
            m.temperature = temperature

    def angle(self, i: int) -> float:
        """Motor ``i``'s true angle from its stored zero [rad]."""
        return self._direction[i] * self._s[i] / self.r - self.motors[i].zero

    def torque(self, i: int) -> float:
        """The torque motor ``i`` applies now [N m] (MIT law in motor mode, 0 in rest mode)."""
        m = self.motors[i]
        if not m.motor_mode:
            return 0.0
        c, lim = m.command, m.motor.limits
        velocity = self._direction[i] * self._sd[i] / self.r
        tau = c.kp * (c.position - self.angle(i)) + c.kd * (c.velocity - velocity) + c.torque
        return min(max(tau, lim.t_min), lim.t_max)

    # -- time ------------------------------------------------------------------------------------
    def advance_to(self, t_end: float):
        """Take the frames waiting on the bus as arriving now, then run the clock to ``t_end`` [s]."""
        if t_end < self._now - _EPS:
            raise ValueError(f"t_end {t_end} is before the emulator's time {self._now}")
        self._drain(self._now)
        self._run(t_end)

    def next_event(self) -> float:
        """Time [s] of the next plant step or due reply."""
        step = self._base + (self._k + 1) * self.dt
        return min(step, self._replies[0][0]) if self._replies else step

    def serve(self, clock: Callable[[], float], stop: threading.Event, max_wait: float = 0.01):
        """Real-time loop until ``stop`` is set: frames are taken as they arrive (at their bus time
        stamps), the plant and the replies follow ``clock`` (which must match ``start_time`` and the
        bus's stamps)."""
        while not stop.is_set():
            wait = min(self.next_event() - clock(), max_wait)
            msg = self.bus.recv(timeout=max(wait, 0.0))
            frames = []
            while msg is not None:
                frames.append((msg, self._arrival(msg, clock())))
                msg = self.bus.recv(timeout=0.0)
            for msg, arrival in frames:          # each frame acts from its arrival on
                self._run(max(arrival, self._now))
                self._handle(msg, arrival)
            self._run(max(clock(), self._now))

    def _arrival(self, msg: can.Message, now: float) -> float:
        """Real time: when a frame reached the bus, from its time stamp (frames read together after
        this thread was held keep their own times), else ``now`` [s]; never before the previous
        frame's."""
        t = msg.timestamp if now - 1.0 < msg.timestamp <= now else now
        self._last_arrival = max(t, self._last_arrival)
        return self._last_arrival

    def _run(self, t_end: float):
        while True:
            t_next = self._base + (self._k + 1) * self.dt
            self._send_due(min(t_next, t_end))
            if t_next > t_end + _EPS:
                break
            self._step()
        self._now = max(self._now, t_end)

    def _step(self):
        if self.command_timeout:
            self._time_out(self._base + self._k * self.dt)
        tau = np.array([self.torque(i) for i in range(len(self.motors))])
        self.tensions = np.maximum(0.0, self._direction * tau / self.r)
        if self.plant is not None:
            self.plant.step(self.tensions)
            self.plant.sense()
            self._s, self._sd = self.plant.tendons()
        self._k += 1
        if self.plant is not None:
            self.history.append(self._base + self._k * self.dt, self.plant.q)

    def _time_out(self, now: float):
        """The firmware's CAN timeout at ``now`` [s]: zero the command of every motor in motor mode
        whose latest frame is older than ``command_timeout``."""
        for m in self.motors:
            silence = now - m.last_frame
            if m.motor_mode and m.command != _NO_COMMAND and silence > self.command_timeout:
                m.command = _NO_COMMAND
                m.timeouts += 1
                if self.on_timeout is not None:
                    self.on_timeout(m.motor.can_id, silence)

    # -- frames ----------------------------------------------------------------------------------
    def _drain(self, arrival: float):
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            self._handle(msg, arrival)

    def _handle(self, msg: can.Message, arrival: float):
        i = self._by_id.get(msg.arbitration_id)
        if i is None or msg.is_error_frame or msg.is_remote_frame:
            return
        m, data = self.motors[i], bytes(msg.data)
        m.frames += 1
        m.last_frame = max(m.last_frame, arrival)
        if data == ENTER_MOTOR_MODE or data == EXIT_MOTOR_MODE:
            m.motor_mode, m.command = data == ENTER_MOTOR_MODE, _NO_COMMAND
        elif data == SET_ZERO_POSITION:
            m.zero += self.angle(i)
            m.zero_count += 1
        elif len(data) == COMMAND_LENGTH:
            m.command = decode_command(m.motor.limits, data)
        else:
            return                                       # malformed: the firmware drops it
        self._replies.append((arrival + self.reply_delay, i))

    def _send_due(self, horizon: float):
        while self._replies and self._replies[0][0] <= horizon + _EPS:
            due, i = self._replies.popleft()
            m = self.motors[i]
            if m.silent:
                continue
            angle = self.angle(i) + (self.rng.normal(0.0, self.noise) if self.noise else 0.0)
            if self.resolution:
                angle = round(angle / self.resolution) * self.resolution
            velocity = self._direction[i] * self._sd[i] / self.r
            extra = (min(max(int(m.temperature), 0), 255), m.error) if self.extended_replies else (None, None)
            data = encode_reply(m.motor.limits, m.motor.can_id, angle, velocity, self.torque(i), *extra)
            self.bus.send(can.Message(arbitration_id=self.host_id, data=data, is_extended_id=False,
                                      timestamp=due))
            self.replies_sent += 1


class EmulatorThread:
    """Serve an emulator in real time on a daemon thread: ``with EmulatorThread(emulator): ...``.
    ``clock`` [s] must be the one the emulator's ``start_time`` was taken from (default
    ``time.time``, the clock of ROS system time and of socketcan's time stamps). An exception in the
    thread stops it and is raised again by :meth:`stop`."""

    def __init__(self, emulator: CanMotorEmulator, clock: Callable[[], float] = time.time):
        self.emulator, self.clock = emulator, clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="can-emulator", daemon=True)
        self.error: Optional[BaseException] = None

    def _serve(self):
        try:
            self.emulator.serve(self.clock, self._stop)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller by stop()
            self.error = exc

    def start(self) -> "EmulatorThread":
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0):
        """Ask the thread to end and wait for it, at most ``timeout`` [s] (RuntimeError naming the
        emulator's thread if it has not ended: a step of its plant that does not return); raise what
        it ended on, if anything."""
        self._stop.set()
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise RuntimeError(f"the CAN motor emulator's thread did not end within {timeout:g} s")
        if self.error is not None:
            raise self.error

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def arm_plant(config_dir: Optional[str] = None, tension: float = 0.0):
    """The simulated plant of the package's ``plant.yaml`` over ``arm.yaml`` (plant model error and
    rotor inertia included), at rest under ``tension`` [N] on every tendon."""
    arm = load_arm_config(os.path.join(config_dir, "arm.yaml") if config_dir else None)
    pc = load_plant_config(arm, os.path.join(config_dir, "plant.yaml") if config_dir else None)
    plant = Plant.of(arm, pc)
    plant.settle(np.full(plant.model.n_tendons, float(tension)))
    return plant
