"""``--live [HOST:]PORT``: the live_view node started beside a run, in a process of its own, so that
a viewer costs the run's nodes nothing but the messages they already publish."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys

from .live_view import check_bind


def parse_address(text: str) -> tuple[str, int]:
    """(host, port) of ``[HOST:]PORT`` (host 127.0.0.1 when left out); ValueError otherwise."""
    host, _, port = text.rpartition(":")
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--live takes [HOST:]PORT with a port in [0, 65535], got {text!r}")
    return host, int(port)


def live_arguments(host: str, port: int, record: str = "") -> list:
    """The live_view node's ``--ros-args`` for ``host``:``port`` and the MCAP file ``record`` (empty:
    none): an address beyond loopback, asked for on the command line, sets ``view.remote``."""
    out = ["-p", f"view.host:={host}", "-p", f"view.port:={port}", "-p", f"view.record:={record}"]
    try:
        check_bind(host, False)
    except ValueError:
        out += ["-p", "view.remote:=true"]
    return out


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
