"""Sphinx extension: the reference pages generated from the code, so that they cannot drift.

At ``builder-inited`` it writes Markdown pages into ``docs/reference/generated/``:

- ``parameters.md``: every parameter of every namespace from its schema (kind, what is allowed,
  the value in ``config/``), the schemas being what every loader validates with;
- ``nodes.md``: every node of the package's console scripts, built for real with rclpy (on
  loopback, a domain of its own) and asked for its publishers, subscriptions, services and
  declared parameters (descriptions, ranges, read-only or live);
- ``cli.md``: every command's ``--help``, from its own argparse parser;
- ``api.md``: the Python API, module by module (autodoc of every module of the four packages).

A parameter without a description, a node that cannot be built from the package's configuration or
a command without help stops the build (a Sphinx error), so an undocumented parameter cannot land.
"""
from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import inspect
import io
import os
import re
import shutil
import tempfile
from pathlib import Path

from sphinx.errors import ExtensionError

GENERATED = Path(__file__).resolve().parents[1] / "reference" / "generated"

# (namespace, schema location, file in config/, prefix of the schema's keys relative to namespace)
SCHEMAS = [
    ("arm", "soft_arm_model.config:ARM_SCHEMA", "arm.yaml", ""),
    ("control", "soft_arm_control.config:CONTROL_SCHEMA", "control.yaml", ""),
    ("tasks", "soft_arm_control.config:TASK_SCHEMA", "tasks.yaml", ""),
    ("plant", "soft_arm_drivers.sim.plant_config:PLANT_SCHEMA", "plant.yaml", ""),
    ("graph", "soft_arm_ros.parameters:GRAPH_SCHEMA", "graph.yaml", ""),
    ("identification", "soft_arm_experiments.excitation:SCHEMA", "identification.yaml", ""),
    ("rig.motors", "soft_arm_drivers.can.driver_config:SCHEMA", "rig.yaml", ""),
    ("rig", "soft_arm_drivers.mocap.bridge_config:MOCAP_SCHEMA", "mocap.yaml", ""),
    ("rig.emulator", "soft_arm_drivers.sim.emulated_rig:SCHEMA", "emulator.yaml", ""),
    ("campaign.tolerances", "soft_arm_experiments.campaigns.plants:SCHEMA", "campaign.yaml", ""),
    ("estimator", "soft_arm_control.shape_estimation:ESTIMATOR_SCHEMA", "estimator.yaml", ""),
    ("view", "soft_arm_experiments.live_view:VIEW_SCHEMA", "view.yaml", ""),
    ("", "soft_arm_ros.parameters:RUN_SCHEMA", None, ""),
]
# nodes that write a file (parameter ``output``): built with one in a scratch folder
WRITERS = ("recorder", "task_runner", "excitation")
# rclpy's own parameters, which every node has
ROS_PARAMETERS = {"use_sim_time", "start_type_description_service"}
# services rclpy gives every node (parameters, type descriptions) and every lifecycle node
STANDARD_SERVICES = ("describe_parameters", "get_parameters", "get_parameter_types", "list_parameters",
                     "set_parameters", "set_parameters_atomically", "get_type_description",
                     "change_state", "get_state", "get_available_states", "get_available_transitions",
                     "get_transition_graph")


def _load(location: str):
    module, _, name = location.partition(":")
    return getattr(importlib.import_module(module), name)


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _value(value) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:g}"
    return f"{value}"


def parameters_page() -> str:
    from soft_arm_model.parameters import default_config_dir, flatten_tree, read_parameters
    config = default_config_dir()
    out = ["# Parameters", "",
           "Every value the nodes and commands read from `config/`, by namespace: the schema each loader "
           "validates with (a value outside what is allowed is refused with the key and this text) and "
           "the value in the package's file. Generated from the schemas.", ""]
    for namespace, location, filename, _ in SCHEMAS:
        schema = _load(location)
        values = {}
        if filename is None:
            out += ["## A run's options (the node's command line, no file)", "",
                    "| key | kind | allowed | in the file |", "|---|---|---|---|"]
        else:
            tree = read_parameters(os.path.join(config, filename))
            for part in namespace.split("."):
                tree = tree.get(part, {}) if isinstance(tree, dict) else {}
            values = flatten_tree(tree) if isinstance(tree, dict) else {}
            out += [f"## `{namespace}` (`config/{filename}`)", "",
                    "| key | kind | allowed | in the file |", "|---|---|---|---|"]
        for key, (kind, _, allowed) in schema.items():
            name = f"{namespace}.{key}" if namespace else key
            if not allowed or len(allowed.strip()) < 4:
                raise ExtensionError(f"{name} has no description of what is allowed")
            shown = "" if key not in values else f"`{_value(values[key])}`"
            out.append(f"| `{name}` | {kind} | {_cell(allowed)} | {_cell(shown)} |")
        out.append("")
    return "\n".join(out)


