"""Shared fixtures. Every rclpy process in the suite stays on loopback with its own domain id."""
import codecs
import gc
import os
import pathlib
import re
import select
import signal
import subprocess
import time
from contextlib import contextmanager

import numpy as np
import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
# pytest-xdist's workers run tests side by side: each on a domain of its own, so that two tests'
# nodes (two "harness" publishers on tendon/command, two simulators) never meet
if os.environ.get("PYTEST_XDIST_WORKER", "").startswith("gw"):
    os.environ["ROS_DOMAIN_ID"] = str(1 + (int(os.environ["ROS_DOMAIN_ID"])
                                           + 1 + int(os.environ["PYTEST_XDIST_WORKER"][2:])) % 200)

# Tests that need the CPU before the rest whenever they want it: real time (the emulated rig, the
# driver's cycle thread, real-time scheduling, mocap streams at 240 Hz), or graphs of node processes
# whose discovery and wall-clock deadlines a loaded machine would stretch, or the live view, whose
# process runs only on the CPU the rest leaves (a loaded machine starves it until the run ends): a
# file, or one test of it. `test/run` runs them in one process (one rig at a time) beside the rest,
# which runs on every core at niceness 19 (docs/decisions/0022). Graphs composed in one process, in
# lockstep, are deterministic whatever the load, and run with the rest.
SERIAL = ("drivers/sim/test_emulated_rig.py", "drivers/sim/test_emulated_hardware.py",
          "experiments/test_realtime.py", "drivers/can/test_motor_driver_node.py",
          "drivers/can/test_periodic_thread.py", "drivers/can/test_loopback_bus.py",
          "drivers/mocap/test_mocap_bridge_node.py", "drivers/mocap/test_mocap_bridge.py",
          "drivers/recording/test_recorder_node.py",
          "graph/test_nodes.py::test_simulator_in_realtime_holds_the_tension_and_counts_missing_commands",
          "graph/test_nodes.py::test_simulator_in_lockstep_keeps_to_its_real_time_factor",
          "graph/test_nodes.py::test_a_slow_clik_takes_a_goal_at_once_and_drops_the_frames_it_cannot_"
          "keep_up_with",
          "graph/test_nodes.py::test_ctrl_c_stops_the_experiment_and_keeps_the_bag",
          "graph/test_graph.py::test_processes_mode_runs_each_node_as_its_own_process",
          "graph/test_identification_graph.py::test_the_identification_experiment_runs_one_process_per_node",
          "test_layering.py::test_controller_nodes_start_without_the_plant_file",
          "test_benches.py::test_the_mocap_bench_measures_through_the_bridge_node",
          "graph/test_live_view_node.py::test_a_viewer_that_never_reads_does_not_slow_the_graph",
          "graph/test_live_view_node.py::test_a_run_with_live_serves_itself_to_a_viewer")


# Tests that assert a closed-loop figure (an error, an RMS, targets reached, a NEES): `test/variants`
# runs them on other arithmetics and on perturbed twins of the plant, where each must hold as well.
FIGURES = ("experiments/test_harness.py", "experiments/test_harness_feedback.py",
           "experiments/test_estimate_in_motion.py", "control/test_shape_estimation.py",
           "control/test_dynamic_estimation.py", "graph/test_graph.py", "graph/test_feedback_graph.py")


# The order in which `test/run` hands pytest-xdist the parallel part's files, whole
# (`--no-loadscope-reorder`); a file missing here runs after them. First the files whose tests mostly
# wait (on processes they start, on sockets, on their own time bounds): at the start their waits
# overlap the real-time part's work, which keeps the cores busy; at the end of the run they would
# leave a core idle (about twenty seconds of one). Then the heaviest, heaviest first by the CPU seconds
# their tests took (`--durations=0`, one Xeon, 2026-12), so that no worker starts a minute of work
# while the other has nothing left; xdist's own order (the files with the most tests first) would
# put these few-test files last.
WAITING_FIRST = ("graph/test_orchestration.py", "graph/test_fork_server.py",
                 "ros/test_localhost_discovery.py", "graph/test_shape_estimator_node.py",
                 "ros/test_hardware_lock.py", "test_wait_for_output.py")
