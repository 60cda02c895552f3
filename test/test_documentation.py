"""The generated reference covers what the code declares: every schema of the packages is rendered,
every key with a description of what it allows; a key without one stops the page. The measured
figures the pages quote are the results files' (the ``{bench}`` role), and so is the README's
sample output."""
import ast
import importlib
import json
import pkgutil
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))

import soft_arm_reference  # noqa: E402
from soft_arm_benchmarks import figure  # noqa: E402

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


def _results(tmp_path):
    (tmp_path / "bench.json").write_text(json.dumps({
        "measured": {"date": "d", "commit": "c", "machine": {}},
        "steps": {"update_us": 7.2194, "rms_m": 0.000399},
        "runs": [{"task": "coiling", "feedback": "fused", "dt": 0.001, "loop": "core, sleep", "rms": 0.35},
                 {"task": "triangle", "feedback": "estimate", "dt": 0.002, "loop": "node", "rms": 0.47,
                  "spec": {"draw": 3}}],
        "draws": [{"rest": [0.1, 0.0008], "mm": 0.21}, {"rest": [0.2, 0.0026], "mm": None},
                  {"rest": [0.3, 0.0011], "mm": 0.27}]}), encoding="utf-8")
    return tmp_path


@pytest.mark.parametrize("spec, text", [
    ("bench.json:steps.update_us:.1f", "7.2"),                      # a number, formatted
    ("bench.json:steps.rms_m*1000:.2f", "0.40"),                    # scaled (m to mm)
    ("bench.json:steps.update_us", "7.22"),                         # .3g when no format
    ("bench.json:draws.*.rest.-1*1000:.1f", "0.8-2.6"),             # every draw: their range
    ("bench.json:draws.*.mm:.2f", "0.21-0.27"),                     # the nulls left out
    ("bench.json:draws.1.rest.0:.1f", "0.2"),                       # list indices
    ("bench.json:draws.*.rest.0*0:.1f", "0.0"),                     # one value where they agree
    ("bench.json:draws.*.rest.0*-1:.1f", "-0.3--0.1"),              # a negative factor
    ("bench.json:runs.[task=coiling;feedback=fused].rms:.2f", "0.35"),     # records, every condition
    ("bench.json:runs.[feedback=fused|estimate].rms:.2f", "0.35-0.47"),   # alternatives
    ("bench.json:runs.[feedback=fused|estimate].rms:.2f:max", "0.47"),    # the largest alone
    ("bench.json:runs.*.rms*-1::min", "-0.47"),                     # the smallest, default format
    ("bench.json:runs.[spec.draw=3].rms:.2f", "0.47"),              # a field of a field
    ("bench.json:runs.[dt=0.002].rms:.2f", "0.47"),                 # a dot inside the filter
    ("bench.json:runs[dt=0.002;feedback=estimate].rms:.2f", "0.47"),      # no dot before it
    ("bench.json:runs.[loop=core, sleep].rms:.2f", "0.35")])       # text with a comma and a space
def test_a_bench_figure_is_the_results_files_number_scaled_ranged_or_filtered(tmp_path, spec, text):
    assert figure(spec, _results(tmp_path)) == text


@pytest.mark.parametrize("spec, says", [
    ("bench.json:steps.missing", "no 'steps.missing'"), ("other.json:steps.rms_m", "No such file"),
    ("bench.json:steps", "not a number"), ("bench.json:draws.5.mm", "no 'draws.5'"),
    ("bench.json:draws.1.mm", "not a number"), ("bench.json steps.rms_m", "not file.json:"),
    ("bench.json:steps.rms_m:.2q", "Unknown format code"),
    ("../bench.json:steps.rms_m", "under bench/results"),
    ("bench.json:runs.[task=pendulum].rms", "no record 'runs.[task=pendulum]'")])
def test_a_bench_figure_that_is_not_there_says_which_and_why(tmp_path, spec, says):
    with pytest.raises(ValueError, match=re.escape(says)) as caught:
        figure(spec, _results(tmp_path))
    assert repr(spec) in str(caught.value)


@pytest.mark.parametrize("page", ["README.md", "docs/getting-started.md"])
def test_the_main_commands_sample_output_is_what_its_bench_measured_last(page):
    """The Table 1 row the README shows ``soft-arm-experiment triangle`` printing is the row
    ``bench/bench_graph.py`` measured last on the same command (``graph.json``), as the command's
    own formatter prints it."""
    from soft_arm_experiments.metrics import Summary, format_table
    row = json.loads((ROOT / "bench/results/graph.json").read_text(encoding="utf-8"))["triangle"]["graph"]
    printed = format_table([], Summary(**row)).split("\n\n", 1)[1].splitlines()
    shown = (ROOT / page).read_text(encoding="utf-8")
    assert [line for line in printed if line not in shown] == []
