"""A run's node processes, forked from one process that has imported what they all import.

A node started from a fresh interpreter spends about a second of CPU before its node does anything:
numpy, numba, scipy.linalg (numba's BLAS), rclpy, the model's kernels, and numba's target context,
made at the first compiled call (docs/decisions/0026-node-processes-fork-from-a-preloaded-server.md).
A run starts up to ten. Its fork server (:class:`ForkServer`, one per run) is an interpreter that
imports those (:data:`PRELOAD`) and makes the target context, without initialising rclpy or
starting a thread of its own, then forks one child per node; the child runs the node's module as
``python -m`` would and pays only for what is its own. The server has two threads it did not
start: importing rclpy loads the tracing library its middleware links (LTTng-UST, ros2_tracing's),
whose two listener threads wait for LTTng's daemon. A fork copies neither: a forked node is not
traced, even where the daemon runs (the launch files' nodes are).

A forked node is set up as every node process of a run is, before it runs anything: the node's
name as the process's (what ps, top and pgrep show; its command line stays the server's, and its
program name, from which rcl names its log file, the interpreter's), a process group of its own (setsid:
a Ctrl-C in the terminal reaches the orchestrator only, which stops the nodes in order), its
scheduling (SCHED_FIFO priority or niceness: every thread it starts inherits it), SIGINT when its
parent ends (PR_SET_PDEATHSIG: the Ctrl-C its shutdown answers, the motor driver's zero torque; it
comes as the server's thread that forked it ends, and the server's exit status once its other
threads have),
every thread's stack on :data:`STACKS_SIGNAL` (faulthandler: also while a thread is stuck in C).
The server itself gets SIGKILL when the orchestrator ends, however it ends (its nodes then get
their SIGINT), and ends with the orchestrator's last request otherwise. It reaps its children and
reports each one's exit status, which :class:`ForkedProcess` (the orchestrator's handle of a node,
``subprocess.Popen``'s interface) reads.

Protocol, one line each way: the orchestrator writes a request (JSON: ``name``, ``module``,
``args``, ``fifo`` (a SCHED_FIFO priority or null), ``niceness``); the server answers ``started
<pid>`` or ``failed <reason>``, and writes ``exited <pid> <status>`` (Popen's returncode: negative
for a signal) when a child ends; ``ready`` once, when it has imported everything.
"""
from __future__ import annotations

import ctypes
import faulthandler
import gc
import json
import os
import runpy
import select
import signal
import subprocess
import sys
import time

STACKS_SIGNAL = signal.SIGUSR1
PR_SET_NAME = 15
PR_SET_PDEATHSIG = 1
# what every node imports (the recorder and the motor driver: rclpy alone), in the server once
PRELOAD = ("numpy", "scipy.linalg", "numba", "rclpy", "rclpy.node", "rclpy.executors",
           "soft_arm_model.kernels")
READY_TIMEOUT = 120.0       # s, for the server's imports (a cold kernel cache compiles one kernel)
ANSWER_TIMEOUT = 10.0       # s, for the server to answer a request (a fork)
CLOSE_TIMEOUT = 5.0         # s, for the server to end once its requests have
# Popen-like returncode of a node whose server ended before it: its exit status is lost
STATUS_LOST = -256


def _prctl(option: int, value) -> None:
    if ctypes.CDLL(None, use_errno=True).prctl(option, value) != 0:
        raise OSError(ctypes.get_errno(), f"prctl({option}) failed")


def _end_with_parent(signum: int):
    """This process gets ``signum`` when the thread that forked it ends (PR_SET_PDEATHSIG)."""
    _prctl(PR_SET_PDEATHSIG, int(signum))


def make_target_context():
    """numba's target context, which it makes at the first compiled call of a process (some 0.4 s
    of CPU: its registries, scipy's BLAS): one cached kernel called, which loads it."""
    import numpy as np

    from soft_arm_model.lie import ad_apply
    ad_apply(np.zeros(6), np.zeros(6), np.zeros(6))


class _Lines:
    """Lines of text from a pipe's read end, read as they come (``read(timeout)``)."""

    def __init__(self, fd: int):
        self.fd, self._buffer, self.closed = fd, b"", False

    def read(self, timeout: float | None) -> list:
        """The complete lines that arrived within ``timeout`` [s] (None: until one does); [] if
        none; at the end of the pipe, :attr:`closed` is set."""
        if not self.closed and select.select([self.fd], [], [], timeout)[0]:
            chunk = os.read(self.fd, 65536)
            self.closed = not chunk
            self._buffer += chunk
        *lines, self._buffer = self._buffer.split(b"\n")
        return [line.decode() for line in lines]


