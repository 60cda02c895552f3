"""Real-time scheduling of a run's processes once they are set up: every thread of a node of the
motors' loop under SCHED_FIFO off the emulated hardware's CPU, the hardware (the node's child
process) below every node on that CPU, and the mocap bridge beside it."""
import os
import subprocess
import sys
import time

import pytest

from soft_arm_experiments import realtime
from soft_arm_experiments.orchestration import _REALTIME, _Children

# a node stand-in: a thread of its own and a child process, both waiting
NODE = """
import multiprocessing, threading, time
threading.Thread(target=time.sleep, args=(60,), daemon=True).start()
child = multiprocessing.get_context("spawn").Process(target=time.sleep, args=(60,), daemon=True)
child.start()
print("up", flush=True)
time.sleep(60)
"""

pytestmark = pytest.mark.skipif(not realtime.permitted(max(_REALTIME.values())),
                                reason="SCHED_FIFO is not permitted here")


def _policies(pid):
    return {tid: (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority,
                  os.sched_getaffinity(tid)) for tid in realtime.threads(pid)}


def test_go_realtime_sets_every_thread_of_a_node_and_its_hardware_apart():
    proc = subprocess.Popen([sys.executable, "-c", NODE], stdout=subprocess.PIPE, text=True)
    bridge = subprocess.Popen([sys.executable, "-c", NODE], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "up"
        assert bridge.stdout.readline().strip() == "up"
        children = _Children([], {}, {"emulated_rig": 30, "mocap_bridge": 20})
        children.procs["emulated_rig"] = proc
        children.procs["mocap_bridge"] = bridge
        hardware = realtime.child_processes(proc.pid)          # the child (and spawn's resource tracker)
        assert hardware
        assert len(realtime.threads(proc.pid)) >= 2
        children.go_realtime()
        cpus, off = os.sched_getaffinity(0), realtime.hardware_cpu()
        for policy, priority, affinity in _policies(proc.pid).values():
            assert (policy, priority) == (os.SCHED_FIFO, 30)
            assert affinity == (cpus if off is None else cpus - {off})
        for pid in hardware:
            for policy, priority, affinity in _policies(pid).values():
                assert (policy, priority) == (os.SCHED_FIFO, realtime.HARDWARE_PRIORITY)
                assert affinity == (cpus if off is None else {off})
        assert realtime.HARDWARE_PRIORITY < min(_REALTIME.values())
        # the mocap bridge beside the hardware, the motors' loop keeping its CPU to itself
        assert "mocap_bridge" in realtime.BESIDE_HARDWARE and "mocap_bridge" in _REALTIME
        assert not realtime.BESIDE_HARDWARE & {"emulated_rig", "inner_loop"}
        for policy, priority, affinity in _policies(bridge.pid).values():
            assert (policy, priority) == (os.SCHED_FIFO, 20)
            assert affinity == (cpus if off is None else {off})
    finally:
        for p in (proc, bridge):
            p.kill()
            p.wait()
        time.sleep(0.1)


# a node stand-in whose second thread is named like a Fast DDS thread
MIDDLEWARE_NODE = """
import threading, time
def middleware():
    with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as fh:
        fh.write("dds.test")
    print("up", flush=True)
    time.sleep(60)
threading.Thread(target=middleware, daemon=True).start()
time.sleep(60)
"""


def tid_of(pid, name):
    return next(tid for tid in realtime.threads(pid) if realtime.thread_name(pid, tid) == name)


def test_go_realtime_puts_the_other_nodes_middleware_threads_just_above_the_normal_policy():
    """A node outside the loop (the recorder) keeps the normal policy, but its Fast DDS threads
    run under SCHED_FIFO MIDDLEWARE_PRIORITY, below the emulated hardware and every loop node."""
    proc = subprocess.Popen([sys.executable, "-c", MIDDLEWARE_NODE], stdout=subprocess.PIPE, text=True)
    loop = subprocess.Popen([sys.executable, "-c", MIDDLEWARE_NODE], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "up" and loop.stdout.readline().strip() == "up"
        children = _Children([], {}, {"inner_loop": 20})
        children.procs.update(recorder=proc, inner_loop=loop)
        children.go_realtime()
        policies = {realtime.thread_name(proc.pid, tid): (policy, priority)
                    for tid, (policy, priority, _) in _policies(proc.pid).items()}
        assert policies["dds.test"] == (os.SCHED_FIFO, realtime.MIDDLEWARE_PRIORITY)
        assert [p for name, p in policies.items() if name != "dds.test"] == [(os.SCHED_OTHER, 0)]
        assert realtime.MIDDLEWARE_PRIORITY < realtime.HARDWARE_PRIORITY
        # a run without real time (not permitted: no real-time nodes) leaves them alone: setting
        # them would raise where the permission is missing
        os.sched_setscheduler(tid_of(proc.pid, "dds.test"), os.SCHED_OTHER, os.sched_param(0))
        unscheduled = _Children([], {}, None)
        unscheduled.procs["recorder"] = proc
        unscheduled.go_realtime()
        assert os.sched_getscheduler(tid_of(proc.pid, "dds.test")) == os.SCHED_OTHER
    finally:
        for p in (proc, loop):
            p.kill()
            p.wait()