def _node_classes():
    """(executable name, module, node class) of every node console script of the package."""
    import rclpy.node
    found = []
    for ep in sorted(importlib.metadata.entry_points(group="console_scripts"), key=lambda e: e.name):
        if not ep.value.startswith("soft_arm_") or ep.name.startswith("soft-arm-"):
            continue
        module = importlib.import_module(ep.value.partition(":")[0])
        classes = [c for _, c in inspect.getmembers(module, inspect.isclass)
                   if issubclass(c, rclpy.node.Node) and c.__module__ == module.__name__]
        if len(classes) != 1:
            raise ExtensionError(f"{ep.name}: expected one node class in {module.__name__}, got {classes}")
        found.append((ep.name, module, classes[0]))
    return found


def _qos(profile) -> str:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    reliability = {ReliabilityPolicy.RELIABLE: "reliable", ReliabilityPolicy.BEST_EFFORT: "best effort"}.get(
        profile.reliability, str(profile.reliability))
    durability = ", transient local" if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL else ""
    return f"{reliability}{durability}, depth {profile.depth}"


def _type(msg_type) -> str:
    module = msg_type.__module__.split(".")
    return f"{module[0]}/{module[1]}/{msg_type.__name__}"


def _summary(module) -> str:
    """The first paragraph of a module's docstring, its reST roles as Markdown code."""
    doc = inspect.getdoc(module) or ""
    first = re.sub(r":[a-z]+:`~?\.?([^`]+)`", r"`\1`", doc.split("\n\n")[0].replace("\n", " "))
    if not first:
        raise ExtensionError(f"{module.__name__} has no docstring")
    return first


def nodes_page() -> str:
    import rclpy
    from rclpy.lifecycle import LifecycleNode
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    out = ["# Nodes", "",
           "Every node of the package, as it declares itself when built from the package's "
           "configuration (each is a console script: `ros2 run soft_arm <node>` on a ROS installation). "
           "Topic names are shown resolved in the root namespace; every one but `/clock` and "
           "`/diagnostics` is relative in the code, so a namespace or `-r from:=to` moves it. "
           "Parameters: see [](parameters.md) for what each allows; *live* ones may be set while the node "
           "runs (`ros2 param set`), the others are read-only. Generated by building each node.", ""]
    from rclpy.parameter import Parameter
    context = rclpy.Context()
    rclpy.init(context=context)
    scratch = Path(tempfile.mkdtemp(prefix="soft_arm_reference_"))   # where the nodes' outputs would go
    try:
        for name, module, cls in _node_classes():
            if name == "emulated_rig":
                out += [f"## `{name}`", "", _summary(module), "",
                        "It is the `motor_driver` node (the same name, topics, services and parameters) "
                        "with emulated motors and a Motive server behind its bus; its own parameters are "
                        "`rig.emulator.*` and the `rig.mocap.*` of the emulated server.", ""]
                continue
            outputs = [Parameter("output", value=str(scratch / name))] if name in WRITERS else []
            if name == "live_view":                  # any free port: another view may be running
                outputs = [Parameter("view.port", value=0)]
            node = cls(context=context, parameter_overrides=outputs)
            try:
                out += _node_section(name, module, node, isinstance(node, LifecycleNode))
            finally:
                close = getattr(node, "close", None)
                if close is not None:
                    close()
                node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
        shutil.rmtree(scratch, ignore_errors=True)
    return "\n".join(out)


