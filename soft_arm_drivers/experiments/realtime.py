"""Real-time scheduling of a run's processes, once they are set up (Linux, where permitted).

The processes the loop closes through run under SCHED_FIFO: under the normal policy a busy
two-core computer holds one of them, or a DDS thread it waits on while it publishes, for 0.1-0.3 s
now and then, and the motor driver's watchdog rightly trips. Two limits of the kernel, and what
the nodes need of a CPU, shape how:

- when the real-time tasks of one CPU use more than ``sched_rt_runtime_us`` (950 ms) of a second,
  every real-time task on that CPU waits 50 ms (measured: a FIFO 50 task beside a FIFO 10 busy
  loop on its CPU waits 50 ms each second). So the emulated hardware, which stands for a machine
  that takes no CPU on the rig, runs on a CPU of its own (:func:`hardware_cpu`) that the nodes keep
  off, from when their set-up (seconds of computing) is done: set up on one CPU, the three
  real-time nodes took 127 s to start once. Its Motive server is a process of its own
  (:mod:`soft_arm_drivers.sim.emulated_motive`), not scheduled here: under the normal policy it
  takes nothing from that CPU's budget. As a thread of the hardware's process it did (the hardware
  took a median 50 % of its CPU, since 37 %), and every fault of a batch under load came with the
  budget's 40-58 ms stall of that CPU (``bench_emulated_rig.py --probe``); in 15 runs since, none;
- equal FIFO priorities do not preempt: the emulated hardware runs below every node
  (:data:`HARDWARE_PRIORITY`), not at the driver's priority, where a plant thread catching up held
  a core the driver waited for. Under the normal policy instead (tried: niceness -10, and -20 on
  a CPU of its own) a lab PC's other work delayed it past the driver's reply timeout;
- the motors' loop (the driver and the inner loop, which its watchdog watches) keeps its CPU to
  itself: the mocap bridge, whose frames feed the outer loop at the camera's rate, runs on the
  emulated hardware's CPU (:data:`BESIDE_HARDWARE`), as the Motive server it reads is there. With
  the three on one CPU, on a computer half as fast, they needed 68-91 % of it and bursts held the
  inner loop past the watchdog (``bench_emulated_rig.py``: 0 valid runs in 3, each ended by a
  50-81 ms gap in the commands; with the bridge beside the hardware, 3 valid in 3). The bridge
  stays under SCHED_FIFO there: under the normal policy (niceness -20) some of its frames were
  stamped no later than the frame before (2-46 in each of 7 runs of 23; in none of 16 under
  SCHED_FIFO).

Every thread of a process is set (a thread inherits its creator's policy and CPUs from then on).

The other processes of the graph (the recorder, the outer loop, the task runner, the orchestrator)
stay under the normal policy, but their middleware threads (Fast DDS's, named ``dds.*``) run under
SCHED_FIFO :data:`MIDDLEWARE_PRIORITY`, below everything else real-time (:func:`schedule` with
``named=MIDDLEWARE_THREADS``). The loop's writers wait on them: Fast DDS's discovery thread,
pairing a reader with a local reliable writer, opens that reader's shared-memory port and polls the
port's listeners, sleeping until they show alive, all the while holding its participant's send lock. The
driver's state publish waited behind it for 43-293 ms when the listeners were those of a starved
process (README, issue 17, stop 33; two batches with this in place: no such stall in 10 runs;
before it, 10 of 27 instrumented runs were ended by one; in alternating batches, 10 of 10 runs
valid with it, 6 of 10 without). It does not cost the outer loop's accuracy (the accuracy lost in
one batch was the clik node's goals waiting behind queued frames: README, issue 17, stop 34). The
recorder lost more messages under load with it (5-23 % of each tendon stream per run, against
0-17 % without) while it spent 36-46 % of a core on rclpy's executor; since it takes its messages
in batches (15 % of a core, stop 35) it loses none in most runs.
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