def _reply(fd: int, line: str):
    os.write(fd, (line + "\n").encode())


def _reap(replies: int):
    """Report every child that has ended."""
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        _reply(replies, f"exited {pid} {os.waitstatus_to_exitcode(status)}")


def _serve(requests: int, replies: int) -> dict:
    """Fork a child per request until the requests end (then exit); returns, in a child only, the
    request it was forked for."""
    wake_r, wake_w = os.pipe()
    for fd in (wake_r, wake_w):
        os.set_blocking(fd, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda signum, frame: None)
    lines = _Lines(requests)
    _reply(replies, "ready")
    while True:
        ready = select.select([requests, wake_r], [], [])[0]
        if wake_r in ready:
            while True:
                try:
                    os.read(wake_r, 4096)
                except BlockingIOError:
                    break
            _reap(replies)
        if requests not in ready:
            continue
        for line in lines.read(0):
            request = json.loads(line)
            sys.stdout.flush()
            sys.stderr.flush()
            try:
                pid = os.fork()
            except OSError as exc:
                _reply(replies, f"failed {exc}")
                continue
            if pid == 0:
                signal.set_wakeup_fd(-1)
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                for fd in (requests, replies, wake_r, wake_w):
                    os.close(fd)
                return request
            _reply(replies, f"started {pid}")
        if lines.closed:
            _reap(replies)
            sys.exit(0)


def _run_node(request: dict, server: int):
    """In a forked child: set up as a node process (module docstring), then run the node's module
    as ``python -m`` would, with the request's arguments."""
    _prctl(PR_SET_NAME, ctypes.c_char_p(request["name"].encode()))
    os.setsid()
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if request["fifo"]:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(request["fifo"]))
    elif request["niceness"]:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, request["niceness"])
        except OSError:
            pass
    _end_with_parent(signal.SIGINT)
    if os.getppid() != server:              # the server ended before the line above
        sys.exit(0)
    faulthandler.register(STACKS_SIGNAL, all_threads=True)
    sys.argv = [request["module"]] + list(request["args"])
    runpy.run_module(request["module"], run_name="__main__", alter_sys=True)


