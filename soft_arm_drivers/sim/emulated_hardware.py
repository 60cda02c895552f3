"""The emulated hardware of the rig: the CAN motors with the simulated arm behind them and the Motive
(NatNet) server streaming the same arm, in the driver's process or in processes of their own.

:func:`start_hardware` starts both on a given bus (threads of the calling process); the
:class:`HardwareProcess` runs them in a child process on the project's cross-process CAN bus
(:mod:`soft_arm_drivers.can.loopback_bus`), as on the rig, where the arm is not in the driver's
process and the driver's cycle does not compete for its interpreter lock with the plant it drives;
there the Motive server is a process of the child's own (:class:`~.emulated_motive.MotiveProcess`),
as Motive runs on a computer of its own, reading the arm from a shared history of its
configurations. The child ends when the parent closes it or dies (it watches a pipe to the
parent), and the Motive server with it.
"""
from __future__ import annotations

import contextlib
import gc
import multiprocessing
import sys
import time
from dataclasses import dataclass

import can
import numpy as np

from soft_arm_drivers.can.driver_config import DriverConfig
from soft_arm_drivers.can.loopback_bus import LoopbackBus, parse_channel
from soft_arm_model import ArmConfig
from soft_arm_model.parameters import ConfigError

from .can_emulator import HISTORY, CanMotorEmulator, EmulatorThread
from .configuration_history import ConfigurationHistory
from .emulated_motive import MotiveProcess, start_motive
from .plant_config import PlantConfig
from .simulated_rig import Plant


@dataclass(frozen=True)
class HardwareSpec:
    """What the emulated hardware is: the driver's motors and bus (``driver``), the arm and the
    plant simulated as the real one, ``emulator`` (``rig.emulator`` values) and ``mocap`` (the
    bridge's configuration: where the Motive server is, what it streams)."""
    driver: DriverConfig
    arm: ArmConfig
    plant: PlantConfig
    emulator: dict
    mocap: object


class Hardware:
    """The running emulators: the motors' thread and the Motive server (a NatNet server thread or a
    :class:`~.emulated_motive.MotiveProcess`); :meth:`close` stops both (and raises what stopped the
    motors' thread, if anything did)."""

    def __init__(self, motors: EmulatorThread, motive):
        self.motors, self.motive = motors, motive

    @property
    def error(self):
        """What stopped the motors' thread or the Motive server's process (None while both run)."""
        return self.motors.error or getattr(self.motive, "error", None)

    def close(self):
        try:
            self.motors.stop()
        finally:
            self.motive.close()


def start_hardware(spec: HardwareSpec, bus: can.BusABC, motive_process: bool = False) -> Hardware:
    """The motor emulator on ``bus`` (motors out of motor mode with arbitrary zeros, the arm hanging
    with slack tendons) and the NatNet server emulator of the same plant: a thread of this process,
    or with ``motive_process`` a process of its own reading a shared history of the plant.
    ConfigError when the Motive server's address cannot be bound."""
    c, emulator, p = spec.driver, spec.emulator, spec.plant
    plant = Plant.of(spec.arm, p)
    plant.settle(np.zeros(plant.model.n_tendons))
    _compile_kernels(plant)
    history = ConfigurationHistory.shared(plant.model.n, HISTORY, p.timestep) if motive_process else None
    try:
        motors = CanMotorEmulator.for_config(
            c, bus, plant, firmware=emulator["firmware"], reply_delay=emulator["reply_delay"],
            command_timeout=emulator["command_timeout"], on_timeout=_say_timeout,
            encoder_resolution=p.encoder_resolution,
            zero_spread=emulator["zero_spread"], seed=emulator["seed"], start_time=time.time(),
            history=history)
        thread = EmulatorThread(motors).start()
        try:
            motive = MotiveProcess(spec, history) if motive_process else \
                start_motive(spec, plant.model, motors.history)
        except BaseException:
            # the set-up's error is the one raised; the thread's (failed, or not ending) comes second
            with contextlib.suppress(Exception):
                thread.stop()
            raise
    finally:
        if history is not None:
            history.unlink()                # mapped by both processes now, or by none
    return Hardware(thread, motive)


def _say_timeout(can_id: int, silence: float):
    """What a motor's CAN timeout did, on this process's standard error."""
    print(f"emulated motors: motor {can_id} heard no frame for {silence:.4f} s: command zeroed "
          f"(firmware CAN timeout), no torque until the next command", file=sys.stderr, flush=True)


