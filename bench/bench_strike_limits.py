"""What bounds the strike's speed: the shortest move the strike planner finds on the controller's model
to the pendulum task's strike target, against the hardware the model is given. Prints a table and
writes JSON.

    python bench/bench_strike_limits.py [--rotor-masses 0.6 0.3 0.15 0] [--tension-limits 5 20]
                                        [--pieces 3 6] [--workers 2]
                                        [--output bench/results/strike_limits.json]

For every combination of the reflected rotor mass on each tendon [kg] (``control.rotor_mass``; the
declared AK80-class rotor is 0.6 kg), the upper tension limit [N] (``control.tension_max``) and the
number of constant tension levels of the planned profile (``pieces``),
:func:`soft_arm_control.strike_planner.plan_strike_move` bisects the shortest duration whose fitted
profile brings the task point within 1 mm of the strike target from the hanging arm (between 0.05
and 0.5 s, 5 bisections: about 14 ms of resolution), the combinations shared out by the campaign
engine (Dask, ``--workers`` at a time). The table gives
that duration, the equivalent task velocity (the target's distance from the hanging arm's task
point over the duration; the paper: 1.48 m/s) and the planned tip speed at the target. A
combination whose fit fails says why.
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import sys
import time

import numpy as np

from soft_arm_experiments.campaigns.engine import map_runs
from timing import results_path, write_results

PAPER_VELOCITY = 1.48      # m/s, the paper's equivalent task velocity of the strike


def plan(job) -> dict:
    """The planner's shortest move for one (rotor mass [kg], tension limit [N], pieces)."""
    rotor_mass, tension_max, pieces = job
    from soft_arm_control.outer_loop import outer_loop_for
    from soft_arm_control.strike_planner import plan_strike_move
    from soft_arm_experiments.harness import load_setup, precompute_targets, schedule
    from soft_arm_model import build_model
    setup = load_setup("pendulum")
    model = build_model(setup.arm)
    control = dataclasses.replace(setup.control, rotor_mass=rotor_mass, tension_max=tension_max)
    outer = outer_loop_for(model, setup.control, setup.task)
    goal = precompute_targets(outer, setup.control, setup.task)[schedule(setup.task)[0][2]]
    distance = float(np.linalg.norm(np.asarray(goal.x) - np.asarray(outer.start.x)))
    row = {"rotor_mass": rotor_mass, "tension_max": tension_max, "pieces": pieces, "distance": distance}
    t0 = time.perf_counter()
    try:
        move = plan_strike_move(model, control, setup.task.space, setup.task.tendons, goal, goal.x,
                                pieces=pieces, min_duration=0.05, max_duration=0.5, bisections=5)
    except ValueError as exc:
        return {**row, "error": str(exc), "wall_s": time.perf_counter() - t0}
    return {**row, "duration": move.duration, "equivalent_velocity": distance / move.duration,
            "arrival_speed": move.arrival_speed, "tension_range": move.as_dict()["tension_range"],
            "wall_s": time.perf_counter() - t0}


def run_spec(spec: dict):
    """One job on a campaign worker (:func:`soft_arm_experiments.campaigns.engine.map_runs`)."""
    return plan(spec["job"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rotor-masses", type=float, nargs="+", default=[0.6, 0.3, 0.15, 0.0])
    parser.add_argument("--tension-limits", type=float, nargs="+", default=[5.0, 20.0])
    parser.add_argument("--pieces", type=int, nargs="+", default=[3, 6])
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2,
                        help="local Dask workers (default: the number of cores)")
    parser.add_argument("--output", default=results_path("strike_limits.json"))
    args = parser.parse_args(argv)
    jobs = list(itertools.product(args.rotor_masses, args.tension_limits, args.pieces))
    specs = [{"job": list(job)} for job in jobs]
    rows = map_runs(f"{os.path.abspath(__file__)}:run_spec", specs, workers=args.workers)
    print(f"the shortest planned strike move (target {rows[0]['distance'] * 1e3:.0f} mm from the hanging "
          f"arm's task point; the paper's equivalent velocity {PAPER_VELOCITY} m/s)")
    print(f"{'rotor kg':>8s} {'T_max N':>7s} {'pieces':>6s} | {'move s':>6s} {'v_eq m/s':>8s} "
          f"{'tip m/s':>7s} {'tensions N':>12s}")
    for r in rows:
        head = f"{r['rotor_mass']:8.2f} {r['tension_max']:7.1f} {r['pieces']:6d} | "
        if "error" in r:
            print(head + "failed: " + r["error"])
            continue
        lo, hi = r["tension_range"]
        print(head + f"{r['duration']:6.3f} {r['equivalent_velocity']:8.2f} {r['arrival_speed']:7.2f} "
                     f"{lo:5.2f}-{hi:<6.2f}")
    write_results(args.output, {"paper_equivalent_velocity": PAPER_VELOCITY, "moves": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