def main(argv: list) -> None:
    """The server: ``argv`` = (the orchestrator's pid, the requests' read end, the replies' write
    end). Returns only in a child, having run its node."""
    parent, requests, replies = (int(a) for a in argv)
    _end_with_parent(signal.SIGKILL)
    if os.getppid() != parent:
        sys.exit(0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # it ends with its requests, or with its parent
    for module in PRELOAD:
        __import__(module)
    make_target_context()
    gc.collect()
    gc.freeze()                 # the children's collections leave the shared imports alone
    server = os.getpid()
    request = _serve(requests, replies)
    _run_node(request, server)


class ForkServer:
    """The orchestrator's side: the server process of one run (started at once, ready when it
    returns: RuntimeError if not within ``timeout`` [s]), in the environment ``env``; its and its
    children's standard output and error go to ``output`` (subprocess's: a file, DEVNULL), by
    default this process's."""

    def __init__(self, env: dict, timeout: float = READY_TIMEOUT, output=None):
        requests_r, self._requests = os.pipe()
        self._replies, replies_w = os.pipe()
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-m", __name__, str(os.getpid()), str(requests_r), str(replies_w)],
                env=env, pass_fds=(requests_r, replies_w), start_new_session=True, stdout=output,
                stderr=output)
        except BaseException:
            os.close(self._requests)
            os.close(self._replies)
            raise
        finally:
            os.close(requests_r)
            os.close(replies_w)
        self._lines = _Lines(self._replies)
        self.exits: dict = {}            # pid: returncode, as the server reports them
        self._answers: list = []
        try:
            self._answer(timeout, "to import what the nodes import (" + ", ".join(PRELOAD) + ")",
                         expected="ready")
        except BaseException:
            self.close()
            raise

    def start(self, name: str, module: str, args: list, fifo: int | None = None,
              niceness: int = 0) -> "ForkedProcess":
        """A child named ``name`` (at most 15 characters: the kernel's process name) that runs
        ``module`` with ``args`` (sys.argv[1:]) under SCHED_FIFO ``fifo`` if given, else at
        ``niceness`` (where permitted). RuntimeError if the server does not fork it."""
        if not 0 < len(name.encode()) <= 15:
            raise ValueError(f"a process name is 1 to 15 bytes, got {name!r}")
        request = {"name": name, "module": module, "args": list(args), "fifo": fifo, "niceness": niceness}
        os.write(self._requests, (json.dumps(request) + "\n").encode())
        answer = self._answer(ANSWER_TIMEOUT, f"to fork the process of {module}")
        if not answer.startswith("started "):
            raise RuntimeError(f"the node fork server could not fork the process of {module}: "
                               f"{answer.partition(' ')[2]}")
        return ForkedProcess(self, int(answer.split()[1]), [module] + list(args))

    def collect(self, timeout: float | None = 0.0):
        """Read what the server wrote within ``timeout`` [s]: exit statuses into :attr:`exits`,
        answers kept for :meth:`_answer`."""
        for line in self._lines.read(timeout):
            kind, _, rest = line.partition(" ")
            if kind == "exited":
                pid, status = rest.split()
                self.exits[int(pid)] = int(status)
            else:
                self._answers.append(line)

    @property
    def ended(self) -> bool:
        """The server has ended (its replies closed): what its children report is all there is."""
        return self._lines.closed

    def _answer(self, timeout: float, what: str, expected: str | None = None) -> str:
        deadline = time.monotonic() + timeout
        while not self._answers:
            remaining = deadline - time.monotonic()
            if self.ended:          # its replies closed: it is exiting, if it has not
                try:
                    status = self.process.wait(CLOSE_TIMEOUT)
                except subprocess.TimeoutExpired:
                    status = "unknown (it closed its replies)"
                raise RuntimeError(f"the node fork server exited with status {status}, waiting {what}")
            if remaining <= 0:
                raise RuntimeError(f"the node fork server did not answer within {timeout:g} s, "
                                   f"waiting {what}")
            self.collect(remaining)
        answer = self._answers.pop(0)
        if expected is not None and answer != expected:
            raise RuntimeError(f"the node fork server answered {answer!r}, waiting {what}")
        return answer

    def check(self):
        """RuntimeError if the server has ended (its nodes get their SIGINT with it)."""
        status = self.process.poll()
        if status is not None:
            raise RuntimeError(f"the node fork server exited with status {status}: its nodes stop with it")

    def close(self, timeout: float = CLOSE_TIMEOUT):
        """End the server (its requests end; a child still running gets its SIGINT), at most
        ``timeout`` [s] later by SIGKILL; what it reported last is read."""
        if self._requests is None:
            return
        os.close(self._requests)
        self._requests = None
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        while not self.ended:
            self.collect(None)
        os.close(self._replies)


class ForkedProcess:
    """A node process the :class:`ForkServer` forked: ``subprocess.Popen``'s ``pid``, ``args``,
    ``returncode``, ``poll``, ``wait``, ``send_signal``, ``kill``. Its exit status comes from the
    server; if the server ended first, :data:`STATUS_LOST` once the process has ended (a pidfd says
    when, and carries its signals, so that a pid used again is never signalled)."""

    def __init__(self, server: ForkServer, pid: int, args: list):
        self.server, self.pid, self.args = server, pid, args
        self.returncode = None
        try:
            self._pidfd = os.pidfd_open(pid)
        except ProcessLookupError:          # ended and reaped already: the server reports it
            self._pidfd = None

    def poll(self):
        """The exit status if the process has ended, else None."""
        if self.returncode is None:
            self.server.collect(0.0)
            self._settle()
        return self.returncode

    def _settle(self):
        if self.pid in self.server.exits:
            self.returncode = self.server.exits[self.pid]
        elif self.server.ended and (self._pidfd is None or select.select([self._pidfd], [], [], 0)[0]):
            self.returncode = STATUS_LOST
        if self.returncode is not None and self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None

    def wait(self, timeout: float | None = None):
        """The exit status, once the process has ended; subprocess.TimeoutExpired if it has not
        within ``timeout`` [s] (None: no bound: after a SIGKILL only)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            remaining = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
            if remaining <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            if self.server.ended:
                select.select([self._pidfd], [], [], remaining)
            else:
                self.server.collect(remaining)
        return self.returncode

    def send_signal(self, signum: int):
        """Signal the process, unless it has ended."""
        if self.poll() is None and self._pidfd is not None:
            try:
                signal.pidfd_send_signal(self._pidfd, signum)
            except ProcessLookupError:
                pass

    def kill(self):
        self.send_signal(signal.SIGKILL)


if __name__ == "__main__":
    main(sys.argv[1:])