def _node_section(name, module, node, managed) -> list:
    out = [f"## `{name}`", "", _summary(module), "",
           f"Module `{module.__name__}`" + (" (a managed lifecycle node)" if managed else "") + ".", "",
           "| direction | topic | type | QoS |", "|---|---|---|---|"]
    for pub in node.publishers:
        if pub.topic_name in ("/parameter_events", "/rosout") or pub.topic_name.endswith("/transition_event"):
            continue
        out.append(f"| publishes | `{pub.topic_name}` | {_type(pub.msg_type)} | {_qos(pub.qos_profile)} |")
    for sub in node.subscriptions:
        if sub.topic_name == "/parameter_events":
            continue
        out.append(f"| subscribes | `{sub.topic_name}` | {_type(sub.msg_type)} | {_qos(sub.qos_profile)} |")
    services = [s for s in node.services if s.srv_name.rsplit("/", 1)[-1] not in STANDARD_SERVICES]
    if services:
        out += ["", "Services: " + ", ".join(f"`{s.srv_name}` ({_type(s.srv_type)})" for s in services)
                + "."]
    declared = sorted(n for n in node._parameters if n not in ROS_PARAMETERS)
    namespaces = sorted({n.split(".")[0] if not n.startswith("rig.") else ".".join(n.split(".")[:2])
                         for n in declared})
    live = []
    for n in declared:
        descriptor = node.describe_parameter(n)
        if not descriptor.description:
            raise ExtensionError(f"{name}: parameter {n} has no description")
        if not descriptor.read_only:
            live.append(n)
    out += ["", f"Parameters: {len(declared)}, of the namespaces " + ", ".join(f"`{s}`" for s in namespaces)
            + "." + (" Live: " + ", ".join(f"`{n}`" for n in live) + "." if live else "")]
    out.append("")
    return out


COMMANDS = [
    ("soft-arm-experiment", "soft_arm_experiments.experiment", []),
    ("soft-arm-harness", "soft_arm_experiments.harness_cli", []),
    ("soft-arm-model", "soft_arm_model.cli", ["summary", "equilibrium", "workspace"]),
    ("soft-arm-targets", "soft_arm_control.targets_cli", []),
    ("soft-arm-identify", "soft_arm_experiments.identify_cli", []),
    ("soft-arm-campaign", "soft_arm_experiments.campaigns.cli", ["robustness", "identification", "sweep"]),
    ("soft-arm-warmup", "soft_arm_experiments.warmup", []),
]


def _help(module, argv) -> str:
    main = importlib.import_module(module).main
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.suppress(SystemExit):
        main(argv + ["--help"])
    text = buffer.getvalue().strip()
    if not text:
        raise ExtensionError(f"{module}: {' '.join(argv)} --help printed nothing")
    return text


def cli_page() -> str:
    out = ["# Commands", "",
           "Every command's own `--help` (generated from its argparse parser). Each exits with 2 and one "
           "line naming what is wrong on a bad flag, file or value; with 1 when a run failed; with 130 on "
           "Ctrl-C.", ""]
    installed = {ep.name for ep in importlib.metadata.entry_points(group="console_scripts")}
    for name, module, subcommands in COMMANDS:
        if name not in installed:
            raise ExtensionError(f"{name} is documented but not installed")
        out += [f"## `{name}`", "", "```text", _help(module, []), "```", ""]
        for sub in subcommands:
            out += [f"### `{name} {sub}`", "", "```text", _help(module, [sub]), "```", ""]
    return "\n".join(out)


PACKAGES = (("soft_arm_model", "the model: geometry, kinematics, statics, dynamics, identification"),
            ("soft_arm_control", "the controller: collocated coordinates, P-satI-D+, CLIK, nodes"),
            ("soft_arm_ros", "the ROS plumbing every node shares"),
            ("soft_arm_drivers", "the rig's hardware and its stand-ins: motors, mocap, simulator, recorder"),
            ("soft_arm_experiments", "the lab's work: experiments, identification runs, campaigns"))


def api_page() -> str:
    import pkgutil
    out = ["# Python API", "",
           "Every module of the four packages, from its docstrings (units and frames are given there). "
           "The layering is one way: `soft_arm_model` imports nothing else of the project, "
           "`soft_arm_control` never sees the simulated plant (`test/test_layering.py`).", ""]
    for package, what in PACKAGES:
        module = importlib.import_module(package)
        out += [f"## `{package}`: {what}", ""]
        names = sorted(m.name for m in pkgutil.walk_packages(module.__path__, package + ".")
                       if not m.ispkg)
        for name in names:
            out += [f"### `{name}`", "", "```{eval-rst}", f".. automodule:: {name}", "```", ""]
    return "\n".join(out)


def generate(app):
    GENERATED.mkdir(parents=True, exist_ok=True)
    for filename, make in (("parameters.md", parameters_page), ("nodes.md", nodes_page),
                           ("cli.md", cli_page), ("api.md", api_page)):
        text = make() + "\n"
        path = GENERATED / filename
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")


def setup(app):
    app.connect("builder-inited", generate)
    return {"version": "1", "parallel_read_safe": True}
