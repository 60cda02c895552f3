"""A campaign's summary from its records: ``summary.json`` (with when, where and at which commit it was
made), ``summary.md`` (the tables) and one histogram figure per group of runs, in the campaign's
folder.

Runs are grouped (a robustness campaign: per task, over all draws and over the draws whose plant can
hold the task's targets; an identification campaign: all draws; a sweep: per outcome), and per group
each figure gets its median, its worst (the end a user fears: the highest error, the lowest
velocity), its best and its 90th percentile towards the worst. Failed runs are counted per group and
listed with their errors; they never drop out silently. Runs outside the distribution (the
structurally different arm, draw ``structural``) are reported on their own.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

# per kind: (figure, dotted path in a result, label, the worse end: "high" or "low")
FIGURES = {
    "task": [("rms_mm", "rms_mm", "steady-state RMS task error [mm]", "high"),
             ("mm_band", "mm_band", "transitions in the mm band", "low"),
             ("velocity_mm_band", "velocity_mm_band", "mm-band task velocity [m/s]", "low"),
             ("velocity_cm_band", "velocity_cm_band", "cm-band task velocity [m/s]", "low"),
             ("infeasible_steps", "infeasible_steps", "online CLIK steps projected onto the limits", "high"),
             ("tracking_rms_mm", "tracking_rms_mm", "tracking RMS, worst window [mm]", "high")],
    "identification": [
        ("youngs_modulus_error_pct", "errors.youngs_modulus", "E error [%]", "high"),
        ("viscosity_error_pct", "errors.viscosity", "viscosity error [%]", "high"),
        ("rotor_mass_error_pct", "errors.rotor_mass", "rotor mass error [%]", "high"),
        ("tip_mass_error_g", "errors.tip_mass_g", "tip mass error [g]", "high"),
        ("friction_error", "errors.friction", "friction error, worst tendon", "high"),
        ("offset_error", "errors.offset_fraction", "offset error, worst tendon [fraction of r]", "high"),
        ("angle_error_deg", "errors.angle_deg", "tendon angle error, worst [deg]", "high"),
        ("frame_rotation_deg", "errors.frame_rotation_deg", "mocap frame rotation error [deg]", "high"),
        ("frame_translation_mm", "errors.frame_translation_mm", "mocap frame translation error [mm]", "high"),
        ("per_uncertainty", "errors.per_uncertainty", "worst error / its uncertainty", "high"),
        ("fit_s", "fit_s", "fit wall time [s]", "high"),
        ("triangle_rms_mm", "triangle.rms_mm", "triangle with the identified arm: RMS [mm]", "high"),
        ("triangle_velocity_mm_band", "triangle.velocity_mm_band",
         "triangle with the identified arm: mm-band velocity [m/s]", "low"),
        ("triangle_true_rms_mm", "triangle_true.rms_mm", "triangle with the true parameters: RMS [mm]",
         "high")],
    "bag": [("tip_rms_mm", "tip_rms_mm", "tip residual RMS [mm]", "high"),
            ("fit_s", "fit_s", "fit wall time [s]", "high")],
    "workspace": [("converged", "converged", "equilibria converged", "low"),
                  ("reach_m", "reach_m", "largest tip distance from the axis [m]", "low"),
                  ("highest_m", "highest_m", "highest tip point [m]", "low")],
}
PERCENT = {"youngs_modulus_error_pct", "viscosity_error_pct", "rotor_mass_error_pct"}
MAX_ROWS = 500           # rows of the per-run table of summary.md; every run is in records.jsonl


def measured() -> dict:
    """When (UTC), on what machine and at which commit a result was made (the docs' benchmark page
    shows all three)."""
    return {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "commit": commit(),
            "machine": machine()}


def machine() -> dict:
    """The CPU model, its count, the Python, the OS."""
    model = platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            model = next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")),
                         model)
    except OSError:
        pass
    return {"cpu": model, "cpus": os.cpu_count(), "python": platform.python_version(),
            "system": platform.platform()}


def commit() -> str:
    """The git commit of the code (``+changes`` when the tree differs from it); ``unknown`` outside
    a clone (an installed package)."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=here, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty else "")


