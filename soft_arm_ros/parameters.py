"""A node's parameters: the package's ``config/<namespace>.yaml`` overlaid with what the node was
given (``--params-file``, ``-p``), validated like every other config file.

A node reads only the namespaces it needs (:meth:`NodeParameters.section`): the controller's nodes
never read the simulated plant's file. A bad value raises ConfigError naming ``namespace.key``, the
value and the allowed range; :func:`~soft_arm_ros.runtime.run_node` logs it and exits with status 2.

Every value a node reads is declared as a ROS parameter with its value in use and a
``ParameterDescriptor``: the schema's text of what is allowed as its description, the interval
that text states as its range (scalars), and ``read_only`` unless the node applies a change while
it runs (``live``). ``ros2 param set`` on a read-only value is refused by rclpy; on a live one the
value is checked like the file's (refused with the key, the value and what is allowed) and handed
to the node's ``apply`` (:meth:`NodeParameters.on_change`), which may refuse it too (a ValueError or
ConfigError: its message is the reason); only then does the parameter change.
"""
from __future__ import annotations

import array
import json
import os
from functools import cached_property
from typing import Callable, Iterable, Mapping

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter

from soft_arm_model.config import ARM_SCHEMA, ArmConfig, load_arm_config
from soft_arm_model.parameters import (ConfigError, allowed_interval, check_value, default_config_dir,
                                       load_section, schema_entry)

ROS_TYPES = {"float": Parameter.Type.DOUBLE, "int": Parameter.Type.INTEGER, "bool": Parameter.Type.BOOL,
             "str": Parameter.Type.STRING, "floats": Parameter.Type.DOUBLE_ARRAY,
             "ints": Parameter.Type.INTEGER_ARRAY, "strs": Parameter.Type.STRING_ARRAY,
             "bools": Parameter.Type.BOOL_ARRAY}

GRAPH_SCHEMA = {
    "task": ("str", lambda v: bool(v), "a task name of tasks.yaml"),
    "simulator.mode": ("str", lambda v: v in ("lockstep", "realtime"), "lockstep or realtime"),
    "simulator.command_timeout": ("float", lambda v: 0 < v <= 10,
                                  "a time in (0, 10] s after which a command is stale"),
    "simulator.max_real_time_factor": ("float", lambda v: 0 <= v <= 1000,
                                       "a factor in [0, 1000] (0: as fast as the graph answers)"),
    "simulator.shape_rate": ("float", lambda v: 0 <= v <= 1000, "a rate in [0, 1000] Hz (0: off)"),
    "recorder.topics": ("strs", lambda v: len(v) >= 1, "one or more topic names"),
    "recorder.chunk_size": ("int", lambda v: 1024 <= v <= 1 << 30, "a size in [1 KiB, 1 GiB] bytes"),
    "recorder.flush_period": ("float", lambda v: 0 < v <= 3600, "a period in (0, 3600] s"),
    "recorder.discovery_period": ("float", lambda v: 0 < v <= 10, "a period in (0, 10] s"),
    "recorder.take_period": ("float", lambda v: 0 < v <= 0.5, "a period in (0, 0.5] s"),
}


# A run's own options, given to a node on its command line (``-p output:=...``), not in a config file.
RUN_SCHEMA = {
    "output": ("str", None, "a path the node writes its result to: the bag directory (recorder), the "
                            "metrics file (task_runner) or the schedule file (excitation); empty: the "
                            "recorder's runs/bag-<time>, the others none"),
    "wait_for_start": ("bool", None, "true: the task or schedule begins at a call of ~/start (on the "
                                     "rig, once the motors are enabled); false: with the first message"),
}
_RUN_DEFAULTS = {"output": "", "wait_for_start": False}


def parameter_overrides(node, prefix: str) -> dict:
    """The node's parameters under ``prefix`` (from --params-file / -p) as dotted overrides relative
    to it. ROS has typed the values already: strings are passed quoted, so that the overrides' YAML
    reading keeps "4.1" or "yes" a string; arrays become lists."""
    out = {}
    for key, param in node.get_parameters_by_prefix(prefix).items():
        value = param.value
        if isinstance(value, str):
            value = json.dumps(value)
        elif isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
            value = list(value)
        out[key] = value
    return out


def descriptor(name: str, kind: str, allowed: str, read_only: bool) -> ParameterDescriptor:
    """The descriptor of a schema entry: its type, what is allowed as description, the interval the
    text states as range (float and int scalars; an open end is refused by the check, not by rclpy)."""
    out = ParameterDescriptor(name=name, type=ROS_TYPES[kind].value, description=f"expected {allowed}",
                              read_only=read_only)
    interval = allowed_interval(allowed)
    if interval is not None and kind == "float":
        out.floating_point_range = [FloatingPointRange(from_value=interval[0], to_value=interval[1],
                                                       step=0.0)]
    elif interval is not None and kind == "int":
        out.integer_range = [IntegerRange(from_value=int(interval[0]), to_value=int(interval[1]), step=1)]
    return out


def ros_value(kind: str, value):
    """``value`` as the value of a ROS parameter of ``kind``, or None when rclpy cannot declare it
    as one (a list of lists; an empty list, whose element type rclpy cannot tell)."""
    if kind in ("floats", "ints", "strs"):
        value = list(value)
        if not value or any(isinstance(v, (list, tuple)) for v in value):
            return None
    return value


