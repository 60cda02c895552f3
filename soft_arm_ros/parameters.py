"""A node's parameters: the package's ``config/<namespace>.yaml`` overlaid with what the node was
given (``--params-file``, ``-p``), validated like every other config file.

A node reads only the namespaces it needs (:meth:`NodeParameters.section`): the controller's nodes
never read the simulated plant's file. A bad value raises ConfigError naming ``namespace.key``, the
value and the allowed range; :func:`~soft_arm_ros.runtime.run_node` logs it and exits with status 2.
"""
from __future__ import annotations

import json
import os
from functools import cached_property
from typing import Mapping

from soft_arm_model.config import ArmConfig, load_arm_config
from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

GRAPH_SCHEMA = {
    "task": ("str", lambda v: bool(v), "a task name of tasks.yaml"),
    "simulator.mode": ("str", lambda v: v in ("lockstep", "realtime"), "lockstep or realtime"),
    "simulator.command_timeout": ("float", lambda v: 0 < v <= 10,
                                  "a time in (0, 10] s after which a command is stale"),
    "simulator.shape_rate": ("float", lambda v: 0 <= v <= 1000, "a rate in [0, 1000] Hz (0: off)"),
    "recorder.topics": ("strs", lambda v: len(v) >= 1, "one or more topic names"),
    "recorder.chunk_size": ("int", lambda v: 1024 <= v <= 1 << 30, "a size in [1 KiB, 1 GiB] bytes"),
    "recorder.flush_period": ("float", lambda v: 0 < v <= 3600, "a period in (0, 3600] s"),
}


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


class NodeParameters:
    """The validated parameters of one node: ``section(namespace, schema)`` for any namespace of the
    package's files (``config/<namespace>.yaml``, top-level key ``namespace``), ``arm`` (the arm
    description) and ``graph`` (``config/graph.yaml``), each overlaid with the node's own values."""

    def __init__(self, node, config_dir: str | None = None):
        self.node = node
        self.config_dir = config_dir or default_config_dir()

    def overrides(self, namespace: str) -> dict:
        """The node's own values under ``namespace`` as dotted overrides."""
        return parameter_overrides(self.node, namespace)

    def section(self, namespace: str, schema: Mapping, filename: str | None = None) -> dict:
        """Validated values (dotted key -> value) of ``namespace`` from ``filename`` (default:
        ``<first element of namespace>.yaml``) in the config directory."""
        name = filename or namespace.split(".")[0] + ".yaml"
        return load_section(os.path.join(self.config_dir, name), namespace, schema,
                            self.overrides(namespace))

    @cached_property
    def arm(self) -> ArmConfig:
        return load_arm_config(os.path.join(self.config_dir, "arm.yaml"), self.overrides("arm"))

    @cached_property
    def graph(self) -> dict:
        return self.section("graph", GRAPH_SCHEMA)

    def task_name(self, known) -> str:
        """``graph.task``, checked against the ``known`` task names."""
        name = self.graph["task"]
        if name not in known:
            raise ConfigError(f"graph.task = {name!r} is not valid: expected one of {sorted(known)}")
        return name