def _value(result: dict, path: str):
    """The figure at dotted ``path`` of a result: a number, or None (a band never reached); a list
    (the track windows) gives its largest value."""
    value = result
    for part in path.split("."):
        if not isinstance(value, dict):
            return None
        value = value.get(part)
    if isinstance(value, list):
        value = max((v for v in value if v is not None), default=None)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value)


def kind_of(record: dict) -> str:
    """Which figures a record has: ``task``, ``identification``, ``bag`` or ``workspace``."""
    spec = record["spec"]
    if spec.get("kind") == "identification":
        return "bag" if "bag" in spec else "identification"
    if spec.get("kind") == "sweep" and spec.get("outcome") == "workspace":
        return "workspace"
    return "task"


def groups_of(records: list) -> dict:
    """The groups a summary is made of: name -> records (failed ones included)."""
    out: dict = {}
    for r in records:
        spec = r["spec"]
        if spec.get("draw") == "structural":
            continue
        if spec.get("kind") == "robustness":
            out.setdefault(f"{spec['task']}, all draws", []).append(r)
            if r["status"] == "ok" and r["result"].get("plant_holds"):
                out.setdefault(f"{spec['task']}, draws whose plant holds the targets", []).append(r)
        elif spec.get("kind") == "sweep":
            out.setdefault(spec["outcome"], []).append(r)
        else:
            out.setdefault("bags" if "bag" in spec else "all draws", []).append(r)
    return out


def statistics(values: list, worse: str) -> dict:
    """Median, worst, best and the 90th percentile towards the worst of ``values`` (Nones left out,
    counted as ``missing``: a band never reached)."""
    present = np.array([v for v in values if v is not None], dtype=float)
    out = {"n": int(present.size), "missing": len(values) - int(present.size)}
    if present.size:
        high = worse == "high"
        out.update(median=float(np.median(present)),
                   worst=float(present.max() if high else present.min()),
                   best=float(present.min() if high else present.max()),
                   p90=float(np.percentile(present, 90 if high else 10)))
    return out


def figures_of(record: dict) -> dict:
    """A finished record's figures by name (errors in % where the name says so)."""
    out = {}
    for name, path, _, _ in FIGURES[kind_of(record)]:
        value = _value(record["result"], path)
        if value is not None and name in PERCENT:
            value *= 100
        if value is not None and path.startswith("errors."):
            value = abs(value)
        out[name] = value
    return out


def summarise(records: list, describe: dict, outcome=None) -> dict:
    """The summary of a campaign's records (see the module's docstring); ``outcome``: the engine's
    :class:`~.engine.Outcome` of this call (its overhead and throughput), if any."""
    summary = {"measured": measured(), "campaign": describe, "runs": len(records),
               "failed": sum(r["status"] != "ok" for r in records),
               "failures": [{"key": r["key"], "spec": _short(r["spec"]),
                             "error": _first_line(r.get("error"))}
                            for r in records if r["status"] != "ok"],
               "groups": {}}
    for name, group in groups_of(records).items():
        ok = [r for r in group if r["status"] == "ok"]
        entry = {"runs": len(group), "failed": len(group) - len(ok), "figures": {}}
        if ok:
            per_run = [figures_of(r) for r in ok]
            for figure, _, label, worse in FIGURES[kind_of(ok[0])]:
                values = [f[figure] for f in per_run]
                if any(v is not None for v in values):
                    entry["figures"][figure] = {"label": label, "worse": worse, **statistics(values, worse)}
            counts = [r["result"]["status_counts"] for r in ok if "status_counts" in r["result"]]
            if counts:
                entry["goal_statuses"] = {s: sum(c[s] for c in counts) for s in counts[0]}
            strikes = [r["result"]["strike"] for r in ok if r["result"].get("strike")]
            if strikes:
                entry["struck"] = sum(s["simulated"]["struck"] for s in strikes)
            worst = _worst_run(ok, per_run)
            if worst:
                entry["worst_run"] = worst
        summary["groups"][name] = entry
    outside = [r for r in records if r["spec"].get("draw") == "structural"]
    if outside:
        summary["structural"] = [{"spec": _short(r["spec"]), "status": r["status"],
                                  **({"figures": figures_of(r)} if r["status"] == "ok"
                                     else {"error": _first_line(r["error"])})}
                                 for r in outside]
    if outcome is not None and outcome.ran:
        run_s = [r["run_s"] for r in outcome.records if r.get("run_s")]
        summary["engine"] = {"workers": outcome.workers, "ran": outcome.ran, "wall_s": outcome.wall_s,
                             "runs_per_hour": 3600.0 * outcome.ran / outcome.wall_s,
                             "run_s_median": float(np.median(run_s)) if run_s else None}
        if outcome.overhead_s and run_s:
            summary["engine"]["overhead_s_median"] = float(np.median(outcome.overhead_s))
            summary["engine"]["overhead_fraction"] = float(np.median(outcome.overhead_s) / np.median(run_s))
    return summary


