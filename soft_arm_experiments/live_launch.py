"""``--live [HOST:]PORT``: the live view of a run. Beside the graph (``soft-arm-experiment``) the
live_view node in a process of its own, so that a viewer costs the run's nodes nothing but the
messages they already publish; in the ROS-free harness (``soft-arm-harness``) a
:class:`HarnessView` fed at every mocap exposure."""
from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time

from .live_view import LiveServer, LiveView, is_loopback


def add_live_argument(parser, what: str):
    """``--live [HOST:]PORT`` on ``parser``; ``what``: how the command serves the view."""
    parser.add_argument("--live", metavar="[HOST:]PORT",
                        help=f"serve the run to the Foxglove app on this address ({what}; HOST 127.0.0.1 "
                             "unless given)")


def parse_address(text: str) -> tuple[str, int]:
    """(host, port) of ``[HOST:]PORT`` (host 127.0.0.1 when left out); ValueError otherwise."""
    host, _, port = text.rpartition(":")
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--live takes [HOST:]PORT with a port in [0, 65535], got {text!r}")
    return host, int(port)


def live_arguments(host: str, port: int, record: str = "") -> list:
    """The live_view node's ``--ros-args`` for ``host``:``port`` and the MCAP file ``record`` (empty:
    none, left to ``config/view.yaml``, since rcl refuses an empty ``-p`` value): an address beyond
    loopback, asked for on the command line, sets ``view.remote``."""
    out = ["-p", f"view.host:={host}", "-p", f"view.port:={port}"]
    out += ["-p", f"view.record:={record}"] if record else []
    return out if is_loopback(host) else out + ["-p", "view.remote:=true"]


READY_FD = "SOFT_ARM_LIVE_READY_FD"    # environment: the pipe the live_view process writes its
#                                       address to, once set up (:func:`report_ready`)
READY_TIMEOUT = 60.0                   # s: the longest a run waits for its live view to be set up


@contextlib.contextmanager
def live_view(address: str | None, ros_args: list, record: str = "", timeout: float = READY_TIMEOUT,
              stopped=lambda: False, processes: int = 1, environ=None):
    """The live_view process for the run while the context lasts (nothing when ``address`` is None),
    writing the view into ``record`` too; yields the address to open once the node is set up (its
    server listening, its subscriptions made), so that the run starts after it and a viewer sees
    all of it: the process starts under SCHED_IDLE and, beside a graph coming up, would otherwise
    be set up only when the run is all but over. RuntimeError, naming what it waited for, if the
    process ends first (its log says why: a port in use, a bad parameter), if it is not set up
    within ``timeout`` s or if ``stopped()`` (polled every 0.1 s) turns true. It is asked to stop
    (SIGINT) at the end and killed after 5 s.

    It starts only where it can meet the run's ``processes`` (the composed run's one, or the nodes'
    and the orchestrator's): on a domain that localhost discovery has too little room left on, two
    of them would take ids it does not reach and never meet (an empty view, or a run that never
    comes up); RuntimeError then, before the view's process starts
    (:func:`soft_arm_ros.localhost_discovery.check_room`). ``environ`` (default this process's) is
    the view's environment: that of the processes it is to meet, so that both discover on one
    range."""
    if address is None:
        yield None
        return
    host, port = parse_address(address)
    from soft_arm_ros.localhost_discovery import check_room
    env = dict(os.environ if environ is None else environ)
    check_room(processes + 1, env)
    command = [sys.executable, "-m", "soft_arm_experiments.live_view_node", "--ros-args", *ros_args,
               *live_arguments(host, port, record)]
    read, write = os.pipe()
    try:
        process = subprocess.Popen(command, start_new_session=True, pass_fds=(write,),
                                   env=dict(env, **{READY_FD: str(write)}))
    finally:
        os.close(write)                  # the process's end is its own: EOF once it exits
    try:
        yield _served(process, read, f"{host}:{port}", timeout, stopped)
    finally:
        os.close(read)
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGINT)
            try:
                process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def _served(process, read: int, asked: str, timeout: float, stopped) -> str:
    """The address the live_view ``process`` writes to the pipe ``read`` once set up."""
    deadline, line = time.monotonic() + timeout, b""
    while not line.endswith(b"\n"):
        if stopped():
            raise RuntimeError(f"stopped while waiting for the live view on {asked} to be set up: "
                               "nothing ran")
        left = deadline - time.monotonic()
        if left <= 0:
            raise RuntimeError(f"the live view on {asked} was not set up within {timeout:g} s")
        if select.select([read], [], [], min(0.1, left))[0]:
            chunk = os.read(read, 256)
            if not chunk:
                try:
                    status = process.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    status = "none yet"
                raise RuntimeError(f"the live view on {asked} ended before it was set up (exit status "
                                   f"{status}; its log says why)")
            line += chunk
    return line.decode().strip()


def report_ready(address: str, environ=os.environ) -> bool:
    """Write ``address`` to the pipe :func:`live_view` waits on (named by ``READY_FD`` in
    ``environ``, taken out of it) and close it; False when no launcher waits (the rig's
    ``ros2 run``). ValueError if the variable names no open file descriptor."""
    fd = environ.pop(READY_FD, None)
    if fd is None:
        return False
    try:
        number = int(fd)
        os.write(number, f"{address}\n".encode())
        os.close(number)
    except (ValueError, OSError) as exc:
        raise ValueError(f"{READY_FD}={fd!r} names no pipe to report the live view's address on: {exc}") \
            from None
    return True


class HarnessView:
    """The harness's observer (:func:`~.harness.run_experiment`) serving the live view on
    ``address`` ([HOST:]PORT): the plant's backbone, the mocap's markers, the estimate, the target and
    the tendons, published at most ``rate`` times per second of wall time (the harness runs faster
    than real time: a viewer sees it fast-forward). ``labels``: the task's coordinates'."""

    def __init__(self, address: str, arm, labels, rate: float = 30.0):
        host, port = parse_address(address)
        self.server = LiveServer(host, port, remote=not is_loopback(host))   # asked for on the command line
        self.view = LiveView(arm.geometry.base_radius, arm.geometry.tip_radius)
        self.labels, self.period, self.next = list(labels), 1.0 / rate, 0.0

    @property
    def address(self) -> str:
        return self.server.address

    def __call__(self, t, rig, frame, estimate, x_d, reference):
        view = self.view
        view.take_backbone(t, rig.plant.stepper.data.p)
        view.take_mocap(t, frame.markers)
        if estimate is not None:
            view.take_estimate(t, estimate.markers, estimate.marker_covariance[-1])
        view.take_target(self.labels, x_d)
        now = time.monotonic()
        if now < self.next:
            return
        self.next = now + self.period
        s, sd = rig.tendons()
        self.server.publish(view, {
            "tendons": {"t": t, "shortening": s.tolist(), "rate": sd.tolist(),
                        "tension": list(map(float, rig.tension)), "reference": reference.shortening.tolist()},
            "task": view.task()})

    def close(self):
        self.server.close()
