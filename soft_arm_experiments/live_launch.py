"""``--live [HOST:]PORT``: the live view of a run. Beside the graph (``soft-arm-experiment``) the
live_view node in a process of its own, so that a viewer costs the run's nodes nothing but the
messages they already publish; in the ROS-free harness (``soft-arm-harness``) a
:class:`HarnessView` fed at every mocap exposure."""
from __future__ import annotations

import contextlib
import os
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


@contextlib.contextmanager
def live_view(address: str | None, ros_args: list, record: str = ""):
    """The live_view process for the run while the context lasts (nothing when ``address`` is None),
    writing the view into ``record`` too; yields the address to open. It is asked to stop (SIGINT)
    at the end and killed after 5 s."""
    if address is None:
        yield None
        return
    host, port = parse_address(address)
    command = [sys.executable, "-m", "soft_arm_experiments.live_view_node", "--ros-args", *ros_args,
               *live_arguments(host, port, record)]
    process = subprocess.Popen(command, start_new_session=True, env=dict(os.environ))
    try:
        yield f"ws://{host}:{port}"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGINT)
            try:
                process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


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