HEAVIEST_FIRST = ("experiments/test_harness.py", "experiments/test_identification_run.py",
                  "experiments/test_estimate_in_motion.py", "campaigns/test_campaign_cli.py",
                  "graph/test_identification_graph.py", "experiments/test_harness_feedback.py",
                  "graph/test_graph.py", "control/test_strike_planner.py", "graph/test_nodes.py",
                  "campaigns/test_campaign_engine.py", "model/test_validation.py")
SCHEDULE = WAITING_FIRST + HEAVIEST_FIRST


def pytest_configure(config):
    """Before anything compiles, once per pytest run (not in xdist's workers): delete the cached
    kernels that sources changed since they were built may have made stale (numba misses an edit
    in another file)."""
    if not hasattr(config, "workerinput"):
        from soft_arm_experiments.kernel_cache import clear_stale
        clear_stale()


def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`SERIAL` ``serial`` and those of :data:`FIGURES` ``figure``; the files
    of :data:`SCHEDULE` first, in its order (each file's tests in theirs)."""
    root = os.path.dirname(os.path.abspath(__file__))
    rank = {}
    for item in items:
        path = os.path.relpath(str(item.fspath), root)
        if path in SERIAL or f"{path}::{item.originalname}" in SERIAL:
            item.add_marker(pytest.mark.serial)
        if path in FIGURES or f"{path}::{item.originalname}" in FIGURES:
            item.add_marker(pytest.mark.figure)
        rank[item.nodeid] = SCHEDULE.index(path) if path in SCHEDULE else len(SCHEDULE)
    items.sort(key=lambda item: rank[item.nodeid])


_frozen_for = [None]     # the module (or class) whose serial tests run on the frozen heap now


@pytest.fixture(autouse=True)
def _real_time_heap(request):
    """A ``serial`` (real-time) test's process is set up as a node's process is
    (:func:`soft_arm_ros.runtime.run_node`): the earlier tests' garbage collected, then what is left
    frozen out of the garbage collector for the test, as a full collection of that heap holds the
    GIL 100-170 ms, past the watchdogs of a driver's cycle thread in the same process. Collected
    first: frozen garbage would keep an earlier test's nodes alive, on this test's topics.

    The heap stays frozen from one test of a module (or class) to the next, so that each test
    collects only what the one before it left, not the whole heap again (a tenth of a second each,
    some fifteen seconds of CPU over the real-time part); the first test of a module unfreezes and
    collects everything, where the fixtures of the module before may have left garbage among the
    frozen objects. A test that is not ``serial`` runs unfrozen."""
    if request.node.get_closest_marker("serial") is None:
        if _frozen_for[0] is not None:
            gc.unfreeze()
            _frozen_for[0] = None
        yield
        return
    if request.node.parent is not _frozen_for[0]:
        gc.unfreeze()
        _frozen_for[0] = request.node.parent
    gc.collect()
    gc.freeze()
    yield


# SOFT_ARM_TWIN=k (1, 2, 3; `test/variants`): every plant this process simulates is a twin of the
# configured one, its physical differences from the controller's arm scaled by 1 +- 1e-6 and its
# mocap drawn from another seed. A figure that holds on the plant and not on its twins was luck.
TWIN = int(os.environ.get("SOFT_ARM_TWIN", "0") or 0)
if TWIN:
    from dataclasses import replace as _replace

    from soft_arm_drivers.sim import plant_config as _plant_config

    _parse_plant = _plant_config.parse_plant

    def _twin_of(value, rng):
        if isinstance(value, float):
            return value * (1.0 + 1e-6 * rng.choice((-1.0, 1.0)))
        if isinstance(value, (list, tuple)) and value and all(isinstance(v, float) for v in value):
            return type(value)(_twin_of(v, rng) for v in value)
        return value

    def _parse_twin(values, arm):
        plant = _parse_plant(values, arm)
        rng = np.random.default_rng(TWIN)
        return _replace(plant, arm_values={k: _twin_of(v, rng) for k, v in sorted(plant.arm_values.items())},
                        mocap_seed=plant.mocap_seed + 1000 * TWIN)

    _plant_config.parse_plant = _parse_twin


from soft_arm_model import build_model, load_arm_config  # noqa: E402

try:
    from soft_arm_interfaces.msg import ConfigurationReference, TaskGoal  # noqa: E402, F401
except ImportError as exc:
    pytest.exit(f"the graph's messages are not built in this environment ({exc}): run "
                "python soft_arm_interfaces/build_pypi.py", returncode=4)


def make_model(**overrides):
    """A model of the default arm with dotted-key overrides (``**{"material.viscosity": 0.0}``)."""
    return build_model(load_arm_config(overrides=overrides))


@pytest.fixture(scope="session")
def model_factory():
    return make_model


@pytest.fixture(scope="session")
def paper_model():
    return build_model()


@pytest.fixture(scope="session")
def full_model():
    """All six strain modes, two divisions, orders 2 and 1: exercises every row of the kernels."""
    return make_model(**{"discretisation.modes.shear_y": True, "discretisation.modes.shear_z": True,
                         "discretisation.legendre_order": [2, 1]})


@pytest.fixture(scope="session")
def loaded_model():
    """The paper's arm carrying a 20 g point mass at the tip (and shear): the tip terms of every kernel."""
    return make_model(**{"tip_mass": 0.02, "discretisation.modes.shear_y": True,
                         "discretisation.modes.shear_z": True})


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def wait_for_output(proc, text: str, timeout: float = 60.0) -> str:
    """Read a process's text output (stdout, stderr merged, a pipe) until a line with ``text`` has
    appeared: what was read, which may run past that line (so that what was read, then
    ``proc.communicate()``'s or :func:`stop`'s output, is the whole output). AssertionError with
    the output if it ends or ``timeout`` [s] passes first. A later wait on the same process also
    searches what this one read past its line.

    The pipe's descriptor is read directly. A buffered ``readline`` takes whatever the pipe holds and
    returns one line, so that a ``select`` on the descriptor waits for the process's next write while
    the line looked for sits unread in the buffer: seen seconds late, after the run it announced."""
    fd = proc.stdout.fileno()
    decoder = codecs.getincrementaldecoder("utf-8")("replace")
    searched = getattr(proc, "output_past_the_last_wait", "")
    read = []
    deadline = time.monotonic() + timeout
    ended = False
    while True:
        end = _end_of_line_with(searched, text, ended)
        if end >= 0:
            proc.output_past_the_last_wait = searched[end:]
            return "".join(read)
        left = deadline - time.monotonic()
        # never a read that blocks past the deadline: a silent process fails the wait on time
        if ended or left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        chunk = os.read(fd, 65536)
        ended = not chunk
        piece = decoder.decode(chunk, final=ended)
        read.append(piece)
        searched += piece
    raise AssertionError(f"{text!r} not seen within {timeout:g} s; output:\n{''.join(read)}")


def _end_of_line_with(output: str, text: str, ended: bool) -> int:
    """The index past the first line of ``output`` that holds ``text`` (the line's newline
    included; a last line without one only once the output has ``ended``), or -1."""
    at = output.find(text)
    if at < 0:
        return -1
    newline = output.find("\n", at + len(text))
    if newline >= 0:
        return newline + 1
    return len(output) if ended else -1


@contextmanager
def killed_on_exit(proc):
    """Run the block; a process still running after it (the block failed) is killed and reaped."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def stop(proc, sig=signal.SIGINT, timeout: float = 60.0) -> str:
    """Send ``sig`` and wait for the process to exit: the rest of its output (if piped). A process
    still running after ``timeout`` [s] is killed and the test fails with its output."""
    proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"the process did not exit on {signal.Signals(sig).name}:\n{out}") from None
    return out or ""


@pytest.fixture
def context():
    """An rclpy context of its own, shut down after the test."""
    import rclpy
    from rclpy.context import Context
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def spin_until(executor, predicate, timeout: float = 10.0, unless_ended=None):
    """Spin ``executor`` until ``predicate()`` holds, or until the process ``unless_ended`` (if
    given) has ended; AssertionError after ``timeout`` [s]."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.005)
        if predicate() or (unless_ended is not None and unless_ended.poll() is not None):
            return
    raise AssertionError(f"timed out after {timeout} s")


def change_state(executor, client, label: str, timeout: float = 10.0) -> bool:
    """Ask a managed node for the lifecycle transition ``label`` through its change_state service
    (``client``, as ``ros2 lifecycle set`` does), spinning ``executor``; whether it succeeded. An
    answer that does not come within ``timeout`` [s] is read from the node's state instead
    (get_state, asked up to three times): the server may answer before the middleware has matched
    the client's response reader, and the answer is lost (the orchestrator meets it the same way,
    ``orchestration._change_state``)."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import GetState

    from soft_arm_experiments.orchestration import GOAL_STATES
    spin_until(executor, client.service_is_ready)
    future = client.call_async(client.srv_type.Request(transition=Transition(label=label)))
    try:
        spin_until(executor, future.done, timeout)
        return future.result().success
    except AssertionError:
        pass
    node = next(n for n in executor.get_nodes() if client in n.clients)
    getter = node.create_client(GetState, client.srv_name.replace("change_state", "get_state"))
    try:
        spin_until(executor, getter.service_is_ready)
        for _ in range(3):
            asked = getter.call_async(GetState.Request())
            try:
                spin_until(executor, asked.done, timeout / 2)
            except AssertionError:
                continue
            return asked.result().current_state.label == GOAL_STATES[label]
        raise AssertionError(f"{label}: neither its answer nor the node's state came ({client.srv_name})")
    finally:
        node.destroy_client(getter)


@pytest.fixture
def make_rig():
    """``make(plant=None, overrides=None, **emulator_options)``: a CAN driver core and motor emulator
    in lockstep (test/drivers/can/can_rig.py, importable from the CAN tests' folder), closed after
    the test."""
    from can_rig import Rig, driver_config
    rigs = []

    def make(plant=None, overrides=None, **options):
        rigs.append(Rig(driver_config(**(overrides or {})), plant, **options))
        return rigs[-1]
    yield make
    for rig in rigs:
        rig.close()


def node_logs(log_dir) -> dict:
    """Per node name: the process ids [int] of the ROS log files (``<exe>_<pid>_<time>.log``, one
    per process) under ``log_dir`` whose lines that node logged."""
    out = {}
    for path in pathlib.Path(log_dir).rglob("*.log"):
        pid = int(re.search(r"_(\d+)_\d+\.log$", path.name).group(1))
        for name in set(re.findall(r"^\[\w+\] \[[\d.]+\] \[([\w.]+)\]", path.read_text(), re.M)):
            out.setdefault(name, []).append(pid)
    return out


# The normalised estimation error squared (NEES) of a 3-D position against the chi-square
# distribution with 3 degrees of freedom: its 1 % and 99 % quantiles. Samples of one run are
# correlated, so a run's mean is judged against the interval of one sample.
CHI2_3_01, CHI2_3_99 = 0.1148, 11.345


def nees_not_overconfident(nees) -> bool:
    """The mean NEES at most the 99 % quantile, and no more than 2 % of the samples beyond it."""
    nees = np.asarray(nees)
    return nees.mean() <= CHI2_3_99 and np.mean(nees > CHI2_3_99) <= 0.02


def nees_bounded(nees) -> bool:
    """Not overconfident, and the mean NEES at least the 1 % quantile of ONE chi-square(3) sample.
    A bound, not honesty: the mean of many frames of an exact covariance is 3 within a much
    narrower interval; this accepts any covariance from about 15 times too large to 100 times too
    small of the error's (the tendon-only estimate's mean is 0.3-0.7: conservative)."""
    return CHI2_3_01 <= np.mean(nees) and nees_not_overconfident(nees)