def _compile_kernels(plant: Plant):
    """Run every kernel the motors' thread calls once, the plant's state kept: on a cold numba
    cache (a fresh install) they compile here, before the hardware reports ready, not in the first
    cycles after the driver enables the motors, where a stalled reply trips its watchdog."""
    q, qd = plant.q.copy(), plant.qd.copy()
    plant.sense(markers=True)
    plant.step(np.zeros(plant.model.n_tendons))
    plant.q, plant.qd = q, qd


def peer_channel(channel: str) -> str:
    """The other end's channel of a ``soft_arm_loopback`` channel ``"LOCAL:PEER"``."""
    local, peer = parse_channel(channel)
    return f"{peer}:{local}"


def _serve(spec: HardwareSpec, conn):
    """The child: the hardware on the bus's other end (the Motive server in a process of its own)
    until the parent closes the pipe or dies, or the motors' thread or the Motive server stops.
    Reports ``("ready", natnet command port, objects frozen out of the garbage collector)`` or
    ``("error", message)`` on the pipe.

    What the set-up allocated (the model, compiled kernels, scipy: some 1.5e5 objects) is collected
    once and frozen out of the garbage collector, as every node's process does
    (:func:`soft_arm_ros.runtime.run_node`): a full collection walking them holds the interpreter
    lock, and with it the motors' thread, for 50-300 ms, past the driver's reply timeout: the
    motors fall silent and the driver faults
    (docs/decisions/0001-nodes-spin-the-events-executor-and-freeze-their-set-up.md)."""
    bus = hardware = None
    try:
        bus = LoopbackBus(peer_channel(spec.driver.channel), preserve_timestamps=True)
        hardware = start_hardware(spec, bus, motive_process=True)
        gc.collect()
        gc.freeze()
        conn.send(("ready", hardware.motive.command_port, gc.get_freeze_count()))
        while hardware.error is None:
            if conn.poll(0.2):               # the parent said stop, or its end closed (it died)
                try:
                    conn.recv()
                except EOFError:
                    pass
                break
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        try:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        except OSError:
            pass
    finally:
        try:
            if hardware is not None:
                hardware.close()
        finally:
            if bus is not None:
                bus.shutdown()


class HardwareProcess:
    """The emulated hardware of ``spec`` in a child process on the ``soft_arm_loopback`` bus whose
    driver end is ``spec.driver.channel``. ``start()`` returns once the hardware is up (ConfigError
    with the child's reason otherwise, or after ``timeout`` [s]); then ``command_port`` is its
    Motive server's and ``frozen_objects`` how many objects of its set-up the child froze out of
    the garbage collector."""

    def __init__(self, spec: HardwareSpec, timeout: float = 60.0):
        self.spec, self.timeout = spec, float(timeout)
        self._conn = self._process = None
        self._error = None
        self.command_port = self.frozen_objects = None

    def start(self) -> "HardwareProcess":
        ctx = multiprocessing.get_context("spawn")        # no copy of the parent's rclpy state
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve, args=(self.spec, child), name="emulated-hardware",
                                    daemon=True)
        self._process.start()
        child.close()
        if not self._conn.poll(self.timeout):
            self.stop()
            raise ConfigError(f"the emulated hardware did not start within {self.timeout:g} s")
        kind, *values = self._conn.recv()
        if kind != "ready":
            self.stop()
            raise ConfigError(f"the emulated hardware did not start: {values[0]}")
        self.command_port, self.frozen_objects = values
        return self

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def error(self) -> str | None:
        """Why the child stopped, if it did on its own (None while it runs)."""
        if self._process is None or self._process.is_alive():
            return None
        if self._error is None:
            self._error = f"the emulated hardware's process ended (exit code {self._process.exitcode})"
            if self._conn is not None and self._conn.poll():
                try:
                    self._error = self._conn.recv()[1]
                except EOFError:
                    pass
        return self._error

    def stop(self):
        """Ask the child to close its emulators, wait for it (then terminate it); idempotent."""
        conn, process = self._conn, self._process
        self._conn = None
        if conn is not None:
            try:
                conn.send("stop")
            except (OSError, BrokenPipeError):
                pass
        if process is not None:
            process.join(5.0)
            if process.is_alive():
                process.terminate()
                process.join(5.0)
        if conn is not None:
            conn.close()
