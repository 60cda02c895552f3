"""The node fork server: each child runs its module as ``python -m`` would, set up as a node process
(its name, a process group of its own, its scheduling, SIGINT when the server ends), from an
interpreter that has the common imports; exit statuses as subprocess.Popen gives them; every wait
bounded and named."""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from soft_arm_experiments import realtime
from soft_arm_experiments.fork_server import PRELOAD, STATUS_LOST, ForkServer

# a node stand-in: writes what it sees of its process into the file named by its first argument,
# then exits with the status of its second, or waits (a negative one), noting a SIGINT
NODE = """
import json, os, sys, time
def report(**facts):
    with open(sys.argv[1], "a", encoding="utf-8") as fh:
        fh.write(json.dumps(facts) + "\\n")
report(argv=sys.argv[1:], name=__name__, ppid=os.getppid(), group_leader=os.getpgid(0) == os.getpid(),
       niceness=os.getpriority(os.PRIO_PROCESS, 0), policy=os.sched_getscheduler(0),
       priority=os.sched_getparam(0).sched_priority,
       preloaded=[m for m in {preload!r} if m in sys.modules],
       comm=open("/proc/self/comm").read().strip(),
       program=os.path.basename(open("/proc/self/cmdline").read().split("\\0")[0]))
status = int(sys.argv[2])
if status < 0:
    try:
        time.sleep(60)
    except KeyboardInterrupt:
        report(interrupted=True)
        sys.exit(7)
sys.exit(status)
"""


@pytest.fixture
def server(tmp_path, monkeypatch):
    (tmp_path / "stand_in_node.py").write_text(NODE.format(preload=PRELOAD), encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    server = ForkServer(dict(os.environ))
    yield server
    server.close()


def _facts(path, count=1, timeout=30.0) -> list:
    import json
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        lines = path.read_text(encoding="utf-8").splitlines() if path.exists() else []
        if len(lines) >= count:
            return [json.loads(line) for line in lines]
        time.sleep(0.05)
    raise AssertionError(f"{path} has fewer than {count} reports after {timeout} s")


def test_a_child_runs_its_module_as_main_in_a_process_group_of_its_own_with_the_imports(server, tmp_path):
    out = tmp_path / "facts"
    proc = server.start("stand_in", "stand_in_node", [str(out), "3"], niceness=5)
    assert proc.wait(timeout=30.0) == 3 and proc.returncode == 3
    facts, = _facts(out)
    assert facts["argv"] == [str(out), "3"] and facts["name"] == "__main__"
    assert facts["ppid"] == server.process.pid and facts["group_leader"]
    assert facts["niceness"] == 5 and facts["policy"] == os.SCHED_OTHER
    assert facts["preloaded"] == list(PRELOAD)
    # named as the node it runs in ps, top and pgrep; its program name (rcl's log file's) python's
    assert facts["comm"] == "stand_in"
    assert facts["program"] == os.path.basename(sys.executable)


def test_a_module_that_does_not_exist_exits_with_status_1_as_python_m_would(server):
    assert server.start("missing", "no_such_node_module", []).wait(timeout=30.0) == 1
    with pytest.raises(ValueError, match="a process name is 1 to 15 bytes"):
        server.start("a_name_too_long_for_ps", "stand_in_node", [])


def test_a_killed_child_reports_the_signal_and_a_bounded_wait_raises(server, tmp_path):
    out = tmp_path / "facts"
    proc = server.start("stand_in", "stand_in_node", [str(out), "-1"])
    _facts(out)
    assert proc.poll() is None
    with pytest.raises(subprocess.TimeoutExpired):
        proc.wait(timeout=0.2)
    proc.kill()
    assert proc.wait(timeout=10.0) == -signal.SIGKILL
    proc.send_signal(signal.SIGINT)                  # ended: nothing is signalled
    # SIGINT reaches the node's own handler (the server ignores it; its children must not)
    other = server.start("stand_in", "stand_in_node", [str(tmp_path / "other"), "-1"])
    _facts(tmp_path / "other")
    other.send_signal(signal.SIGINT)
    assert other.wait(timeout=10.0) == 7
    assert _facts(tmp_path / "other", 2)[1] == {"interrupted": True}


def test_a_child_gets_sigint_when_the_server_ends_and_its_status_is_said_lost(server, tmp_path):
    out = tmp_path / "facts"
    proc = server.start("stand_in", "stand_in_node", [str(out), "-1"])
    _facts(out)
    server.close()
    assert _facts(out, 2)[1] == {"interrupted": True}
    assert proc.wait(timeout=10.0) == STATUS_LOST


@pytest.mark.skipif(not realtime.permitted(5), reason="SCHED_FIFO is not permitted here")
def test_a_real_time_child_is_under_sched_fifo_before_its_module_runs(server, tmp_path):
    out = tmp_path / "facts"
    proc = server.start("stand_in", "stand_in_node", [str(out), "0"], fifo=5, niceness=5)
    assert proc.wait(timeout=30.0) == 0
    facts, = _facts(out)
    assert (facts["policy"], facts["priority"]) == (os.SCHED_FIFO, 5)


def test_a_server_that_cannot_import_says_what_it_waited_for(tmp_path, monkeypatch):
    (tmp_path / "numba.py").write_text("raise ImportError('a broken numba')\n", encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    begin = time.monotonic()
    with pytest.raises(RuntimeError, match=r"the node fork server exited with status 1, waiting to "
                                           r"import what the nodes import \(numpy, scipy.linalg, numba"):
        ForkServer(dict(os.environ))
    assert time.monotonic() - begin < 60.0


def test_a_server_that_does_not_get_ready_in_time_is_stopped_naming_the_wait(tmp_path, monkeypatch):
    (tmp_path / "numba.py").write_text("import time\ntime.sleep(60)\n", encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    with pytest.raises(RuntimeError, match=r"the node fork server did not answer within 0.5 s, waiting "
                                           r"to import what the nodes import"):
        ForkServer(dict(os.environ), timeout=0.5)


def test_a_run_whose_fork_server_is_killed_says_so_and_its_nodes_end(tmp_path, monkeypatch):
    """The orchestrator's check names the server, not a node's lost status; the node got its SIGINT
    with the server, and its stop keeps the status as lost, which the run's exit names."""
    from soft_arm_experiments import orchestration
    from soft_arm_experiments.orchestration import _Children, exit_failure
    (tmp_path / "stand_in_node.py").write_text(NODE.format(preload=PRELOAD), encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    monkeypatch.setattr(orchestration, "node_module", lambda name: "stand_in_node")
    out = tmp_path / "facts"
    children = _Children([str(out), "-1"], {})
    try:
        children.start("recorder")
        _facts(out)
        children.check()
        os.kill(children.server.process.pid, signal.SIGKILL)
        assert _facts(out, 2)[1] == {"interrupted": True}
        # the node's SIGINT comes as the server's thread that forked it ends; the server's process
        # ends (and its status can be read) once its other threads have (the tracing library's
        # listeners, fork_server's module docstring): under load, some time later
        deadline = time.monotonic() + 10.0
        while True:
            try:
                children.check()
            except RuntimeError as exc:
                assert re.fullmatch(r"the node fork server exited with status -9: its nodes stop with it",
                                    str(exc)), exc
                break
            assert time.monotonic() < deadline, "the check did not see the server's end within 10 s"
            time.sleep(0.02)
    finally:
        children.stop(timeout=10.0)
    assert children.exits == {"recorder": STATUS_LOST}
    assert exit_failure(children.exits) == \
        "node recorder ended after the node fork server, its exit status lost"
