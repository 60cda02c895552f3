"""The generated reference covers what the code declares: every schema of the packages is rendered,
every key with a description of what it allows; a key without one stops the page."""
import ast
import importlib
import pkgutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))

import soft_arm_reference  # noqa: E402

PACKAGES = ("soft_arm_model", "soft_arm_ros", "soft_arm_control", "soft_arm_drivers", "soft_arm_experiments")


def _schemas_in_the_code() -> set:
    """module:name of every module-level schema (a dict named *SCHEMA of (kind, check, allowed))."""
    found = set()
    for package in PACKAGES:
        for info in pkgutil.walk_packages(importlib.import_module(package).__path__, package + "."):
            module = importlib.import_module(info.name)
            for name, value in vars(module).items():
                if name.endswith("SCHEMA") and isinstance(value, dict) \
                        and all(isinstance(v, tuple) and len(v) == 3 for v in value.values()):
                    if _defined_here(module, name):
                        found.add(f"{info.name}:{name}")
    return found


def _defined_here(module, name) -> bool:
    """The schema is assigned in ``module`` itself (not imported from another)."""
    source = Path(module.__file__).read_text(encoding="utf-8")
    return f"\n{name} = " in source or f"\n{name}: " in source


def test_every_schema_of_the_code_is_in_the_reference():
    documented = {location for _, location, _, _ in soft_arm_reference.SCHEMAS}
    assert _schemas_in_the_code() == documented


def test_every_key_is_rendered_with_what_it_allows():
    """Each key's row of the parameters page holds its own kind and what it allows, beside it."""
    rows = {line.split(" | ")[0]: line for line in soft_arm_reference.parameters_page().splitlines()
            if line.startswith("| `")}
    for namespace, location, _, _ in soft_arm_reference.SCHEMAS:
        for key, (kind, _, allowed) in soft_arm_reference._load(location).items():
            name = f"{namespace}.{key}" if namespace else key
            row = rows.get(f"| `{name}`")
            assert row is not None, name
            expected = f"| `{name}` | {kind} | {soft_arm_reference._cell(allowed)} | "
            assert row.startswith(expected), (name, row)


def test_a_key_without_a_description_stops_the_reference(monkeypatch):
    from soft_arm_ros import parameters
    monkeypatch.setitem(parameters.GRAPH_SCHEMA, "recorder.undocumented", ("float", None, ""))
    with pytest.raises(Exception, match="graph.recorder.undocumented has no description"):
        soft_arm_reference.parameters_page()


def test_every_command_of_the_package_is_documented():
    tree = ast.parse((ROOT / "setup.py").read_text(encoding="utf-8"))
    scripts = {node.value.partition(" = ")[0] for node in ast.walk(tree)
               if isinstance(node, ast.Constant) and isinstance(node.value, str)
               and node.value.startswith("soft-arm-") and " = " in node.value}
    assert scripts and scripts == {name for name, _, _ in soft_arm_reference.COMMANDS}


def test_every_command_has_its_help():
    page = soft_arm_reference.cli_page()
    for name, _, subcommands in soft_arm_reference.COMMANDS:
        assert f"## `{name}`" in page
        for sub in subcommands:
            assert f"### `{name} {sub}`" in page
    assert page.count("usage:") >= len(soft_arm_reference.COMMANDS)
