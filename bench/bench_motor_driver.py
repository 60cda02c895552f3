"""Benchmark of the CAN motor driver's loop against the motor emulator. Prints a table, writes JSON.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_motor_driver.py [--seconds 5]
        [--output bench/results/motor_driver.json]

The driver core (``MotorDriver.cycle``, all four motors of config/rig.yaml, enabled, a new command
every cycle) runs from a timed loop at 500 Hz and at 1 kHz on a bus of two kinds: python-can's
``virtual`` (in-process; it deep-copies every frame) and the project's ``soft_arm_loopback`` (UDP on
127.0.0.1, the emulated rig's bus); the
emulator answers from a thread of the same process (real time, 0.2 ms reply delay), either with the
arm behind it (``soft_arm_control.rig.Plant`` stepped every 1 ms: it competes for the GIL) or with
static tendons (the bus alone). Two ways of waiting for the next period: ``sleep`` (``time.sleep``
up to the deadline) and ``sleep+spin`` (sleep to 0.3 ms before it, then poll the clock, yielding the
GIL). Then the ``motor_driver`` node itself: its cycle thread (``PeriodicThread``, apart from the
executor ``run_node`` spins), with the arm emulator.

Reported per run: the period between successive cycle starts minus the nominal period (jitter:
p50 and p99 of its absolute value, max), the lateness of each start behind its deadline, the time
one cycle takes, the share of cycles in which every motor's reply had arrived, and the fault if
one was latched. One machine, nothing else running; wall-clock numbers, not a real-time kernel.
"""
from __future__ import annotations

import argparse
import itertools
import os
import time

import numpy as np

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import can  # noqa: E402

from soft_arm_drivers.can.driver_config import load_driver_config  # noqa: E402
from soft_arm_drivers.can.loopback_bus import free_udp_ports  # noqa: E402
from soft_arm_drivers.can.motor_driver import MotorDriver  # noqa: E402
from soft_arm_drivers.sim.can_emulator import CanMotorEmulator, EmulatorThread, arm_plant  # noqa: E402

from timing import results_path, write_results  # noqa: E402

SPIN_MARGIN = 3e-4          # s before a deadline where sleep+spin stops sleeping
_CHANNELS = itertools.count()


def _wait(deadline: float, strategy: str):
    if strategy == "sleep":
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        return
    delay = deadline - SPIN_MARGIN - time.monotonic()
    if delay > 0:
        time.sleep(delay)
    while time.monotonic() < deadline:
        time.sleep(0)                           # yields the GIL to the emulator thread


def _stats(starts, deadlines, durations, complete, period) -> dict:
    starts, deadlines = np.asarray(starts), np.asarray(deadlines)
    jitter = np.abs(np.diff(starts) - period) * 1e6
    late = (starts - deadlines) * 1e6
    dur = np.asarray(durations) * 1e6
    return {"cycles": int(starts.size),
            "jitter_p50_us": float(np.percentile(jitter, 50)),
            "jitter_p99_us": float(np.percentile(jitter, 99)),
            "jitter_max_us": float(jitter.max()),
            "late_p50_us": float(np.percentile(late, 50)), "late_p99_us": float(np.percentile(late, 99)),
            "late_max_us": float(late.max()),
            "cycle_p50_us": float(np.percentile(dur, 50)) if dur.size else None,
            "cycle_p99_us": float(np.percentile(dur, 99)) if dur.size else None,
            "complete_share": float(np.mean(complete)) if len(complete) else None}


def _rig(rate: float, plant, interface: str = "virtual"):
    """The driver's configuration on a new channel of ``interface`` and the emulator on its other end."""
    if interface == "virtual":
        channel = emulator_channel = f"bench_motor_driver_{os.getpid()}_{next(_CHANNELS)}"
    else:
        driver_port, emulator_port = free_udp_ports(2)
        channel, emulator_channel = f"{driver_port}:{emulator_port}", f"{emulator_port}:{driver_port}"
    cfg = load_driver_config(overrides={"interface": interface, "channel": channel, "rate": rate})
    bus = can.Bus(interface=interface, channel=emulator_channel, preserve_timestamps=True)
    emulator = CanMotorEmulator.for_config(cfg, bus, plant, reply_delay=2e-4, start_time=time.time())
    return cfg, bus, emulator


