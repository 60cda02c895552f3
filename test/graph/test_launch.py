"""Launch files cannot run here (no launch on PyPI): check that what they name exists."""
import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _console_scripts():
    tree = ast.parse((ROOT / "setup.py").read_text())
    scripts = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and " = " in node.value:
            scripts.add(node.value.split(" = ")[0].strip())
    return scripts


def _constant(tree, name):
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{name} not found")


@pytest.mark.parametrize("path", sorted((ROOT / "launch").glob("*.launch.py")), ids=lambda p: p.name)
def test_launch_file_names_existing_executables_and_parameter_files(path):
    tree = ast.parse(path.read_text())
    nodes = _constant(tree, "NODES")
    files = _constant(tree, "PARAMETER_FILES")
    assert nodes and files
    assert set(nodes) <= _console_scripts()
    for name in files:
        assert (ROOT / "config" / name).is_file(), name
    assert "package=\"soft_arm\"" in path.read_text()


@pytest.mark.parametrize("name", ["rig.launch.py", "sim.launch.py"])
def test_the_task_launches_read_arm_yaml_last(name):
    """An identified arm put in arm.yaml's place carries its mocap calibration and estimator priors
    (soft-arm-identify): given last, they win over mocap.yaml's and estimator.yaml's. The
    identification launch keeps mocap.yaml's calibration, the one soft-arm-identify composes with."""
    files = _constant(ast.parse((ROOT / "launch" / name).read_text()), "PARAMETER_FILES")
    assert files[-1] == "arm.yaml" and files.count("arm.yaml") == 1
    ident = _constant(ast.parse((ROOT / "launch" / "identification.launch.py").read_text()),
                      "PARAMETER_FILES")
    assert ident.index("mocap.yaml") > ident.index("arm.yaml")


def test_the_simulated_graph_records_on_the_simulators_clock():
    """sim.launch.py gives the recorder use_sim_time (as soft-arm-experiment --processes does), and
    only nodes it starts."""
    text = (ROOT / "launch" / "sim.launch.py").read_text()
    tree = ast.parse(text)
    assert _constant(tree, "SIM_TIME_NODES") == ["recorder"]
    assert set(_constant(tree, "SIM_TIME_NODES")) <= set(_constant(tree, "NODES"))
    assert '"use_sim_time": name in SIM_TIME_NODES' in text


def test_there_are_launch_files_for_the_simulated_and_the_physical_rig():
    assert (ROOT / "launch" / "sim.launch.py").is_file()
    assert (ROOT / "launch" / "rig.launch.py").is_file()


@pytest.mark.parametrize("path", sorted((ROOT / "config").glob("*.yaml")), ids=lambda p: p.name)
def test_parameter_file_parses_with_rcl(path):
    """rcl's own YAML rules differ from PyYAML's (a bare y is a boolean there): every parameter
    file must load through rclpy --params-file."""
    import rclpy
    context = rclpy.Context()
    rclpy.init(args=["check", "--ros-args", "--params-file", str(path)], context=context)
    rclpy.shutdown(context=context)


@pytest.mark.parametrize("name", ["rig.launch.py", "identification.launch.py"])
def test_the_rig_launches_manage_the_lifecycle_drivers(name):
    """The launches configure the managed drivers (and activate only the bridge: the motors wait for
    the operator); the nodes they manage are the ones that are lifecycle nodes."""
    from soft_arm_drivers.can.motor_driver_node import MotorDriverNode
    from soft_arm_drivers.mocap.mocap_bridge_node import MocapBridgeNode
    from soft_arm_ros.lifecycle import ManagedHardwareNode
    tree = ast.parse((ROOT / "launch" / name).read_text())
    managed = _constant(tree, "MANAGED")
    assert managed == {"motor_driver": "inactive", "mocap_bridge": "active"}
    assert set(managed) <= set(_constant(tree, "NODES"))
    for cls in (MotorDriverNode, MocapBridgeNode):
        assert issubclass(cls, ManagedHardwareNode)


def test_the_identification_launch_lets_the_excitation_command_the_motors():
    """The motor driver takes commands from one node: there, the excitation, not the inner loop."""
    tree = ast.parse((ROOT / "launch" / "identification.launch.py").read_text())
    own = _constant(tree, "OWN")
    assert own["motor_driver"]["rig.motors.command_publisher"] == "/excitation"
    assert "excitation" in _constant(tree, "NODES") and "inner_loop" not in _constant(tree, "NODES")
