"""The emulated Motive (NatNet) server of the emulated hardware: the cameras see the simulated arm
at their exposure times, on a thread (:func:`start_motive`) or in a process of its own
(:class:`MotiveProcess`).

On the rig Motive runs on a computer of its own. So does the emulated one when the hardware runs in
a process of its own: :class:`MotiveProcess` starts ``python -m soft_arm_drivers.sim.emulated_motive``,
which reads the arm's configurations from the motors' shared
:class:`~.configuration_history.ConfigurationHistory`. It runs under the normal scheduling policy
whatever its parent's (the cameras' frames are stamped with their exposure times, so a frame sent
late is still right), and so takes nothing from the real-time budget of the CPU that steps the
plant (:mod:`soft_arm_experiments.realtime`). That plant runs below the nodes on its CPU and falls
behind real time now and then (by up to 27 ms under a busy two-core machine's load), so each frame
waits until the plant has stepped to its exposure (``NatNetEmulator``'s ``reached``). It ends when
its standard input closes: when the hardware's process closes it or dies.
"""
from __future__ import annotations

import gc
import os
import pickle
import select
import signal
import subprocess
import sys
import time

import numpy as np

from soft_arm_model import ArmData, marker_positions
from soft_arm_model.parameters import ConfigError

from .configuration_history import ConfigurationHistory
from .natnet_emulator import NatNetEmulator
from .occlusion import Occlusions
from .simulated_rig import Plant

_READY, _ERROR = "ready", "error"


def start_motive(spec, model, history: ConfigurationHistory) -> NatNetEmulator:
    """The NatNet server emulator of ``spec`` (a :class:`~.emulated_hardware.HardwareSpec`) streaming
    the markers of the plant ``model`` at the configurations of its ``history`` at the exposure
    times [s, system time], as the miscalibrated mocap reports them, with the plant's noise
    (seeded); each frame once the history has reached its exposure. ConfigError when the Motive
    server's address cannot be bound."""
    p, mocap, emulator = spec.plant, spec.mocap, spec.emulator
    data = ArmData(model)
    marker_positions(model, history.at(time.time()), data)    # compiled before the stream
    rng = np.random.default_rng(p.mocap_seed)
    occlusions = Occlusions.for_plant(p, model.marker_X.size)
    started = time.time()

    def markers(t: float) -> np.ndarray:
        """On the NatNet thread: the plant at the exposure time ``t`` [s, system time]; the markers
        the cameras do not see are NaN (the emulator flags them occluded, as Motive does). The
        occlusion's blackout counts from the server's start."""
        true = marker_positions(model, history.at(t), data)
        out = p.as_mocap_reports(true) + rng.normal(0.0, p.mocap_noise, true.shape)
        if occlusions is not None:
            out[~occlusions.of_arm(model, data, t - started)] = np.nan
        return out

    ids = {"rigid_body_ids" if mocap.source == "rigid_bodies" else "labeled_marker_ids": mocap.ids}
    try:
        return NatNetEmulator(
            markers, version=emulator["natnet_version"], rate=p.mocap_rate, layout="both",
            calibration=mocap.calibration, address=mocap.server_address,
            command_port=mocap.command_port, latency=p.mocap_latency, reached=history.reached,
            **ids).start()
    except OSError as exc:
        raise ConfigError(f"rig.mocap.command_port = {mocap.command_port}: the emulated Motive "
                          f"server cannot bind {mocap.server_address}:{mocap.command_port}: "
                          f"{exc.strerror}") from None


class MotiveProcess:
    """The emulated Motive server of ``spec`` in a process of its own, reading the arm from the
    shared ``history``. Returns once the server streams (then :attr:`command_port` is its port);
    ConfigError with the process's reason otherwise, or after ``timeout`` [s]."""

    def __init__(self, spec, history: ConfigurationHistory, timeout: float = 60.0):
        # unbuffered: a line read must not pull the next into a buffer that select() cannot see
        self._process = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, bufsize=0)
        try:
            pickle.dump((spec, history.path, history.n, history.rows, history.dt), self._process.stdin)
            self._process.stdin.flush()
            self.command_port = int(self._answer(timeout))
        except BaseException:
            self.close()
            raise

    def _answer(self, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        out = self._process.stdout
        while True:
            ready, _, _ = select.select([out], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                raise ConfigError(f"the emulated Motive server did not start within {timeout:g} s")
            line = out.readline().decode(errors="replace").strip()
            if not line:
                raise ConfigError("the emulated Motive server's process ended before it started "
                                  f"(exit code {self._process.wait()})")
            kind, _, value = line.partition(" ")
            if kind == _READY:
                return value
            if kind == _ERROR:
                raise ConfigError(value)

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def error(self) -> str | None:
        """Why the process ended, if it did (None while it runs)."""
        code = self._process.poll()
        return None if code is None else f"the emulated Motive server's process ended (exit code {code})"

    def close(self):
        """Close its standard input (it ends), wait for it (then kill it); idempotent."""
        try:
            self._process.stdin.close()
        except OSError:
            pass
        try:
            self._process.wait(5.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._process.stdout.close()


def _normal_policy():
    """Every thread of this process (the imports' too: a BLAS pool) under the normal scheduling
    policy: it was started by a process that may be under SCHED_FIFO, which threads inherit."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setscheduler(int(tid), os.SCHED_OTHER, os.sched_param(0))
        except (AttributeError, OSError):
            pass


def main() -> int:
    """The process: the spec and the history's file on standard input (pickled), a line ``ready
    <command port>`` or ``error <reason>`` on standard output, then serve until standard input
    closes."""
    _normal_policy()
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # a terminal's Ctrl-C: the hardware ends us
    spec, path, n, rows, dt = pickle.load(sys.stdin.buffer)
    try:
        history = ConfigurationHistory.open(path, n, rows, dt)
        natnet = start_motive(spec, Plant.of(spec.arm, spec.plant).model, history)
    except Exception as exc:  # noqa: BLE001 - reported to the hardware's process, which raises it
        reason = str(exc) if isinstance(exc, ConfigError) else f"{type(exc).__name__}: {exc}"
        print(_ERROR, " ".join(reason.split()), flush=True)
        return 1
    try:
        gc.collect()            # the set-up out of the garbage collector, as in every node
        gc.freeze()
        print(_READY, natnet.command_port, flush=True)
        sys.stdin.buffer.read()
    finally:
        natnet.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