def _first_line(error) -> str:
    """The first line of a run's error (its type and message), '' without one."""
    lines = (error or "").strip().splitlines()
    return lines[0] if lines else ""


def _short(spec: dict) -> dict:
    """A specification with what names the run (task, draw, seed, sets, outcome, bag), not the plant."""
    return {k: v for k, v in spec.items() if k in ("kind", "task", "draw", "seed", "sets", "outcome", "bag")}


def _worst_run(ok: list, per_run: list) -> dict | None:
    """The run of the worst first figure (RMS error, E error, reach), to rerun it by its key."""
    first, _, _, worse = FIGURES[kind_of(ok[0])][0]
    scored = [(f[first], r) for f, r in zip(per_run, ok) if f[first] is not None]
    if not scored:
        return None
    value, record = (max if worse == "high" else min)(scored, key=lambda p: p[0])
    return {"figure": first, "value": value, "key": record["key"], "spec": _short(record["spec"])}


def to_markdown(summary: dict, records: list) -> str:
    """The summary's tables and one row per run (the first :data:`MAX_ROWS`), for ``summary.md``."""
    out = [f"# Campaign {summary['campaign'].get('kind', '')}", "",
           f"{summary['runs']} runs, {summary['failed']} failed; made {summary['measured']['date']} at "
           f"commit `{summary['measured']['commit']}`.", ""]
    for name, entry in summary["groups"].items():
        out += [f"## {name}", "", f"{entry['runs']} runs, {entry['failed']} failed.", ""]
        if entry["figures"]:
            out += ["| figure | median | worst | 90 % | best | runs without it |",
                    "|---|---|---|---|---|---|"]
            for figure in entry["figures"].values():
                if "median" in figure:
                    out.append(f"| {figure['label']} | {figure['median']:.4g} | {figure['worst']:.4g} | "
                               f"{figure['p90']:.4g} | {figure['best']:.4g} | {figure['missing']} |")
            out.append("")
        if "goal_statuses" in entry:
            statuses = entry["goal_statuses"]
            out += ["Goals by status: " + ", ".join(f"{k} {v}" for k, v in statuses.items()), ""]
        if "struck" in entry:
            out += [f"Ball struck on {entry['struck']} of {entry['runs'] - entry['failed']} runs.", ""]
        if "worst_run" in entry:
            w = entry["worst_run"]
            out += [f"Worst run ({w['figure']} {w['value']:.4g}): key `{w['key']}`, "
                    f"{json.dumps(w['spec'])}.", ""]
    for r in summary.get("structural", []):
        text = (", ".join(f"{k} {v:.4g}" for k, v in r["figures"].items() if v is not None)
                if r["status"] == "ok" else f"failed: {r['error']}")
        out += [f"Structurally different arm ({json.dumps(r['spec'])}): {text}.", ""]
    out += runs_table(records)
    if summary["failures"]:
        out += ["## Failed runs", ""] + [f"- `{f['key']}` {json.dumps(f['spec'])}: {f['error']}"
                                         for f in summary["failures"]] + [""]
    if "engine" in summary:
        e = summary["engine"]
        out += [f"This call: {e['ran']} runs on {e['workers']} workers in {e['wall_s']:.0f} s "
                f"({e['runs_per_hour']:.0f} runs/h; a run's median {e['run_s_median']:.1f} s"
                + (f", overhead per run {e['overhead_s_median'] * 1e3:.0f} ms = "
                   f"{e['overhead_fraction'] * 100:.2f} %" if "overhead_fraction" in e else "") + ").", ""]
    return "\n".join(out)


