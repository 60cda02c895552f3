"""Sphinx extension: the benchmark page, rendered from what the bench scripts wrote.

Every bench script writes ``bench/results/<name>.json`` with when (UTC), on what machine and at
which commit it was measured (``bench/timing.py``). At ``builder-inited`` this writes
``docs/benchmarks/generated.md``: per results file, that header and its figures as tables (nested
mappings flattened to dotted keys, lists of records as tables), and, for a campaign's folder
(``bench/results/campaigns/*/``: ``summary.json``, ``summary.md`` and the plots), its summary
tables and histograms. A results file that is not JSON, or lacks its header, stops the build.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from sphinx.errors import ExtensionError

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "bench" / "results"
PAGE = Path(__file__).resolve().parents[1] / "benchmarks" / "generated.md"
MAX_ROWS = 60            # rows of one table before the rest is left to the JSON file


def _fmt(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    if value is None:
        return "-"
    return str(value).replace("|", "\\|").replace("\n", " ")


def _scalar(value) -> bool:
    return value is None or isinstance(value, (bool, int, float, str))


def _flatten(tree, prefix="") -> tuple[list, list]:
    """(dotted key, value) of the scalar leaves, and (dotted key, list of records) of the tables."""
    leaves, tables = [], []
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            inner_leaves, inner_tables = _flatten(value, name + ".")
            leaves += inner_leaves
            tables += inner_tables
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            tables.append((name, value))
        elif isinstance(value, list) and all(_scalar(v) for v in value) and len(value) <= 12:
            leaves.append((name, "[" + ", ".join(_fmt(v) for v in value) + "]"))
        elif _scalar(value):
            leaves.append((name, _fmt(value)))
    return leaves, tables


def _records_table(name, records) -> list:
    columns = [k for k, v in records[0].items() if _scalar(v)]
    if not columns:
        return []
    out = [f"**{name}** ({len(records)} records)", "", "| " + " | ".join(columns) + " |",
           "|" + "---|" * len(columns)]
    for record in records[:MAX_ROWS]:
        out.append("| " + " | ".join(_fmt(record.get(c)) for c in columns) + " |")
    if len(records) > MAX_ROWS:
        out.append(f"| ... {len(records) - MAX_ROWS} more in the JSON file | " + " | " * (len(columns) - 1))
    return out + [""]


def _section(path: Path) -> list:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ExtensionError(f"{path}: not a results file: {exc}") from None
    measured = data.pop("measured", None)
    if not isinstance(measured, dict) or not {"date", "commit", "machine"} <= set(measured):
        raise ExtensionError(f"{path}: no 'measured' header (date, commit, machine): write it with "
                             "bench/timing.py's write_results")
    machine = measured["machine"]
    out = [f"## {path.stem}", "",
           f"Measured {measured['date']} at commit `{measured['commit']}` on {machine.get('cpus')} "
           f"x {machine.get('cpu')}, Python {machine.get('python')}. File: "
           f"`{path.relative_to(ROOT)}`.", ""]
    leaves, tables = _flatten(data)
    if leaves:
        out += ["| figure | value |", "|---|---|"] + [f"| `{k}` | {v} |" for k, v in leaves[:4 * MAX_ROWS]]
        out.append("")
    for name, records in tables:
        out += _records_table(name, records)
    return out


def _campaigns(page_dir: Path) -> list:
    """Per campaign folder: its header (from ``summary.json``), its summary tables (``summary.md`` up
    to the per-run table, which stays in the folder) and its histograms."""
    out = []
    for summary in sorted((RESULTS / "campaigns").glob("*/summary.json")):
        header = [f"## Campaign `{summary.parent.name}`"] + _section(summary)[1:4]
        tables = (summary.parent / "summary.md").read_text(encoding="utf-8").partition("\n## Runs")[0]
        lines = tables.splitlines()[1:]                # its title is the section's
        out += header + [("#" + line) if line.startswith("#") else line for line in lines] + [""]
        for image in sorted(summary.parent.glob("*.png")):
            target = page_dir / "images" / f"{summary.parent.name}-{image.name}"
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(image, target)
            out += [f"![{image.stem}](images/{target.name})", ""]
    return out


def generate(app):
    PAGE.parent.mkdir(parents=True, exist_ok=True)
    out = ["# Results", "",
           "What the bench scripts measured last, file by file (`bench/results/`), with when, where and at "
           "which commit. Rerun a script to refresh its file; the page is rebuilt with the docs.", ""]
    files = sorted(RESULTS.glob("*.json"))
    if not files:
        out += ["No results yet: run the bench scripts (see [](index.md)).", ""]
    for path in files:
        out += _section(path)
    out += _campaigns(PAGE.parent)
    text = "\n".join(out) + "\n"
    if not PAGE.exists() or PAGE.read_text(encoding="utf-8") != text:
        PAGE.write_text(text, encoding="utf-8")


def setup(app):
    app.connect("builder-inited", generate)
    return {"version": "1", "parallel_read_safe": True}
