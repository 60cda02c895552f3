"""The emulated hardware of the rig: the CAN motors with the simulated arm behind them and the Motive
(NatNet) server streaming the same arm, in the driver's process or in a process of its own.

:func:`start_hardware` starts both on a given bus (threads of the calling process); the
:class:`HardwareProcess` runs them in a child process on the project's cross-process CAN bus
(:mod:`soft_arm_drivers.can.loopback_bus`), as on the rig, where the arm is not in the driver's
process and the driver's cycle does not compete for its interpreter lock with the plant it drives.
The child ends when the parent closes it or dies (it watches a pipe to the parent).
"""
from __future__ import annotations

import gc
import multiprocessing
import time
from dataclasses import dataclass

import can
import numpy as np

from soft_arm_drivers.can.driver_config import DriverConfig
from soft_arm_drivers.can.loopback_bus import LoopbackBus, parse_channel
from soft_arm_model import ArmConfig, ArmData, marker_positions
from soft_arm_model.parameters import ConfigError

from .can_emulator import CanMotorEmulator, EmulatorThread
from .natnet_emulator import NatNetEmulator
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
    """The running emulators: the motors' thread and the NatNet server; :meth:`close` stops both
    (and raises what stopped the motors' thread, if anything did)."""

    def __init__(self, motors: EmulatorThread, natnet: NatNetEmulator):
        self.motors, self.natnet = motors, natnet

    @property
    def error(self):
        return self.motors.error

    def close(self):
        try:
            self.motors.stop()
        finally:
            self.natnet.close()


def start_hardware(spec: HardwareSpec, bus: can.BusABC) -> Hardware:
    """The motor emulator on ``bus`` (motors out of motor mode with arbitrary zeros, the arm hanging
    with slack tendons) and the NatNet server emulator of the same plant. ConfigError when the
    Motive server's address cannot be bound."""
    c, emulator, mocap, p = spec.driver, spec.emulator, spec.mocap, spec.plant
    plant = Plant.of(spec.arm, p)
    plant.settle(np.zeros(plant.model.n_tendons))
    data = ArmData(plant.model)
    _compile_kernels(plant, data)
    motors = CanMotorEmulator.for_config(
        c, bus, plant, reply_delay=emulator["reply_delay"], encoder_resolution=p.encoder_resolution,
        zero_spread=emulator["zero_spread"], seed=emulator["seed"], start_time=time.time())
    thread = EmulatorThread(motors).start()
    rng = np.random.default_rng(p.mocap_seed)

    def markers(t: float) -> np.ndarray:
        """On the NatNet thread: the plant at the exposure time ``t`` [s, system time]."""
        true = marker_positions(plant.model, motors.configuration_at(t), data)
        return p.as_mocap_reports(true) + rng.normal(0.0, p.mocap_noise, true.shape)

    ids = {"rigid_body_ids" if mocap.source == "rigid_bodies" else "labeled_marker_ids": mocap.ids}
    try:
        natnet = NatNetEmulator(
            markers, version=emulator["natnet_version"], rate=p.mocap_rate, layout="both",
            calibration=mocap.calibration, address=mocap.server_address,
            command_port=mocap.command_port, latency=p.mocap_latency, **ids).start()
    except OSError as exc:
        thread.stop()
        raise ConfigError(f"rig.mocap.command_port = {mocap.command_port}: the emulated Motive "
                          f"server cannot bind {mocap.server_address}:{mocap.command_port}: "
                          f"{exc.strerror}") from None
    return Hardware(thread, natnet)


def _compile_kernels(plant: Plant, data: ArmData):
    """Run every kernel the motors' and the NatNet threads call once, the plant's state kept: on a
    cold numba cache (a fresh install) they compile here, before the hardware reports ready, not
    in the first cycles after the driver enables the motors, where a stalled reply trips its
    watchdog."""
    q, qd = plant.q.copy(), plant.qd.copy()
    plant.sense(markers=True)
    plant.step(np.zeros(plant.model.n_tendons))
    plant.q, plant.qd = q, qd
    marker_positions(plant.model, q, data)


def peer_channel(channel: str) -> str:
    """The other end's channel of a ``soft_arm_loopback`` channel ``"LOCAL:PEER"``."""
    local, peer = parse_channel(channel)
    return f"{peer}:{local}"


def _serve(spec: HardwareSpec, conn):
    """The child: the hardware on the bus's other end until the parent closes the pipe or dies.
    Reports ``("ready", natnet command port, objects frozen out of the garbage collector)`` or
    ``("error", message)`` on the pipe.

    What the set-up allocated (the model, compiled kernels, scipy: some 1.5e5 objects) is collected
    once and frozen out of the garbage collector, as every node's process does
    (:func:`soft_arm_ros.runtime.run_node`): a full collection walking them holds the interpreter
    lock, and with it the motors' and the NatNet threads, for 50-300 ms (measured, *ad hoc*), past
    the driver's reply timeout: the motors fall silent and the driver faults."""
    bus = hardware = None
    try:
        bus = LoopbackBus(peer_channel(spec.driver.channel), preserve_timestamps=True)
        hardware = start_hardware(spec, bus)
        gc.collect()
        gc.freeze()
        conn.send(("ready", hardware.natnet.command_port, gc.get_freeze_count()))
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
