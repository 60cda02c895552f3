"""Dynamic-task benchmark: the pendulum strike over seeded runs, the peak tip speeds of coiling and
triangle against the paper's, and the tracking error against path speed, on the declared plant.
Prints three tables and writes JSON.

    python bench/bench_dynamic.py [--runs 10] [--planned-runs 3] [--speeds 0.0125 0.025 0.05 0.1 0.2]
                                  [--sizes 0.01 0.015] [--workers 2] [--output bench/results/dynamic.json]

Every figure is one ``soft-arm-harness TASK --json`` run, each a process of its own, the runs shared
out by the campaign engine (Dask, ``--workers`` at a time; ``soft_arm_experiments.campaigns.engine``):
- pendulum, ``--runs`` times with ``plant.mocap.seed`` 0, 1, ... (the mocap noise differs): struck
  or not, the impact time after the release, the ball's speed before and after, and the equivalent
  task velocity of the strike, the tip's displacement to the strike target over the time from the
  reference step to the impact (the paper: 1.48 m/s, struck 0.35 s after the release); the same
  with the planned move (``timing: planned``, :mod:`soft_arm_control.strike_planner`),
  ``--planned-runs`` times;
- coiling and triangle: the peak tip speed against the paper's (3.63 and 2.52 m/s; the pendulum's
  4.37 m/s beside its runs), with the Table 1 figures;
- tracking: a circle in the coiling plane (``tasks.tracking``'s, of each radius of ``--sizes``
  [m]) at each path speed of ``--speeds`` [m/s] (period = 2 pi size / speed), a window of whole
  periods at least the task's ``steady_time`` + 8 s long, with the path learned
  (``control.clik.track_learning``, :mod:`soft_arm_control.track_learning`) and without: tracking
  RMS and maximum error after ``steady_time``, and the RMS of the window's last period.
The same strike on randomly drawn plants is ``soft-arm-campaign robustness --tasks pendulum``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np

from soft_arm_experiments.campaigns.engine import map_runs
from timing import results_path, run_harness, write_results

PAPER = {"strike_time": 0.35, "strike_velocity": 1.48}     # s after the release, m/s


def harness(task: str, sets: list) -> dict:
    """``soft-arm-harness TASK --json`` with ``--set`` overrides: its JSON, or {"error": ...}."""
    proc = run_harness(task, sets)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1:]}
    return json.loads(proc.stdout)


def pendulum_run(seed: int, timing: str = "rehearsed") -> dict:
    out = harness("pendulum", [f"plant.mocap.seed={seed}", f"tasks.pendulum.pendulum.timing={timing}"])
    if "error" in out:
        return {"seed": seed, **out}
    strike, plan = out["strike"]["simulated"], out["strike"]["plan"]
    # the reference steps at send_delay, the ball goes at release_delay (both after the window starts)
    travel = None
    if strike["struck"]:
        travel = plan["release_delay"] + strike["impact_time"] - plan["send_delay"]
    displacement = out["transitions"][0]["displacement"]
    return {"seed": seed, "struck": strike["struck"], "impact_time": strike["impact_time"],
            "ball_speed_before": strike["ball_speed_before"],
            "ball_speed_after": strike["ball_speed_after"],
            "displacement": displacement, "travel_time": travel,
            "equivalent_velocity": displacement / travel if travel else None,
            "peak_speed": out["summary"]["peak_speed"], "paper_peak_speed": out["paper_peak_speed"]}


def speed_run(task: str) -> dict:
    out = harness(task, [])
    if "error" in out:
        return {"task": task, **out}
    s = out["summary"]
    return {"task": task, "peak_speed": s["peak_speed"], "paper_peak_speed": out["paper_peak_speed"],
            "rms_mm": s["rms_error"] * 1e3, "velocity_mm": s["velocity_mm"],
            "velocity_cm": s["velocity_cm"],
            "mm_band": s["reached_mm"], "transitions": s["transitions"]}


def tracking_run(speed: float, size: float, steady: float, learned: bool) -> dict:
    period = 2 * math.pi * size / speed
    window = period * math.ceil((steady + 8.0) / period)
    sets = ['tasks.tracking.phases=["approach","circle_fast"]',
            f"tasks.tracking.phase.circle_fast.trajectory.size={size!r}",
            f"tasks.tracking.phase.circle_fast.trajectory.period={period!r}",
            f"tasks.tracking.phase.circle_fast.window={window!r}"]
    out = harness("tracking", sets + ([] if learned else ["control.clik.track_learning.gain=0"]))
    head = {"size": size, "speed": speed, "learned": learned, "period": period}
    if "error" in out:
        return {**head, **out}
    t = out["tracking"][0]
    goal = next(g for g in out["targets"] if g["mode"] == "track")
    return {**head, "speed": t["path_speed"], "window": window, "rms_mm": t["rms_error"] * 1e3,
            "max_mm": t["max_error"] * 1e3, "last_period_rms_mm": t["last_period_rms_error"] * 1e3,
            "status": goal["status"], "learned_periods": goal["learned_periods"],
            "backed_off_periods": goal["backed_off_periods"], "frozen_periods": goal["frozen_periods"]}


def strike_table(title: str, strikes: list) -> dict:
    """Print the strikes of one timing rule (pendulum_run results) as a table and their summary;
    return the summary."""
    print(f"pendulum strike on the declared plant, {title} ({len(strikes)} runs, mocap seeds "
          f"0-{len(strikes) - 1}; the paper: struck {PAPER['strike_time']} s after the release, "
          f"{PAPER['strike_velocity']} m/s)")
    print(f"{'seed':>4s} {'struck':>6s} {'impact s':>8s} {'ball m/s':>13s} {'disp m':>6s} "
          f"{'travel s':>8s} {'v_eq m/s':>8s} {'peak m/s':>8s}")
    for r in strikes:
        if "error" in r:
            print(f"{r['seed']:4d} failed: {' '.join(r['error'])}")
            continue
        print(f"{r['seed']:4d} {'yes' if r['struck'] else 'no':>6s} {r['impact_time'] or 0:8.3f} "
              f"{r['ball_speed_before'] or 0:6.2f}>{r['ball_speed_after'] or 0:<6.2f} "
              f"{r['displacement']:6.3f} {r['travel_time'] or 0:8.3f} "
              f"{r['equivalent_velocity'] or 0:8.2f} {r['peak_speed']:8.2f}")
    ok = [r for r in strikes if "error" not in r]
    struck = [r for r in ok if r["struck"]]
    velocities = [r["equivalent_velocity"] for r in struck]
    summary = {
        "strikes": len(struck), "runs": len(strikes), "failed_runs": len(strikes) - len(ok),
        "impact_time": [min((r["impact_time"] for r in struck), default=None),
                        max((r["impact_time"] for r in struck), default=None)],
        "equivalent_velocity_median": float(np.median(velocities)) if velocities else None,
    }
    print(f"struck {summary['strikes']}/{summary['runs']}, impact {summary['impact_time']} s after the "
          f"release, equivalent velocity median {summary['equivalent_velocity_median']} m/s\n")
    return summary


def _run(job):
    kind, arg = job
    if kind == "pendulum":
        return pendulum_run(*arg)
    if kind == "speed":
        return speed_run(*arg)
    return tracking_run(*arg)


def run_spec(spec: dict):
    """One job on a campaign worker (:func:`soft_arm_experiments.campaigns.engine.map_runs`)."""
    return _run(spec["job"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--planned-runs", type=int, default=3)
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.0125, 0.025, 0.05, 0.1, 0.2])
    parser.add_argument("--sizes", type=float, nargs="+", default=None,
                        help="circle radii [m] (default: the tracking task's, and 0.015)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2,
                        help="local Dask workers (default: the number of cores)")
    parser.add_argument("--output", default=results_path("dynamic.json"))
    args = parser.parse_args(argv)
    from soft_arm_experiments.harness import load_setup
    track = load_setup("tracking").task
    sizes = args.sizes or [next(ph.trajectory.size for ph in track.phases if ph.name == "circle_fast"), 0.015]
    jobs = ([("pendulum", (k,)) for k in range(args.runs)]
            + [("pendulum", (k, "planned")) for k in range(args.planned_runs)]
            + [("speed", (t,)) for t in ("coiling", "triangle")]
            + [("tracking", (v, a, track.steady_time, learned)) for a in sizes for v in args.speeds
               for learned in (False, True)])
    specs = [{"job": list(job)} for job in jobs]
    results = map_runs(f"{os.path.abspath(__file__)}:run_spec", specs, workers=args.workers)
    strikes = results[:args.runs]
    planned = results[args.runs:args.runs + args.planned_runs]
    speeds = results[args.runs + args.planned_runs:args.runs + args.planned_runs + 2]
    tracking = results[args.runs + args.planned_runs + 2:]
    rehearsed_summary = strike_table("rehearsed step", strikes)
    planned_summary = strike_table("planned move", planned) if planned else None
    ok = [r for r in strikes if "error" not in r]
    print("\npeak tip speed against the paper's arm")
    print(f"{'task':9s} {'peak m/s':>8s} {'paper':>6s} {'ratio':>6s} | {'RMS mm':>7s} {'v_mm':>6s} "
          f"{'v_cm':>6s} {'mm band':>8s}")
    for r in speeds:
        if "error" in r:
            print(f"{r['task']:9s} failed: {' '.join(r['error'])}")
            continue
        print(f"{r['task']:9s} {r['peak_speed']:8.2f} {r['paper_peak_speed']:6.2f} "
              f"{r['peak_speed'] / r['paper_peak_speed']:6.2f} | {r['rms_mm']:7.2f} "
              f"{r['velocity_mm'] or 0:6.3f} {r['velocity_cm'] or 0:6.3f} "
              f"{r['mm_band']:4d}/{r['transitions']}")
    if ok:
        peak, paper = float(np.median([r["peak_speed"] for r in ok])), ok[0]["paper_peak_speed"]
        print(f"{'pendulum':9s} {peak:8.2f} {paper:6.2f} {peak / paper:6.2f} | (median of the runs)")
    print("\ntracking a circle in the coiling plane against path speed: RMS, max and the last "
          "period's RMS [mm], the path unlearned | learned (periods learned/backed off/frozen, status)")
    print(f"{'radius mm':>9s} {'speed m/s':>9s} {'period s':>8s} | {'RMS':>6s} {'max':>6s} {'last':>6s} | "
          f"{'RMS':>6s} {'max':>6s} {'last':>6s}")
    for plain, learned in zip(tracking[::2], tracking[1::2]):
        cells = []
        for r in (plain, learned):
            cells.append("failed: " + " ".join(r["error"]) if "error" in r else
                         f"{r['rms_mm']:6.2f} {r['max_mm']:6.2f} {r['last_period_rms_mm']:6.2f}")
        extra = "" if "error" in learned else (
            f" ({learned['learned_periods']}/{learned['backed_off_periods']}/{learned['frozen_periods']}, "
            f"{learned['status']})")
        print(f"{plain['size'] * 1e3:9.1f} {plain['speed']:9.4f} {plain['period']:8.2f} | {cells[0]} | "
              f"{cells[1]}{extra}")
    summary = {
        **rehearsed_summary, "planned": planned_summary,
        "peak_speed_ratio": {r["task"]: r["peak_speed"] / r["paper_peak_speed"]
                             for r in speeds if "error" not in r},
        "tracking_rms_mm": {f"{r['size'] * 1e3:.0f} mm, {r['speed']:.4f} m/s, "
                            f"{'learned' if r['learned'] else 'unlearned'}": r.get("rms_mm")
                            for r in tracking},
    }
    write_results(args.output, {"summary": summary, "strikes": strikes, "planned_strikes": planned,
                                "speeds": speeds, "tracking": tracking})
    return 0


if __name__ == "__main__":
    sys.exit(main())
