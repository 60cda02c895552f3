"""Sphinx extension: the benchmark page, rendered from what the bench scripts wrote.

Every bench script writes ``bench/results/<name>.json`` with when (UTC), on what machine and at
which commit it was measured (``bench/timing.py``). At ``builder-inited`` this writes
``docs/benchmarks/generated.md``: per results file, that header and its figures as tables (nested
mappings flattened to dotted keys, lists of records as tables), and, for a campaign's folder
(``bench/results/campaigns/*/``: ``summary.json``, ``summary.md`` and the plots), its summary
tables and histograms. A results file that is not JSON, or lacks its header, stops the build.

The role ``{bench}`file.json:dotted.key[*factor][:format][:min|max]``` puts one figure of a
results file into a page's prose, so that a page quotes what the scripts measured last, not a copy
of it (see :func:`figure`); the page is read again when the file changes.
"""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

from docutils import nodes
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


_FIGURE = re.compile(r"^(?P<file>[\w/.-]+\.json):(?P<key>[^:]+?)(?:\*(?P<factor>[0-9.eE+-]+))?"
                     r"(?::(?P<format>[^:]*))?(?::(?P<extreme>min|max))?$")


_ABSENT = object()        # a field a record lacks: its text matches no condition's


def _field(record, name: str):
    """A record's field by its dotted name (``spec.task``), or ``_ABSENT``."""
    for part in name.split("."):
        if not isinstance(record, dict) or part not in record:
            return _ABSENT
        record = record[part]
    return record


def _select(tree, keys: list, trail: str) -> list:
    """The values at ``keys`` below ``tree``: a key ``*`` takes every element of a list or value of
    a mapping; ``[name=a|b;other.inner=c]`` the records of a list whose fields (dotted: a field of a
    field) match (as text, one of the alternatives, every condition); an integer indexes a list
    (negative from its end)."""
    if not keys:
        return [tree]
    key, rest = keys[0], keys[1:]
    here = f"{trail}.{key}" if trail else key
    if key == "*" and isinstance(tree, (list, dict)):
        values = tree.values() if isinstance(tree, dict) else tree
        return [v for value in values for v in _select(value, rest, here)]
    if key.startswith("[") and key.endswith("]") and isinstance(tree, list):
        conditions = [c.partition("=") for c in key[1:-1].split(";")]
        records = [r for r in tree if all(str(_field(r, name)) in alternatives.split("|")
                                          for name, _, alternatives in conditions)]
        if not records:
            raise KeyError(f"no record {here!r}")
        return [v for record in records for v in _select(record, rest, here)]
    if isinstance(tree, dict) and key in tree:
        return _select(tree[key], rest, here)
    if isinstance(tree, list) and re.fullmatch(r"-?\d+", key) and -len(tree) <= int(key) < len(tree):
        return _select(tree[int(key)], rest, here)
    raise KeyError(f"no {here!r}")


def _keys(key: str) -> list:
    """The steps of a dotted key: its dot-separated parts, a record filter ``[...]`` one step of its
    own whether a dot comes before it or not (``runs.[method=imex]``, ``runs[method=imex]``), dots
    inside the filter kept (``[dt_s=0.001]``)."""
    return re.findall(r"\[[^\]]*\]|[^.\[]+", key)


def _parse(spec: str) -> re.Match:
    """The parts of a figure's spec; ValueError, naming it, if malformed or outside bench/results."""
    match = _FIGURE.match(spec.strip())
    if match is None:
        raise ValueError(f"{spec!r}: not file.json:dotted.key[*factor][:format][:min|max]")
    if ".." in match["file"].split("/"):
        raise ValueError(f"{spec!r}: a results file is under bench/results")
    return match


def figure(spec: str, results: Path = RESULTS) -> str:
    """The text of one figure of a results file, ``file.json:dotted.key[*factor][:format][:min|max]``:
    the number at that key of ``bench/results/file.json`` (a path below it: a campaign's folder), times
    ``factor`` (units: 1000 for m to mm), formatted by ``format`` (Python's format spec, ``.3g`` if
    none). A key through ``*`` or a record filter (:func:`_select`: every draw, the runs of one
    scenario) reads as the range of its values, ``low-high``, or one value where they agree at that
    format, or its smallest or largest value alone (``:min``, ``:max``); values that are null (a
    figure a draw did not reach) are left out.
    Raises ValueError, naming the spec, for a malformed spec, a missing file or key, or no number."""
    match = _parse(spec)
    path = results / match["file"]
    try:
        tree = json.loads(path.read_text(encoding="utf-8"))
        values = _select(tree, _keys(match["key"]), "")
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{spec!r}: {exc}") from None
    numbers = [v for v in values if v is not None]
    if not numbers or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
        raise ValueError(f"{spec!r}: not a number: {str(values)[:120]}")
    scale = (lambda v: float(match["factor"]) * v) if match["factor"] else (lambda v: v)
    fmt = match["format"] or ".3g"
    try:
        low, high = (format(v, fmt) for v in sorted(scale(v) for v in (min(numbers), max(numbers))))
    except ValueError as exc:
        raise ValueError(f"{spec!r}: {exc}") from None
    if match["extreme"]:
        return low if match["extreme"] == "min" else high
    return low if low == high else f"{low}-{high}"


def _figure_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    try:
        # an incremental build reads the page again when the file changes
        inliner.document.settings.env.note_dependency(str(RESULTS / _parse(text)["file"]))
        return [nodes.Text(figure(text))], []
    except ValueError as exc:
        message = inliner.reporter.error(f"bench figure: {exc}", line=lineno)
        return [inliner.problematic(rawtext, rawtext, message)], [message]


def setup(app):
    app.connect("builder-inited", generate)
    app.add_role("bench", _figure_role)
    return {"version": "1", "parallel_read_safe": True}
