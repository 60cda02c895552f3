"""The packages are layered one way: soft_arm_model < soft_arm_ros < soft_arm_control < soft_arm_drivers
< soft_arm_experiments.

The model is physics and knows nothing of ROS; the ROS plumbing knows nothing of the controller or
the drivers; the controller knows nothing of the simulated rig, the hardware drivers, recording or
the experiments, and never reads the simulated plant's parameters (``plant.yaml``); the drivers and
their stand-ins know nothing of the experiments and campaigns run on them.
"""
import ast
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("soft_arm_model", "soft_arm_ros", "soft_arm_control", "soft_arm_drivers", "soft_arm_experiments")
# what each package must not import (itself or anything below it)
FORBIDDEN = {
    "soft_arm_model": ("soft_arm_ros", "soft_arm_control", "soft_arm_drivers", "soft_arm_experiments",
                       "rclpy"),
    "soft_arm_ros": ("soft_arm_control", "soft_arm_drivers", "soft_arm_experiments"),
    "soft_arm_control": ("soft_arm_drivers", "soft_arm_experiments"),
    "soft_arm_drivers": ("soft_arm_experiments",),
}


def imported_modules(source: str, module: str) -> set:
    """Absolute names of every module ``source`` (the text of ``module``) imports, at any depth."""
    package = module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            found.add(name)
            found.update(f"{name}.{alias.name}" for alias in node.names)
    return found


def forbidden(source: str, module: str) -> list:
    """The names ``source`` (the text of ``module``) imports from a layer above its package's."""
    package = module.split(".", 1)[0]
    return sorted(name for name in imported_modules(source, module)
                  if any(name == f or name.startswith(f + ".") for f in FORBIDDEN.get(package, ())))


def violations(package: str) -> list:
    """(module, imported name) pairs of ``package`` that break its layer."""
    out = []
    for path in sorted((ROOT / package).rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        out += [(module, name) for name in forbidden(path.read_text(), module)]
    return out


def test_the_checker_sees_relative_and_nested_imports():
    src = "def f():\n    from ..drivers.sim import plant\nfrom . import clik\nimport rclpy.node\n"
    names = imported_modules(src, "soft_arm_control.sub.mod")
    assert "soft_arm_control.drivers.sim.plant" in names
    assert "soft_arm_control.sub.clik" in names
    assert "rclpy.node" in names


@pytest.mark.parametrize("module", ["soft_arm_drivers.sim.plant", "soft_arm_control.clik",
                                    "soft_arm_model.statics"])
def test_an_import_of_the_experiments_from_below_is_refused(module):
    source = ("from soft_arm_experiments.harness import run_experiment\n"
              "import soft_arm_experiments.campaigns\n")
    assert forbidden(source, module) == ["soft_arm_experiments.campaigns", "soft_arm_experiments.harness",
                                         "soft_arm_experiments.harness.run_experiment"]
    assert forbidden("from soft_arm_drivers.sim import plant\n", "soft_arm_experiments.harness") == []


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_package_imports_a_layer_above_it(package):
    assert violations(package) == []


def test_importing_the_controller_loads_no_driver_or_simulated_rig():
    modules = [".".join(p.relative_to(ROOT).with_suffix("").parts)
               for p in sorted((ROOT / "soft_arm_control").rglob("*.py"))]
    code = ("import sys\n" + "".join(f"import {m}\n" for m in modules)
            + "print(sorted(m for m in sys.modules if m.startswith('soft_arm_drivers')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("module", ["soft_arm_model.parameters", "soft_arm_drivers.recording.recorder_node",
                                    "soft_arm_drivers.can.motor_driver_node"])
def test_what_needs_no_model_starts_without_numba_or_the_kernels(module):
    """A node that only reads parameters (the recorder, the motor driver) does not import numba
    and the model's kernels (about 0.2 s of CPU at each start, on every node of every graph)."""
    code = (f"import sys\nimport {module}\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'scipy') "
            "or m == 'soft_arm_model.kernels'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("module", ["soft_arm_control.clik_node", "soft_arm_control.inner_loop_node",
                                    "soft_arm_control.shape_estimator_node",
                                    "soft_arm_drivers.sim.simulator_node",
                                    "soft_arm_experiments.task_runner_node"])
def test_the_graph_s_nodes_start_without_scipy_s_optimisers_and_splines(module):
    """They use them only on demand (a target's closest point, a strike's plan and its metrics):
    imported at start they cost each node 0.1-0.25 s of CPU."""
    code = (f"import sys\nimport {module}\n"
            "print(sorted(m for m in sys.modules if m in ('scipy.optimize', 'scipy.interpolate')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert out.stdout.strip() == "[]"


def test_the_model_package_gives_every_public_name_on_first_use():
    import soft_arm_model

    assert set(soft_arm_model.__all__) <= set(dir(soft_arm_model))
    for name in soft_arm_model.__all__:
        assert getattr(soft_arm_model, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        soft_arm_model.nothing  # noqa: B018


def test_the_controller_package_never_names_the_plant_file():
    for path in (ROOT / "soft_arm_control").rglob("*.py"):
        text = path.read_text()
        assert "plant.yaml" not in text and "PLANT_SCHEMA" not in text, path


def test_controller_nodes_start_without_the_plant_file(tmp_path):
    """The controller's nodes read arm, control, tasks and graph only: with no plant.yaml in the
    config directory they still start (a node that read it would raise ConfigError)."""
    import rclpy

    from soft_arm_control.clik_node import ClikNode
    from soft_arm_control.inner_loop_node import InnerLoopNode
    from soft_arm_model.parameters import default_config_dir

    config = tmp_path / "config"
    shutil.copytree(default_config_dir(), config)
    (config / "plant.yaml").unlink()
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "-p", "graph.task:=coiling"])
    try:
        for cls in (ClikNode, InnerLoopNode):
            node = cls(str(config), context=context, start_parameter_services=False)
            try:
                assert node.get_name() in ("clik", "inner_loop")
            finally:
                node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