def runs_table(records: list) -> list:
    """Markdown lines: per run, what names it (draw or sample, task or outcome, the plant's E scale),
    its status and its figures (``-``: a band never reached)."""
    if not records:
        return []
    names = list(dict.fromkeys(name for r in records for name, *_ in FIGURES[kind_of(r)]))
    out = ["## Runs", "", "| run | key | status | " + " | ".join(names) + " |",
           "|---|---|---|" + "---|" * len(names)]
    for r in records[:MAX_ROWS]:
        spec = r["spec"]
        what = " ".join(str(spec[k]) for k in ("task", "outcome", "draw", "sample") if k in spec)
        if "bag" in spec:
            what = os.path.basename(spec["bag"])
        if r["result"] is not None and "plant_holds" in r["result"]:
            what += "" if r["result"]["plant_holds"] else " (plant cannot hold)"
        figures = figures_of(r) if r["status"] == "ok" else {}
        cells = ["-" if figures.get(n) is None else f"{figures[n]:.4g}" for n in names]
        out.append(f"| {what} | `{r['key'][:8]}` | {r['status']} | " + " | ".join(cells) + " |")
    if len(records) > MAX_ROWS:
        out.append(f"\n... {len(records) - MAX_ROWS} more runs in records.jsonl")
    return out + [""]


def histograms(records: list, summary: dict, folder: Path) -> list:
    """One PNG per group: a histogram per figure with its median and worst marked; the paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    paths = []
    for index, (name, group) in enumerate(groups_of(records).items()):
        ok = [r for r in group if r["status"] == "ok"]
        figures = summary["groups"][name]["figures"]
        shown = [f for f in figures if "median" in figures[f]]
        if not ok or not shown:
            continue
        per_run = [figures_of(r) for r in ok]
        columns = min(3, len(shown))
        rows = -(-len(shown) // columns)
        fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.0 * rows), squeeze=False)
        for ax, figure in zip(axes.flat, shown):
            values = [f[figure] for f in per_run if f[figure] is not None]
            ax.hist(values, bins=min(30, max(5, len(values) // 3)), color="#4c72b0")
            ax.axvline(figures[figure]["median"], color="k", lw=1.2, label="median")
            ax.axvline(figures[figure]["worst"], color="#c44e52", lw=1.2, ls="--", label="worst")
            ax.set_xlabel(figures[figure]["label"], fontsize=8)
            ax.set_ylabel("runs")
        for ax in list(axes.flat)[len(shown):]:
            ax.set_visible(False)
        axes.flat[0].legend(fontsize=7)
        fig.suptitle(f"{name}: {len(ok)} runs", fontsize=10)
        fig.tight_layout()
        path = Path(folder) / f"histograms-{index + 1}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def write_report(folder, records: list, describe: dict, outcome=None) -> dict:
    """``summary.json``, ``summary.md`` and the histograms into ``folder``; the summary."""
    folder = Path(folder)
    summary = summarise(records, describe, outcome)
    summary["plots"] = [p.name for p in histograms(records, summary, folder)]
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    (folder / "summary.md").write_text(to_markdown(summary, records), encoding="utf-8")
    return summary
