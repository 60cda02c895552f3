"""A node's process: the executor it spins, its life from creation to a clean exit on a signal."""
from __future__ import annotations

import gc
import re
import signal
import sys

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions

from soft_arm_model.parameters import ConfigError


def make_executor(context=None):
    """The executor every soft_arm process spins: rclpy's events executor (callbacks dispatched from
    C++, about a third of the CPU time per callback of the SingleThreadedExecutor, which rebuilds
    its wait set in Python for every callback) where this rclpy has it, else the
    SingleThreadedExecutor. One thread; a node is added once. See
    docs/decisions/0001-nodes-spin-the-events-executor-and-freeze-their-set-up.md."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        from rclpy.executors import SingleThreadedExecutor
        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


def run_node(factory, name: str, args=None, executor_factory=make_executor) -> int:
    """Create a node with ``factory()`` and spin it (``executor_factory()``, default
    :func:`make_executor`) until Ctrl-C, SIGTERM or until it sets ``done``; a ConfigError while
    creating it is logged and gives exit status 2.

    The first SIGINT or SIGTERM ends the spin between two callbacks (a callback is never cut short
    and the context stays valid while it runs); a second one interrupts the spin at once. A node's
    ``close()`` (if any) then runs, whatever ended the spin (a signal during start-up included), with
    signals ignored so that nothing cuts it short (a driver's zero torque), before the node, the
    executor and the context go; the previous signal handlers come back at the end. What the set-up
    allocated is frozen out of the garbage collector (``gc.freeze``). A node whose ``failure`` is set
    when it ends (an exception a thread of its own ended on, a duty it failed) gives exit status 1."""
    stop = []

    def request_stop(signum, frame):
        if stop:
            raise KeyboardInterrupt
        stop.append(signum)

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = executor = None
    try:
        try:
            rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        except RCLError as exc:          # a --ros-args rcl refuses (a params file it cannot parse)
            raise ConfigError(_rcl_reason(exc)) from None
        node = factory()
        # The set-up leaves some 10^5 long-lived objects (models, compiled kernels, rclpy): a full
        # collection would walk them all, some 50 ms at a time, in the middle of a control period.
        # Collect once now and keep them out of every later collection.
        gc.collect()
        gc.freeze()
        executor = executor_factory()
        executor.add_node(node)
        while not stop and rclpy.ok() and not getattr(node, "done", False):
            executor.spin_once(timeout_sec=0.1)
    except ConfigError as exc:
        if rclpy.ok():
            rclpy.logging.get_logger(name).fatal(f"bad parameter: {exc}")
        else:
            print(f"{name}: bad parameter: {exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for sig in previous:
            signal.signal(sig, signal.SIG_IGN)
        try:
            if node is not None:
                close = getattr(node, "close", None)
                if close is not None:
                    close()
        finally:
            if executor is not None:
                executor.shutdown()
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    return 1 if getattr(node, "failure", None) is not None else 0


def _rcl_reason(exc: Exception) -> str:
    """rcl's message without the C source locations it appends (", at .../parse.c:841")."""
    return re.sub(r",? at /\S+:\d+", "", str(exc)).strip().rstrip(",")
