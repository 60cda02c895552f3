"""soft_arm_interfaces: the installed messages are the package's (built from its .msg files, with the
fields the code writes), cross between rclpy processes, are recorded with their definitions and read
back by rosbags and mcap with the values sent; the PyPI build step is idempotent and fails clearly."""
import importlib.util
import pathlib
import shutil
import subprocess
import sys
import textwrap

import pytest
import rclpy
from mcap.reader import make_reader
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from rosbags.typesys import get_types_from_msg
from soft_arm_interfaces.msg import ConfigurationReference, TaskGoal

from conftest import killed_on_exit, spin_until, wait_for_output
from soft_arm_control.outer_loop import MODES
from soft_arm_experiments.figures import read_series
from soft_arm_drivers.recording.message_definitions import message_definition, type_description_hash
from soft_arm_drivers.recording.recorder_node import RecorderNode
from soft_arm_ros.contract import QOS, TOPICS, TYPES
from soft_arm_ros.conversions import configuration_reference, goal_of, task_goal

ROOT = pathlib.Path(__file__).resolve().parents[2]
SOURCE = ROOT / "soft_arm_interfaces"
SCHEMA = {
    TaskGoal: {"header": "std_msgs/Header", "mode": "string", "phase": "string", "window": "double",
               "labels": "sequence<string>", "target": "sequence<double>"},
    ConfigurationReference: {"header": "std_msgs/Header", "goal": "uint32", "mode": "string",
                             "q_d": "sequence<double>", "labels": "sequence<string>",
                             "target": "sequence<double>", "x_model": "sequence<double>"},
}
LABELS = ["marker4.x", "marker4.z"]


def _goal():
    return task_goal(12.5, [0.01, -0.3], TaskGoal.MODE_TRACK, "circle", 5.0, LABELS)


def _reference():
    return configuration_reference(12.75, 3, TaskGoal.MODE_CLIK, [0.1, -0.2, 0.3], LABELS,
                                   [0.01, -0.3], [0.011, -0.299])


