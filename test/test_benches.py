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
    assert {"soft_arm_drivers.experiments.experiment", "soft_arm_control.inner_loop_node"} <= set(
        _modules_run(BENCH / "bench_graph.py"))


@pytest.mark.parametrize("name", SCRIPTS)
def test_a_bench_script_imports_and_every_module_it_runs_exists(name, bench_path):
    importlib.import_module(name)
    for module in _modules_run(BENCH / f"{name}.py"):
        assert importlib.util.find_spec(module) is not None, \
            f"{name}.py runs python -m {module}: no such module"


def test_the_mocap_bench_measures_through_the_bridge_node(bench_path):
    """Its emulated server streams at 240 Hz on loopback for 2 s; the node, configured and activated,
    publishes the frames (more than 300 arrive), and the latency it measures is positive."""
    from bench_mocap import bench_ros_latency
    out = bench_ros_latency(duration=1.0)
    assert out["received"] > 300, out
    assert 0 < out["to_mocap_markers"]["p50_ms"] <= out["to_mocap_markers"]["p99_ms"], out