class NodeParameters:
    """The validated parameters of one node: ``section(namespace, schema)`` for any namespace of the
    package's files (``config/<namespace>.yaml``, top-level key ``namespace``), ``arm`` (the arm
    description) and ``graph`` (``config/graph.yaml``), each overlaid with the node's own values and
    declared with descriptors (module docstring). ``live``: the full names (``control.inner_loop.
    proportional``) the node applies while it runs, through the function given to :meth:`on_change`."""

    def __init__(self, node, config_dir: str | None = None, live: Iterable[str] = ()):
        self.node = node
        self.config_dir = config_dir or default_config_dir()
        self.live = frozenset(live)
        self._described: dict = {}          # full name -> (namespace, key, schema)
        self._apply: Callable | None = None
        node.add_on_set_parameters_callback(self._on_set)

    def on_change(self, apply: Callable[[dict], None]):
        """``apply(changes)`` is called with the checked values of live parameters being set (full
        name -> value) before they change; it raises ValueError or ConfigError to refuse them."""
        self._apply = apply

    def describe(self, namespace: str, schema: Mapping, values: Mapping):
        """Declare (or give a descriptor to) every value of ``namespace`` (dotted key -> value in
        use) that ROS can hold, read-only unless live."""
        for key, value in values.items():
            name = f"{namespace}.{key}"
            entry = schema_entry(schema, key)
            if name in self._described or entry is None or (
                    self.node.has_parameter(name) and self.node.describe_parameter(name).read_only):
                continue                                 # described already (by another reader)
            kind, _, allowed = entry
            ros = ros_value(kind, value)
            if ros is None:
                continue
            d = descriptor(name, kind, allowed, read_only=name not in self.live)
            if self.node.has_parameter(name):          # given as an override: keep the value in use
                self.node.set_descriptor(name, d, alternative_value=Parameter(
                    name, ROS_TYPES[kind], ros).get_parameter_value())
            else:
                self.node.declare_parameter(name, ros, d)
            self._described[name] = (namespace, key, schema)    # from now on a set is checked

    def _on_set(self, parameters) -> SetParametersResult:
        changes = {}
        for p in parameters:
            if p.name not in self._described:
                continue                                 # rclpy's own (use_sim_time) and the rest
            namespace, key, schema = self._described[p.name]
            value = list(p.value) if isinstance(p.value, (array.array, tuple)) else p.value
            try:
                changes[p.name] = check_value(schema, namespace, key, value)
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        if changes:
            if self._apply is None:
                return SetParametersResult(successful=False,
                                           reason=f"{sorted(changes)}: not applied while the node runs")
            try:
                self._apply(changes)
            except (ValueError, ConfigError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def run_option(self, key: str):
        """The run option ``key`` (:data:`RUN_SCHEMA`) the node was given, or its default; declared
        read-only with its description. ConfigError for a value of the wrong kind."""
        kind, _, allowed = RUN_SCHEMA[key]
        value = self.node.get_parameter(key).value if self.node.has_parameter(key) else _RUN_DEFAULTS[key]
        if not isinstance(value, type(_RUN_DEFAULTS[key])):
            raise ConfigError(f"{key} = {value!r} is not valid: expected {allowed}")
        d = descriptor(key, kind, allowed, read_only=True)
        if self.node.has_parameter(key):
            self.node.set_descriptor(key, d, alternative_value=Parameter(key, ROS_TYPES[kind], value)
                                     .get_parameter_value())
        else:
            self.node.declare_parameter(key, value, d)
        return value

    def overrides(self, namespace: str) -> dict:
        """The node's own values under ``namespace`` as dotted overrides; ConfigError when the node
        was given a value where the namespace's keys belong (``-p arm:=5``)."""
        parts = namespace.split(".")
        for prefix in (".".join(parts[:k]) for k in range(1, len(parts) + 1)):
            if self.node.has_parameter(prefix):
                raise ConfigError(f"{prefix} = {self.node.get_parameter(prefix).value!r} is not valid: "
                                  f"expected the {prefix}.* parameters, not a value")
        return parameter_overrides(self.node, namespace)

    def section(self, namespace: str, schema: Mapping, filename: str | None = None,
                defaults: Mapping | None = None) -> dict:
        """Validated values (dotted key -> value) of ``namespace`` from ``filename`` (default:
        ``<first element of namespace>.yaml``) in the config directory; ``defaults``: dotted values
        relative to ``namespace`` laid over the file beneath the node's own."""
        name = filename or namespace.split(".")[0] + ".yaml"
        values = load_section(os.path.join(self.config_dir, name), namespace, schema,
                              {**(defaults or {}), **self.overrides(namespace)})
        self.describe(namespace, schema, values)
        return values

    @cached_property
    def arm(self) -> ArmConfig:
        path = os.path.join(self.config_dir, "arm.yaml")
        self.describe("arm", ARM_SCHEMA, load_section(path, "arm", ARM_SCHEMA, self.overrides("arm")))
        return load_arm_config(path, self.overrides("arm"))

    @cached_property
    def graph(self) -> dict:
        return self.section("graph", GRAPH_SCHEMA)

    def task_name(self, known) -> str:
        """``graph.task``, checked against the ``known`` task names."""
        name = self.graph["task"]
        if name not in known:
            raise ConfigError(f"graph.task = {name!r} is not valid: expected one of {sorted(known)}")
        return name
