"""Helpers shared by the benchmark scripts: timing, writing the results, running the harness."""
import itertools
import json
import os
import subprocess
import sys
import time

import numpy as np

from soft_arm_experiments.campaigns import report as campaign_report


def best_of(fn, repeats: int = 7, inner: int = 500) -> float:
    """The best mean time [s] of one call of ``fn`` over ``repeats`` runs of ``inner`` calls."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, (time.perf_counter() - t0) / inner)
    return best


def ticks(period: float):
    """An endless clock for the steps being timed: 0, period, 2 period, ... [s], one at a time (an
    array of them would be gigabytes, its allocation the bench's slowest part)."""
    return (k * period for k in itertools.count())


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] of process ``pid`` so far (Linux /proc)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def results_path(name: str) -> str:
    """The default output of a benchmark: ``bench/results/<name>``."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", name)


def write_results(path: str, results: dict):
    """Write ``results`` as JSON to ``path`` with when (UTC), on what machine and at which commit
    they were measured (the docs' benchmark page shows all three); say where."""
    measured = campaign_report.measured()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump({"measured": measured, **results}, fh, indent=2, default=float)
    print(f"wrote {path}")


def run_harness(task: str, sets=(), *args: str) -> subprocess.CompletedProcess:
    """``soft-arm-harness TASK --json --quiet`` in a process of its own, with ``--set`` for each of
    ``sets`` (``ns.key=value``) and further command-line ``args``; stdout and stderr captured."""
    command = [sys.executable, "-m", "soft_arm_experiments.harness_cli", task, "--json", "--quiet"]
    command += [a for s in sets for a in ("--set", s)] + list(args)
    return subprocess.run(command, capture_output=True, text=True)
