"""The bench scripts stay runnable: each imports, every module it runs with ``python -m`` exists, and
the mocap bench's measurement through the bridge node (a managed node it must bring up) measures."""
import ast
import importlib
import importlib.util
import pathlib

import pytest

BENCH = pathlib.Path(__file__).resolve().parents[1] / "bench"
SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py"))


@pytest.fixture
def bench_path(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))


def _modules_run(path: pathlib.Path) -> list:
    """The modules a script runs as ``[..., "-m", "<module>", ...]`` (list literals)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.List):
            items = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
            out += [module for flag, module in zip(items, items[1:])
                    if flag == "-m" and isinstance(module, str)]
    return out


def test_the_scripts_run_modules():
    """The check below has something to check: the graph bench runs the experiment and a node."""
    assert {"soft_arm_experiments.experiment", "soft_arm_control.inner_loop_node"} <= set(
        _modules_run(BENCH / "bench_graph.py"))


@pytest.mark.parametrize("name", SCRIPTS)
def test_a_bench_script_imports_and_every_module_it_runs_exists(name, bench_path):
    importlib.import_module(name)
    for module in _modules_run(BENCH / f"{name}.py"):
        assert importlib.util.find_spec(module) is not None, \
            f"{name}.py runs python -m {module}: no such module"


def test_the_mocap_bench_measures_through_the_bridge_node(bench_path):
    """Its emulated server streams at 240 Hz on loopback for 2 s; the node, configured and activated,
    publishes the frames (more than 300), and the latency measured on those that reach the probe is
    positive. The probe's own count is not the node's: on the stream's best-effort, depth-1 QoS a
    probe spun by a loaded machine misses frames, as any late subscriber would (254 of about 470
    reached it on a CI run)."""
    from bench_mocap import bench_ros_latency
    out = bench_ros_latency(duration=1.0)
    assert out["published"] > 300 and out["received"] > 100, out
    assert 0 < out["to_mocap_markers"]["p50_ms"] <= out["to_mocap_markers"]["p99_ms"], out


def test_the_pyelastica_timing_leaves_its_compilation_out():
    """In a process of its own, the model bench's PyElastica warm-up makes every machine-code
    overload the timed runs call (compiled, or loaded from numba's cache: a cold cache's
    compilation falls there); the timed runs after it add none. Counted at numba's dispatchers
    (an overload added is one compiled or loaded), not timed: a timing test would need an empty
    cache, some 20 s of compilation, and a quiet machine."""
    import json
    import subprocess
    import sys
    script = (
        "import json, sys\n"
        "from numba.core.dispatcher import Dispatcher\n"
        "added = []\n"
        "compile_overload = Dispatcher.compile\n"
        "def counted(self, sig):\n"
        "    before = len(self.overloads)\n"
        "    entry = compile_overload(self, sig)\n"
        "    added.extend([self.py_func.__qualname__] * (len(self.overloads) - before))\n"
        "    return entry\n"
        "Dispatcher.compile = counted\n"
        f"sys.path.insert(0, {str(BENCH)!r})\n"
        "from bench_model import elastica_cantilever, elastica_warm_up\n"
        "from soft_arm_model import load_arm_config\n"
        "config = load_arm_config()\n"
        "elastica_warm_up(config, 9.81)\n"
        "warm_up = list(added)\n"
        "run = elastica_cantilever(config, 9.81, 0.02, 10, 2e-5, sample=0.01)\n"
        "print(json.dumps({'warm_up': warm_up, 'timed': added[len(warm_up):], 'stable': run['stable'],\n"
        "                  'track': run['track'].tolist()}))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    overloads = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(overloads["warm_up"]) > 10, overloads          # PyElastica's kernels, not a no-op
    assert overloads["timed"] == [] and overloads["stable"], overloads
    track = overloads["track"]                     # the tip at 0, 10 and 20 ms: straight, then sagging
    assert len(track) == 3 and track[0][0] == pytest.approx(0.38) and abs(track[0][1]) < 1e-12, track
    assert track[2][1] < track[1][1] < 0.0, track


def test_pyelasticas_track_is_at_the_sample_times_whatever_its_step(bench_path, monkeypatch):
    """A rod whose tip moves at a constant velocity: its track is the tip at 0, 20, 40 ... ms exactly,
    also at a step of 0.32 ms, which 20 ms is not a whole number of (sampling at every 62nd step
    would lag the samples by 0.24 s at the end of a 3 s run)."""
    import numpy as np
    import bench_model

    class Rod:
        position_collection = np.zeros((3, 2))

    class Stepper:
        def step(self, sim, t, dt):
            Rod.position_collection[:2, -1] = (t + dt, 2.0 * (t + dt))
            return t + dt
    monkeypatch.setattr(bench_model, "_elastica_system", lambda *args: (None, Rod, Stepper()))
    config = type("Config", (), {"geometry": type("Geometry", (), {"length": 100.0})})
    run = bench_model.elastica_cantilever(config, 9.81, 3.0, 10, 3.2e-4, sample=0.02)
    times = 0.02 * np.arange(151)
    assert run["track"].shape == (151, 2)
    assert np.allclose(run["track"], np.column_stack([times, 2.0 * times]), atol=1e-9, rtol=0.0)


def test_the_cantilevers_ratio_is_taken_where_this_model_is_as_accurate_in_both_senses(bench_path):
    """The fastest of this model's runs as accurate as PyElastica's in its transient and at its
    settled tip, neither alone; a transient's error is over the samples both tracks have; this
    model's track starts at the straight arm's tip and has a sample every SAMPLE_S."""
    import numpy as np
    from bench_model import SAMPLE_S, _cantilever_run, cheapest_at_accuracy, transient_error
    from soft_arm_model import build_model, load_arm_config
    track, reference = [[0.0, 0.0], [0.0, 0.3], [9.0, 9.0]], [[0.0, 0.0], [0.4, 0.0]]
    assert transient_error(track, reference) == pytest.approx(0.5)
    runs = [{"wall_s": 1.0, "transient_error_m": 0.001, "error_vs_kirchhoff_m": 0.002},
            {"wall_s": 0.1, "transient_error_m": 0.005, "error_vs_kirchhoff_m": 0.002},   # transient
            {"wall_s": 0.2, "transient_error_m": 0.001, "error_vs_kirchhoff_m": 0.003},   # settled
            {"wall_s": 0.5, "transient_error_m": 0.004, "error_vs_kirchhoff_m": 0.002}]
    assert cheapest_at_accuracy(runs, 0.0045, 0.0022) is runs[3]
    assert cheapest_at_accuracy(runs, 0.0035, 0.0022) is runs[0]
    assert cheapest_at_accuracy(runs, 0.0005, 0.0022) is None
    m = build_model(load_arm_config(overrides={"gravity": [-9.81, 0.0, 0.0]}))
    run = _cantilever_run(m, "ros2", 2e-3, 4 * SAMPLE_S)
    assert run["track"].shape == (5, 2) and np.allclose(run["track"][0], [0.38, 0.0], atol=1e-12)
    assert np.array_equal(run["track"][-1], run["tip"]) and run["tip"][1] < -1e-3


def test_the_sensing_draws_judge_the_blind_loop_against_the_worse_of_two_holds(bench_path):
    """A transition where the hold and its 1e-6 twin end on different equilibria (20 mm apart) is a
    flip of the plant's, and the blind run ending as the worse of them is no worse than holding; a
    blind run beyond both holds is worse by its distance to the worse one."""
    from bench_sensing import _versus_hold
    holds = {"hold": {"finals": [0.010, 0.050, 0.003]}, "hold_twin": {"finals": [0.010, 0.070, 0.003]}}
    worse, flips = _versus_hold({"finals": [0.010, 0.070, 0.003], **holds})
    assert flips == 1 and abs(worse) < 1e-12
    worse, flips = _versus_hold({"finals": [0.012, 0.060, 0.003], **holds})
    assert flips == 1 and abs(worse - 0.002) < 1e-12