def _build_module():
    spec = importlib.util.spec_from_file_location("build_pypi", SOURCE / "build_pypi.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _fields(msg) -> dict:
    return {name: getattr(msg, name) for name in msg.get_fields_and_field_types()}


def _equal_value(a, b) -> bool:
    """Field values equal, a sequence (list, array.array, numpy array) element by element."""
    return list(a) == list(b) if hasattr(a, "__len__") and not isinstance(a, str) else a == b


# -- the schema -----------------------------------------------------------------------------------
def test_the_installed_messages_are_built_from_the_package_and_have_the_schema_the_code_writes():
    build = _build_module()
    layout = build._Layout(pathlib.Path(sys.prefix), "soft_arm_interfaces")
    assert build._up_to_date(layout, build._digest(SOURCE, sorted((SOURCE / "msg").glob("*.msg")))), \
        "soft_arm_interfaces/ changed since it was built: python soft_arm_interfaces/build_pypi.py"
    for cls, schema in SCHEMA.items():
        assert cls.get_fields_and_field_types() == schema, cls.__name__
        # the .msg text as the recorder stores it (and rosbags parses it) has the same fields
        type_name = f"soft_arm_interfaces/msg/{cls.__name__}"
        parsed = get_types_from_msg(message_definition(type_name), type_name)[type_name][1]
        assert [name for name, _ in parsed] == list(schema)
        assert type_description_hash(type_name).startswith("RIHS01_")
    assert TYPES["task/goal"] == "soft_arm_interfaces/msg/TaskGoal"
    assert TYPES["arm/configuration_reference"] == "soft_arm_interfaces/msg/ConfigurationReference"
    # the goal modes the message documents are the clik node's
    assert sorted(getattr(TaskGoal, f"MODE_{m.upper()}") for m in MODES) == sorted(MODES)
    # the code fills every field (none is left at its default)
    for msg in (_goal(), _reference()):
        empty = type(msg)()
        unset = [name for name, value in _fields(msg).items() if _equal_value(value, getattr(empty, name))]
        assert not unset, (type(msg).__name__, unset)


def test_a_goal_is_read_by_its_labels_in_arm_base():
    goal = _goal()
    target, mode, phase = goal_of(goal, LABELS)
    assert target.tolist() == [0.01, -0.3] and (mode, phase) == ("track", "circle")
    assert goal_of(goal, LABELS[::-1])[0].tolist() == [-0.3, 0.01]          # reordered by label
    assert goal_of(TaskGoal(target=[1.0, 2.0]), LABELS)[1] == "clik"         # no labels, no mode
    with pytest.raises(ValueError, match="marker4.x, marker3.z"):
        goal_of(goal, ["marker4.x", "marker3.z"])
    goal.header.frame_id = "world"
    with pytest.raises(ValueError, match="arm_base"):
        goal_of(goal, LABELS)


# -- across processes ---------------------------------------------------------------------------------
PUBLISHER = textwrap.dedent("""
    import sys
    import rclpy
    from soft_arm_interfaces.msg import TaskGoal
    from soft_arm_ros.contract import QOS, TOPICS
    from soft_arm_ros.conversions import task_goal
    rclpy.init()
    node = rclpy.create_node("goal_publisher")
    pub = node.create_publisher(TaskGoal, TOPICS["goal"], QOS["task/goal"])
    pub.publish(task_goal(12.5, [0.01, -0.3], "track", "circle", 5.0, ["marker4.x", "marker4.z"]))
    print("published", flush=True)
    sys.stdin.read()                    # until the test is done
    node.destroy_node()
    rclpy.shutdown()
""")


def test_a_goal_published_by_one_process_is_received_by_another(context):
    proc = subprocess.Popen([sys.executable, "-c", PUBLISHER], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with killed_on_exit(proc):
        wait_for_output(proc, "published")
        node = rclpy.create_node("goal_subscriber", context=context)
        received = []
        node.create_subscription(TaskGoal, TOPICS["goal"], received.append, QOS["task/goal"])
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            spin_until(executor, lambda: received, timeout=20.0)      # latched: sent before we joined
        finally:
            executor.shutdown()
            node.destroy_node()
        proc.stdin.close()
        proc.wait(timeout=20)
    assert proc.returncode == 0
    assert received[0] == _goal() and received[0].header.stamp.sec == 12


# -- recorded and read back -----------------------------------------------------------------------------
def test_a_recorded_bag_reads_back_with_rosbags_and_mcap(context, tmp_path):
    bag = tmp_path / "bag"
    publisher = rclpy.create_node("typed_publisher", context=context)
    goals = publisher.create_publisher(TaskGoal, TOPICS["goal"], QOS["task/goal"])
    references = publisher.create_publisher(ConfigurationReference, TOPICS["configuration"],
                                            QOS["arm/configuration_reference"])
    recorder = RecorderNode(context=context, parameter_overrides=[
        Parameter("output", value=str(bag)),
        Parameter("graph.recorder.topics", value=["task/goal", "arm/configuration_reference"]),
        Parameter("graph.recorder.flush_period", value=0.2)])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(recorder)
    executor.add_node(publisher)
    sent = {"/task/goal": _goal(), "/arm/configuration_reference": _reference()}
    try:
        spin_until(executor, lambda: goals.get_subscription_count() and references.get_subscription_count())
        goals.publish(sent["/task/goal"])
        references.publish(sent["/arm/configuration_reference"])
        spin_until(executor, lambda: recorder.count >= 2)
    finally:
        executor.shutdown()
        recorder.close()
        recorder.destroy_node()
        publisher.destroy_node()
    # rosbags, as the figures and soft-arm-identify read bags (types registered from the bag)
    series = read_series(str(bag))
    for topic, msg in sent.items():
        (stamp, read), = series[topic[1:]]
        assert stamp == pytest.approx(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
        for name, value in _fields(msg).items():
            if name != "header":
                assert _equal_value(getattr(read, name), value), (topic, name)
        assert read.header.frame_id == "arm_base"
    # mcap: each channel's schema is the type's definition, each message decodes to what was sent
    with open(bag / "bag_0.mcap", "rb") as fh:
        records = list(make_reader(fh).iter_messages())
    assert len(records) == 2
    for schema, channel, message in records:
        cls = type(sent[channel.topic])
        assert schema.name == f"soft_arm_interfaces/msg/{cls.__name__}" and schema.encoding == "ros2msg"
        assert schema.data.decode() == message_definition(schema.name)
        assert deserialize_message(message.data, cls) == sent[channel.topic]


# -- the build step -------------------------------------------------------------------------------------
def test_the_build_step_is_idempotent_and_rebuilds_what_changed(tmp_path):
    build = _build_module()
    source = tmp_path / "src"
    shutil.copytree(SOURCE, source, ignore=shutil.ignore_patterns("__pycache__"))
    prefix = tmp_path / "prefix"
    first = build.build(prefix, source=source)
    assert first["built"]
    files = {f: (prefix / f).stat().st_mtime_ns for f in first["files"]}
    assert "lib/libsoft_arm_interfaces__rosidl_typesupport_fastrtps_c.so" in files
    assert any(f.endswith("soft_arm_interfaces/msg/_task_goal.py") for f in files)
    assert "share/soft_arm_interfaces/msg/TaskGoal.msg" in files
    again = build.build(prefix, source=source)
    assert not again["built"] and again["files"] == first["files"]
    assert {f: (prefix / f).stat().st_mtime_ns for f in files} == files       # nothing rewritten
    # a message changed: built again; a broken one: refused, saying which step and why
    goal = source / "msg" / "TaskGoal.msg"
    goal.write_text(goal.read_text() + "\n# a comment\n")
    assert build.build(prefix, source=source)["built"]
    goal.write_text(goal.read_text() + "float64 bad field\n")
    with pytest.raises(build.BuildError, match="translating the .msg files to .idl failed"):
        build.build(prefix, source=source)
