"""Campaign engine benchmark: the robustness triangle on drawn plants, on one Dask worker and on two,
through the engine ``soft-arm-campaign`` uses. Prints throughput, speed-up, the overhead per run and
what a 1,000-draw campaign costs; writes JSON.

    python bench/bench_campaign.py [--draws 8] [--seed 100] [--tasks triangle]
                                   [--output bench/results/campaign.json]

Each configuration runs the same draws (seeds ``seed .. seed + draws - 1``) in a fresh folder, so
both do the same work. Throughput: runs per hour of wall time, from the first submission to the
last record. Overhead per run: the time a worker spends between the end of one run and the start of
its next (scheduling, transfer of the specification and the result) plus the writing of the record
(:func:`soft_arm_experiments.campaigns.engine.overheads`), against the median run's own time. The
1,000-draw estimate divides the draws' runs by the two-worker throughput per worker, on this
machine and on ten like it (a Dask cluster of their cores: runs are independent, the scheduler
sends a few hundred bytes per run).
"""
from __future__ import annotations

import argparse
import sys
import tempfile

import numpy as np

from soft_arm_experiments.campaigns.engine import run_campaign
from soft_arm_experiments.campaigns.plants import draw_plant, load_tolerances
from timing import results_path, write_results

FUNCTION = "soft_arm_experiments.campaigns.runs:robustness"


def measure(specs: list, workers: int) -> dict:
    """The campaign of ``specs`` on ``workers`` workers in a scratch folder: its figures."""
    with tempfile.TemporaryDirectory(prefix="bench-campaign-") as folder:
        out = run_campaign(folder, FUNCTION, specs, workers=workers)
    failed = [r["error"] for r in out.records if r["status"] != "ok"]
    if failed or out.interrupted:
        raise RuntimeError(f"{len(failed)} runs failed: {failed[:3]}")
    run_s = np.array([r["run_s"] for r in out.records])
    overhead = np.array(out.overhead_s) if out.overhead_s else np.zeros(1)
    return {"workers": out.workers, "runs": out.ran, "wall_s": out.wall_s,
            "runs_per_hour": 3600.0 * out.ran / out.wall_s, "run_s_median": float(np.median(run_s)),
            "run_s_sum": float(run_s.sum()), "overhead_s_median": float(np.median(overhead)),
            "overhead_s_max": float(overhead.max()),
            "overhead_fraction_median": float(np.median(overhead) / np.median(run_s)),
            "busy_fraction": float(run_s.sum() / (out.wall_s * out.workers))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--tasks", nargs="+", default=["triangle"])
    parser.add_argument("--output", default=results_path("campaign.json"))
    args = parser.parse_args(argv)
    tolerances = load_tolerances()
    specs = [{"kind": "robustness", "task": task, "draw": seed, "plant": draw_plant(seed, tolerances),
              "sets": []} for seed in range(args.seed, args.seed + args.draws) for task in args.tasks]
    one = measure(specs, 1)
    two = measure(specs, 2)
    speedup = two["runs_per_hour"] / one["runs_per_hour"]
    per_worker = two["runs_per_hour"] / two["workers"]
    runs_1000 = 1000 * len(args.tasks)
    cost = {"runs": runs_1000, "one_machine_h": runs_1000 / two["runs_per_hour"],
            "ten_machines_h": runs_1000 / (10 * two["runs_per_hour"]),
            "core_hours": runs_1000 / per_worker}
    print(f"{'workers':>7s} {'runs':>4s} {'wall s':>7s} {'runs/h':>7s} {'run s (median)':>14s} "
          f"{'overhead ms (median/max)':>24s} {'overhead %':>10s} {'busy %':>6s}")
    for r in (one, two):
        print(f"{r['workers']:7d} {r['runs']:4d} {r['wall_s']:7.1f} {r['runs_per_hour']:7.1f} "
              f"{r['run_s_median']:14.1f} {r['overhead_s_median'] * 1e3:11.1f} / "
              f"{r['overhead_s_max'] * 1e3:9.1f} "
              f"{r['overhead_fraction_median'] * 100:10.3f} {r['busy_fraction'] * 100:6.1f}")
    print(f"two workers / one: {speedup:.2f}x; {per_worker:.1f} runs per hour per worker")
    print(f"1,000 draws of {' and '.join(args.tasks)} ({runs_1000} runs): {cost['one_machine_h']:.1f} h "
          f"on the measuring machine, {cost['ten_machines_h']:.1f} h on ten of its kind "
          f"({cost['core_hours']:.0f} core-hours)")
    write_results(args.output, {"draws": args.draws, "seed": args.seed, "tasks": args.tasks,
                                "one_worker": one, "two_workers": two, "speedup": speedup,
                                "runs_per_hour_per_worker": per_worker, "thousand_draws": cost})
    return 0


if __name__ == "__main__":
    sys.exit(main())
