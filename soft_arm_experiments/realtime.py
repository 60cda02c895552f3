"""Real-time scheduling of a run's processes, once they are set up (Linux, where permitted).

The processes the loop closes through run under SCHED_FIFO: under the normal policy a busy
two-core computer holds one of them, or a DDS thread it waits on while it publishes, for 0.1-0.3 s
now and then, and the motor driver's watchdog rightly trips. Two limits of the kernel, and what
the nodes need of a CPU, shape how:

- when the real-time tasks of one CPU use more than ``sched_rt_runtime_us`` (950 ms) of a second,
  every real-time task on that CPU waits 50 ms. So the emulated hardware, which stands for a
  machine that takes no CPU on the rig, runs on a CPU of its own (:func:`hardware_cpu`), which the
  nodes keep off once their set-up is done (seconds of computing each: the three real-time nodes
  set up on one CPU under SCHED_FIFO take minutes). Its Motive server is a process of its own
  (:mod:`soft_arm_drivers.sim.emulated_motive`) under the normal policy, so that it takes nothing
  from that CPU's budget (see
  docs/decisions/0003-emulated-hardware-runs-below-the-nodes-on-a-cpu-of-its-own.md);
- equal FIFO priorities do not preempt: the emulated hardware runs below every node
  (:data:`HARDWARE_PRIORITY`), so that a plant thread catching up does not hold a core the driver
  waits for; under the normal policy a lab PC's other work would delay it past the driver's reply
  timeout;
- the motors' loop (the driver and the inner loop, which its watchdog watches) keeps its CPU to
  itself: the mocap bridge, whose frames feed the outer loop at the camera's rate, runs on the
  emulated hardware's CPU (:data:`BESIDE_HARDWARE`), as the Motive server it reads is there, since
  on one CPU the three need most of it and their bursts hold the inner loop past the watchdog. The
  bridge stays under SCHED_FIFO there, since under the normal policy some of its frames get stamps
  that go back (see docs/decisions/0004-mocap-bridge-runs-on-the-emulated-hardwares-cpu.md).

Every thread of a process is set (a thread inherits its creator's policy and CPUs from then on).

The other processes of the graph (the recorder, the outer loop, the task runner, the orchestrator)
stay under the normal policy, but their middleware threads (Fast DDS's, named ``dds.*``) run under
SCHED_FIFO :data:`MIDDLEWARE_PRIORITY`, below everything else real-time (:func:`schedule` with
``named=MIDDLEWARE_THREADS``). The loop's writers wait on them: Fast DDS's discovery thread,
pairing a reader with a local reliable writer, opens that reader's shared-memory port and polls the
port's listeners, sleeping until they show alive, all the while holding its participant's send
lock, so that a starved process's listeners hold up the driver's state publish, and with it the
driver's whole process, for tens to hundreds of milliseconds (see
docs/decisions/0005-middleware-threads-of-the-other-processes-run-under-sched-fifo.md).
"""
from __future__ import annotations

import os

HARDWARE_PRIORITY = 10     # SCHED_FIFO priority of the emulated hardware: below every node's
MIDDLEWARE_PRIORITY = 1    # SCHED_FIFO priority of the other processes' middleware threads
MIDDLEWARE_THREADS = "dds."    # the name prefix of Fast DDS's threads
BESIDE_HARDWARE = frozenset({"mocap_bridge"})   # real-time nodes on the emulated hardware's CPU


def permitted(priority: int) -> bool:
    """Whether this process may give SCHED_FIFO ``priority`` (tried on itself, then undone): root,
    CAP_SYS_NICE or an rtprio limit."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        os.sched_setscheduler(0, policy, param)
        return True
    except (AttributeError, OSError):
        return False


def hardware_cpu() -> int | None:
    """The CPU the emulated hardware runs on under SCHED_FIFO: the last of this process's, or None
    with a single CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[-1] if len(cpus) > 1 else None


def threads(pid: int) -> list:
    """The thread ids of process ``pid``."""
    return [int(tid) for tid in os.listdir(f"/proc/{pid}/task")]


def child_processes(pid: int) -> list:
    """The process ids whose parent is ``pid``."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="utf-8") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue                                  # gone meanwhile
        if ppid == pid:
            out.append(int(entry))
    return out


def thread_name(pid: int, tid: int) -> str:
    """The name of thread ``tid`` of process ``pid`` ("" if it ended)."""
    try:
        with open(f"/proc/{pid}/task/{tid}/comm", encoding="utf-8") as fh:
            return fh.read().strip()
    except OSError:
        return ""


def schedule(pid: int, priority: int, cpus=None, named: str = ""):
    """The threads of process ``pid`` whose names start with ``named`` (every thread by default)
    under SCHED_FIFO ``priority``, on ``cpus`` (a set) if given; its other threads untouched.
    OSError if not permitted; threads that end meanwhile are skipped."""
    for tid in threads(pid):
        if named and not thread_name(pid, tid).startswith(named):
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            if cpus is not None:
                os.sched_setaffinity(tid, cpus)
        except ProcessLookupError:
            continue