def bench_core(rate: float, plant, strategy: str, seconds: float, interface: str) -> dict:
    cfg, bus, emulator = _rig(rate, plant, interface)
    period = 1.0 / rate
    starts, deadlines, durations, complete = [], [], [], []
    with EmulatorThread(emulator):
        with MotorDriver(cfg) as driver:
            t0 = time.monotonic() + 0.05
            driver.enable()
            for k in range(int(seconds * rate)):
                deadline = t0 + k * period
                _wait(deadline, strategy)
                start = time.monotonic()
                driver.command([1.0 + 0.5 * np.sin(2 * np.pi * start), 0.5, 0.5, 0.5])
                state, diagnostics = driver.cycle()
                durations.append(time.monotonic() - start)
                starts.append(start)
                deadlines.append(deadline)
                complete.append(state.complete)
            fault = diagnostics.fault
    bus.shutdown()
    return {**_stats(starts, deadlines, durations, complete, period), "fault": fault}


def bench_node(rate: float, plant, seconds: float) -> dict:
    """The node's cycle thread beside the executor run_node spins, with a hook on each cycle."""
    import rclpy
    from rclpy.parameter import Parameter

    from soft_arm_drivers.can.motor_driver_node import MotorDriverNode
    from soft_arm_ros.runtime import make_executor

    cfg, bus, emulator = _rig(rate, plant)
    period = 1.0 / rate
    context = rclpy.Context()
    rclpy.init(context=context)
    starts, durations, complete = [], [], []
    try:
        with EmulatorThread(emulator):
            node = MotorDriverNode(context=context, parameter_overrides=[
                Parameter(f"rig.motors.{k}", value=v) for k, v in
                {"interface": "virtual", "channel": cfg.channel, "rate": rate,
                 "watchdog_timeout": 1.0}.items()])
            node.trigger_configure()                # opens the bus, finds the motors: the driver exists
            if node.driver is None:
                raise RuntimeError("the motor_driver node did not configure (see its log)")
            original = node.driver.cycle

            def timed_cycle(held):
                now = time.monotonic()
                starts.append(now)
                result = original(held)
                node.driver.command([1.0, 0.5, 0.5, 0.5])   # a controller's answer
                durations.append(time.monotonic() - now)
                complete.append(result.state.complete)
                return result
            node.driver.cycle = timed_cycle
            node.trigger_activate()                 # motor mode, as the operator's activate
            executor = make_executor(context=context)
            executor.add_node(node)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.1)
            fault = node.driver.fault
            executor.shutdown()
            node.close()
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
        bus.shutdown()
    starts = np.asarray(starts[10:])                    # after start-up
    # the thread keeps no deadline list here: lateness is measured against the ideal grid of the first cycle
    deadlines = starts[0] + period * np.round((starts - starts[0]) / period)
    return {**_stats(starts, deadlines, durations[10:], complete[10:], period), "fault": fault}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="duration of each run [s]")
    parser.add_argument("--output", default=results_path("motor_driver.json"))
    args = parser.parse_args()
    plant = arm_plant()
    runs = []
    for rate in (500.0, 1000.0):
        for interface in ("virtual", "soft_arm_loopback"):
            for emulator, p in (("arm", plant), ("bus only", None)):
                for strategy in ("sleep", "sleep+spin"):
                    result = bench_core(rate, p, strategy, args.seconds, interface)
                    runs.append({"rate_hz": rate, "loop": f"core, {strategy}", "bus": interface,
                                 "emulator": emulator, **result})
        runs.append({"rate_hz": rate, "loop": "node, cycle thread", "bus": "virtual", "emulator": "arm",
                     **bench_node(rate, plant, args.seconds)})
    header = (f"{'rate':>6} {'loop':<18} {'bus':<17} {'emulator':<9} {'jitter p50':>10} {'p99':>8} "
              f"{'max':>8} {'late p99':>9} {'cycle p50':>9} {'p99':>7} {'complete':>8}  fault")
    print(header + "\n" + "-" * len(header))
    for r in runs:
        print(f"{r['rate_hz']:6.0f} {r['loop']:<18} {r['bus']:<17} {r['emulator']:<9} "
              f"{r['jitter_p50_us']:8.0f}us "
              f"{r['jitter_p99_us']:6.0f}us {r['jitter_max_us']:6.0f}us {r['late_p99_us']:7.0f}us "
              f"{r['cycle_p50_us']:7.0f}us {r['cycle_p99_us']:5.0f}us {r['complete_share']:8.1%}  "
              f"{r['fault'] or '-'}")
    write_results(args.output, {"seconds_per_run": args.seconds, "reply_delay_s": 2e-4, "runs": runs})


if __name__ == "__main__":
    main()
