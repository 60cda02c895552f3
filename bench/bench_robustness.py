"""Robustness benchmark: the controller, unchanged, on many randomly drawn plants. Prints a table per
draw and the distribution, writes JSON.

    python bench/bench_robustness.py [--draws 10] [--seed 0] [--tasks triangle coiling]
                                     [--set ns.key=value ...] [--jobs 2]
                                     [--output bench/results/robustness.json]

Each draw is a plant that differs from the controller's arm the way a cast silicone arm differs from
its drawing (tolerances below, uniform within them, seeded): Young's modulus and viscosity +-20 %,
density +-5 %, tendon angles +-3 deg at the base and at the end (each tendon its own), offsets
0.6 +-0.05 of the radius, friction 0.05-0.2 per tendon, strain order 3-5 on the tendon span with
and without shear, a 0-5 g tip payload. Every task runs on every draw with ``soft-arm-harness``, one
process per run, ``--jobs`` at a time (both cores by default). Reported per run: steady-state RMS
task error, transitions in the mm band, mm- and cm-band task velocities, and the CLIK's
infeasibility events (online steps that had to be projected onto the tension limits), each goal's
status and the number of goals per status (ok, constrained, saturated, stalled, unreached, held; a
goal closed away from its target is never ok: ``GoalReport.status``); whether the drawn plant itself
can hold the targets (solved on its own model: within the limits and stable under the inner loop; a
target it cannot hold no controller reaches); then the median and the worst draw per task, over
all draws and over the draws whose plant holds the targets; for a task with track windows
(``--tasks tracking``) the tracking RMS and maximum error of each window too, for the pendulum
whether the ball was struck. A structurally different arm (``STRUCTURAL_PLANT``) runs too, as
draw ``structural``, outside the distribution.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from soft_arm_control.outer_loop import STATUSES
from timing import results_path, run_harness, write_results

TOLERANCES = {
    "youngs_modulus_scale": (0.8, 1.2), "viscosity_scale": (0.8, 1.2), "density_scale": (0.95, 1.05),
    "angle_error_deg": 3.0, "offset_fraction": (0.55, 0.65), "friction": (0.05, 0.2),
    "legendre_order": (3, 5), "tip_payload": (0.0, 0.005),
}
N_TENDONS = 4
# A structurally different arm, run first as draw "structural": E -12 %, viscosity +30 %, density
# +5 %, offsets 0.57-0.64, base angles off by 2-3 deg, uneven friction, order 4 with shear.
STRUCTURAL_PLANT = {
    "youngs_modulus_scale": 0.88, "viscosity_scale": 1.3, "density_scale": 1.05,
    "friction": [0.09, 0.16, 0.12, 0.1], "tendon.offset_fraction": [0.57, 0.64, 0.6, 0.62],
    "tendon.start_angle_error": [0.04, -0.05, 0.03, -0.04], "tendon.end_angle_error": [0.0, 0.0, 0.0, 0.0],
    "discretisation.legendre_order": [4, 0], "discretisation.shear": True, "tip_payload": 0.0,
}


def draw_plant(rng: np.random.Generator) -> dict:
    """One plant, as ``plant.*`` overrides of plant.yaml."""
    t = TOLERANCES
    angle = np.deg2rad(t["angle_error_deg"])
    return {
        "youngs_modulus_scale": round(float(rng.uniform(*t["youngs_modulus_scale"])), 4),
        "viscosity_scale": round(float(rng.uniform(*t["viscosity_scale"])), 4),
        "density_scale": round(float(rng.uniform(*t["density_scale"])), 4),
        "friction": [round(float(f), 4) for f in rng.uniform(*t["friction"], N_TENDONS)],
        "tendon.offset_fraction": [round(float(f), 4)
                                   for f in rng.uniform(*t["offset_fraction"], N_TENDONS)],
        "tendon.start_angle_error": [round(float(a), 5) for a in rng.uniform(-angle, angle, N_TENDONS)],
        "tendon.end_angle_error": [round(float(a), 5) for a in rng.uniform(-angle, angle, N_TENDONS)],
        "discretisation.legendre_order": [int(rng.integers(t["legendre_order"][0],
                                                           t["legendre_order"][1] + 1)), 0],
        "discretisation.shear": bool(rng.integers(0, 2)),
        "tip_payload": round(float(rng.uniform(*t["tip_payload"])), 5),
    }


def plant_holds(task: str, overrides: list) -> dict:
    """Whether the drawn plant itself can hold the task's targets: the precomputed CLIK solved on
    the plant's own model, margin [N] from the tension limits and stability under the inner loop
    (:func:`soft_arm_control.target_margin.check_arm`). A target it cannot hold no controller reaches."""
    from soft_arm_control.target_margin import check_arm, is_robust
    from soft_arm_drivers.experiments.harness import load_setup
    setup = load_setup(task, overrides=overrides)
    results = check_arm(setup.plant.plant_arm(setup.arm), setup.control, setup.task, setup.task.targets)
    return {"plant_holds": is_robust(results, min_margin=0.0),
            "plant_margins": [r.margin for r in results], "plant_stable": [r.stable for r in results]}


def run_one(task: str, plant: dict, sets=()) -> dict:
    """``soft-arm-harness TASK --json`` on the plant, with the ``--set`` overrides ``sets`` (e.g.
    another trajectory); its summary, or the error; whether the plant can hold the targets at all."""
    overrides = [f"plant.{key}={json.dumps(value)}" for key, value in plant.items()] + list(sets)
    holds = plant_holds(task, overrides)
    t0 = time.perf_counter()
    proc = run_harness(task, overrides)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"ok": False, "error": proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"],
                "wall_s": wall, **holds}
    out = json.loads(proc.stdout)
    s = out["summary"]
    goals = [g for g in out["targets"] if g["online_steps"]]
    return {"ok": True, "wall_s": wall, "rms_mm": s["rms_error"] * 1e3, "mm_band": s["reached_mm"],
            "transitions": s["transitions"], "velocity_mm_band": s["velocity_mm"],
            "velocity_cm_band": s["velocity_cm"],
            "infeasible_steps": sum(g["infeasible_steps"] for g in goals),
            "statuses": [g["status"] for g in goals],
            "status_counts": {status: sum(g["status"] == status for g in goals) for status in STATUSES},
            "tracking_rms_mm": [r["rms_error"] * 1e3 for r in out.get("tracking", [])],
            "tracking_max_mm": [r["max_error"] * 1e3 for r in out.get("tracking", [])],
            "tracking_last_period_rms_mm": [None if r["last_period_rms_error"] is None
                                            else r["last_period_rms_error"] * 1e3
                                            for r in out.get("tracking", [])],
            "strike": out.get("strike"), **holds}


def _strike(strike: dict | None) -> str:
    """The simulated strike's outcome in a few words ('' without a pendulum)."""
    if strike is None:
        return ""
    sim = strike["simulated"]
    if sim["struck"]:
        return (f"  struck {sim['impact_time']:.3f} s after the release (ball peak at "
                f"{strike['plan']['ball_time']:.3f} s)")
    return f"  missed by {sim.get('closest_approach', float('nan')) * 1e3:.1f} mm"


def _distribution(drawn: list) -> dict:
    """Median and worst of the completed runs among ``drawn``."""
    ok = [r for r in drawn if r["ok"]]
    failed = len(drawn) - len(ok)
    if not ok:
        return {"runs": 0, "failed": failed}
    rms = np.array([r["rms_mm"] for r in ok])
    band = np.array([r["mm_band"] for r in ok])
    vmm = np.array([r["velocity_mm_band"] or 0.0 for r in ok])
    tracking = {}
    if ok[0]["strike"] is not None:
        tracking["strikes"] = sum(r["strike"]["simulated"]["struck"] for r in ok)
    if ok[0]["tracking_rms_mm"]:
        worst = np.array([max(r["tracking_rms_mm"]) for r in ok])
        tracking = {"tracking_rms_mm_worst_window_median": float(np.median(worst)),
                    "tracking_rms_mm_worst": float(worst.max()),
                    "tracking_max_mm_worst": float(max(max(r["tracking_max_mm"]) for r in ok))}
        last = [max((v for v in r["tracking_last_period_rms_mm"] if v is not None), default=np.nan)
                for r in ok]
        if not np.all(np.isnan(last)):
            tracking["tracking_last_period_rms_mm_worst_window_median"] = float(np.nanmedian(last))
            tracking["tracking_last_period_rms_mm_worst"] = float(np.nanmax(last))
    return {**tracking, "runs": len(ok), "failed": failed, "rms_mm_median": float(np.median(rms)),
            "rms_mm_worst": float(rms.max()), "mm_band_median": float(np.median(band)),
            "mm_band_worst": int(band.min()), "transitions": ok[0]["transitions"],
            "velocity_mm_band_median": float(np.median(vmm)),
            "draws_with_infeasibility": sum(r["infeasible_steps"] > 0 for r in ok),
            "goal_statuses": {status: sum(r["status_counts"][status] for r in ok) for status in STATUSES}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tasks", nargs="+", default=["triangle", "coiling"])
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE",
                        help="a configuration override for every run (soft-arm-harness --set)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--output", default=results_path("robustness.json"))
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    plants = [STRUCTURAL_PLANT] + [draw_plant(rng) for _ in range(args.draws)]
    jobs = [(task, i) for i in range(len(plants)) for task in args.tasks]
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(run_one, [task for task, _ in jobs], [plants[i] for _, i in jobs],
                                [args.sets] * len(jobs)))
    runs = [{"task": task, "draw": i - 1 if i else "structural", "plant": plants[i], **r}
            for (task, i), r in zip(jobs, results)]
    print(f"{'task':9s} {'draw':>5s} {'E':>5s} {'order':>5s} {'shear':>5s} {'tip g':>5s} {'holds':>5s} "
          f"{'RMS mm':>7s} {'mm band':>8s} {'v_mm m/s':>8s} {'v_cm m/s':>8s} {'infeas.':>7s}  statuses")
    for r in runs:
        p = r["plant"]
        head = (f"{r['task']:9s} {r['draw']!s:>5s} {p['youngs_modulus_scale']:5.2f} "
                f"{p['discretisation.legendre_order'][0]:5d} {str(p['discretisation.shear']):>5s} "
                f"{p['tip_payload'] * 1e3:5.1f} {'yes' if r['plant_holds'] else 'no':>5s}")
        if not r["ok"]:
            print(f"{head}  failed: {' '.join(r['error'])}")
            continue
        print(f"{head} {r['rms_mm']:7.2f} {r['mm_band']:4d}/{r['transitions']:<3d} "
              f"{r['velocity_mm_band'] or 0:8.3f} {r['velocity_cm_band'] or 0:8.3f} "
              f"{r['infeasible_steps']:7d}  {' '.join(r['statuses'])}"
              + (f"  tracking RMS {' '.join(f'{v:.2f}' for v in r['tracking_rms_mm'])} mm (last period "
                 f"{' '.join('-' if v is None else f'{v:.2f}' for v in r['tracking_last_period_rms_mm'])})"
                 if r["tracking_rms_mm"] else "") + _strike(r["strike"]))
    summary = {}
    for task in args.tasks:
        drawn = [r for r in runs if r["task"] == task and r["draw"] != "structural"]
        summary[task] = {"all draws": _distribution(drawn),
                         "draws whose plant holds the targets": _distribution(
                             [r for r in drawn if r["plant_holds"]])}
        for name, s in summary[task].items():
            if "rms_mm_median" not in s:
                print(f"{task}, {name}: no completed run ({s['failed']} failed)")
                continue
            print(f"{task}, {name} ({s['runs']}): RMS median {s['rms_mm_median']:.2f} mm, worst "
                  f"{s['rms_mm_worst']:.2f} mm; mm band median {s['mm_band_median']:.0f}, worst "
                  f"{s['mm_band_worst']}/{s['transitions']}; mm-band velocity median "
                  f"{s['velocity_mm_band_median']:.3f} m/s; failed {s['failed']}; draws with infeasible "
                  f"steps {s['draws_with_infeasibility']}; goals by status: "
                  + ", ".join(f"{status} {n}" for status, n in s["goal_statuses"].items())
                  + (f"; tracking RMS of the worst window: median "
                     f"{s['tracking_rms_mm_worst_window_median']:.2f} mm, worst "
                     f"{s['tracking_rms_mm_worst']:.2f} mm (max error {s['tracking_max_mm_worst']:.2f} mm)"
                     + (f"; last period: median {s['tracking_last_period_rms_mm_worst_window_median']:.2f}, "
                        f"worst {s['tracking_last_period_rms_mm_worst']:.2f} mm"
                        if "tracking_last_period_rms_mm_worst" in s else "")
                     if "tracking_rms_mm_worst" in s else "")
                  + (f"; struck on {s['strikes']} of {s['runs']}" if "strikes" in s else ""))
    write_results(args.output, {"tolerances": TOLERANCES, "seed": args.seed, "summary": summary,
                                "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
