"""Sensing benchmark: the shape estimate against the simulator's truth, and the closed loop on each
feedback (mocap, fused, estimate) under four mocap scenarios; prints tables, writes JSON.

    python bench/bench_sensing.py [--tasks triangle coiling] [--feedbacks mocap fused estimate]
                                  [--scenarios clean realistic heavy lost] [--workers 2]
                                  [--output bench/results/sensing.json]
    python bench/bench_sensing.py --draws 10 [--tasks triangle] [--output bench/results/sensing_draws.json]

With ``--draws``, each blind run (no marker, the loop on the estimate) is printed beside the same run
holding the precomputed references (``hold``: on the mocap, without a marker), and beside a hold on
the plant's twin (its Young's modulus scale 1e-6 larger, ``TWIN``). A plant far from its model may
have more than one equilibrium under one reference (the crossed tendons' branches, the tendons'
friction): which one a transition ends on is then decided by the last micrometre of the state
before it, and the twin's hold shows where that is so. ``worse`` is the largest amount [mm] by which
a transition's final error on the estimate exceeds the worse of the two holds'; ``flips`` counts
the transitions whose holds end more than ``FLIP`` apart; ``refused`` counts the trust region's
refusals. ``--seeds`` runs chosen draws instead of the first N.

Without ``--draws``, the filters of :data:`FILTERS` are compared besides (``filters``): the first
task, blind, its loop holding the precomputed references (the same motion for each filter), the
tip's error in motion and at rest and its mean NEES in motion and at rest.

Scenarios (``plant.mocap.occlusion``): *clean*, no occlusion; *realistic*, the declared plant's
(the cameras' lines of sight against the arm's body, 1 % dropouts); *heavy*, realistic with the
tip marker lost 30 % of the time in 0.5 s bursts; *lost*, realistic until the end of the first
target's window, then no marker at all; *blind*, no marker ever (the tendons alone from the start:
no marker has corrected the learnt stiffness and friction). Every run is on the declared plant
(plant.yaml) with the controller's model, its figures on the plant's true markers (a lost mocap
measures nothing), and beside them as the mocap measured them (``measured``: the README's kind,
the markers' noise in it; none when a window was never seen).

The estimate's error is per marker, RMS, median, 95th percentile and maximum, at rest (the true tip
slower than 5 mm/s) and in motion, from the estimator's first second on (the *lost* runs: from the
mocap's loss, when the estimator has the tendons alone). The estimate's consistency: the fraction
of frames whose tip NEES is above the chi-square 99 % bound (3 degrees of freedom), and its mean (3
for an honest filter).
"""
from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

import numpy as np

from soft_arm_experiments.campaigns.engine import map_runs
from timing import results_path, write_results

REST_SPEED = 0.005        # m/s: the true tip slower than this is at rest
TWIN = 1e-6               # relative change of the plant's Young's modulus scale in the hold's twin
FLIP = 0.001              # m: holds whose transitions end further apart than this flipped
CHI2_99 = 11.345          # chi-square, 3 degrees of freedom, 99 %
SCENARIOS = {
    "clean": ["plant.mocap.occlusion.enabled=false"],
    "realistic": [],
    "heavy": ["plant.mocap.occlusion.bursts.fraction=[0.0, 0.0, 0.0, 0.3]",
              "plant.mocap.occlusion.bursts.duration=0.5"],
    "lost": None,           # blackout from the end of the first window, set per task
    "blind": ["plant.mocap.occlusion.blackout=[0.0, 1.0e6]"],
}
# The filters compared on the tendons alone (``filters`` in the output): the static balance, the
# dynamics with the casting tolerance's routing considered (estimator.yaml's priors), and the
# dynamics sure of the drawing's routing (what the declared plant, whose tendons run on their drawn
# paths, would allow a filter told so).
FILTERS = {
    "static": ["estimator.process_model=static"],
    "dynamic": ["estimator.process_model=dynamic"],
    "dynamic_routing_exact": ["estimator.process_model=dynamic", "estimator.prior.tendon_offset=0.0",
                              "estimator.prior.tendon_angle=0.0"],
}


def _sets(task: str, scenario: str) -> list:
    if scenario != "lost":
        return SCENARIOS[scenario]
    from soft_arm_experiments.harness import load_setup, schedule
    first = schedule(load_setup(task).task)[0][3]
    return [f"plant.mocap.occlusion.blackout=[{first}, 1.0e6]"]


def _errors(rec: dict, select) -> dict:
    """Per marker RMS, median, 95th percentile and maximum [m] of the estimate's error on the
    frames ``select``."""
    err = np.linalg.norm(rec["markers_estimated"] - rec["markers_true"], axis=2)[select]
    if not err.size:
        return {"frames": 0}
    return {"frames": int(err.shape[0]), "rms": np.sqrt(np.mean(err ** 2, axis=0)).tolist(),
            "max": err.max(axis=0).tolist(), "median": np.median(err, axis=0).tolist(),
            "p95": np.percentile(err, 95, axis=0).tolist()}


def _measured(task, result) -> dict:
    """The run's figures as the mocap measured them (the README's and Table 1's kind, the markers'
    noise in them), or why there are none (a window the mocap never saw)."""
    from soft_arm_experiments.harness import window_metrics
    from soft_arm_experiments.metrics import summarise
    try:
        s = summarise(window_metrics(task, result.transitions, result.record)[0])
    except ValueError as exc:
        return {"none": str(exc)}
    return {"rms_error": s.rms_error, "reached_mm": s.reached_mm, "velocity_mm": s.velocity_mm,
            "velocity_cm": s.velocity_cm}


def _figures(result, after) -> dict:
    """A run's closed-loop figures (on the plant's truth) and its estimate's, on the frames from
    ``after`` (a function of the mocap times [s] to a bool mask) on."""
    rec = result.record.arrays()
    s = result.summary
    t = rec["t_mocap"]
    speed = np.linalg.norm(np.gradient(rec["markers_true"][:, -1], t, axis=0), axis=1)
    kept = after(t)
    diff = rec["markers_estimated"][:, -1] - rec["markers_true"][:, -1]
    nees = np.einsum("ki,kij,kj->k", diff, np.linalg.inv(rec["marker_covariance"][:, -1]), diff)
    rest = kept & (speed < REST_SPEED)
    moving = kept & (speed >= REST_SPEED)
    return {"rms_error": s.rms_error, "reached_mm": s.reached_mm, "reached_cm": s.reached_cm,
            "transitions": s.transitions, "velocity_mm": s.velocity_mm, "velocity_cm": s.velocity_cm,
            "statuses": sorted({g["status"] for g in result.goals}),
            "seen": rec["markers_seen"].mean(axis=0).tolist(),
            "estimate_at_rest": _errors(rec, rest),
            "estimate_moving": _errors(rec, moving),
            "tip_nees_mean": float(nees[kept].mean()),
            "tip_nees_above_99": float(np.mean(nees[kept] > CHI2_99)),
            "tip_nees_rest_mean": float(nees[rest].mean()) if rest.any() else None,
            "tip_nees_moving_mean": float(nees[moving].mean()) if moving.any() else None}


def run_spec(spec: dict) -> dict:
    """One run on a campaign worker: the closed loop and the estimate's figures."""
    from soft_arm_experiments.harness import load_setup, run_experiment
    t0 = time.perf_counter()
    setup = load_setup(spec["task"], overrides=spec["sets"], feedback=spec["feedback"])
    result = run_experiment(setup, estimate=True, truth=True)
    lost_at = spec["lost_at"] if spec["scenario"] == "lost" else 0.0
    return {**{k: spec[k] for k in ("task", "feedback", "scenario")},
            **_figures(result, lambda t: (t >= 1.0) & (t >= lost_at)),
            "measured": _measured(setup.task, result), "wall_s": time.perf_counter() - t0}


def _blind(task: str, overrides: list, twin: list, arm_file=None) -> dict:
    """``task`` without a marker, closed on the estimate, with the controller's (and estimator's)
    model of ``arm_file`` (None: arm.yaml); targets its model cannot hold moved to the closest it
    can (``--accept-closest``). Beside it, ``hold``: the same run on the mocap, which without a
    marker takes no online step and holds the precomputed references (what closing the loop on the
    estimate must never be worse than), on the plant of ``overrides`` and on its ``twin`` (overrides
    of the plant 1e-6 away: ``hold_twin``); ``finals`` [m], each transition's final error on the
    truth, ``online_steps`` per goal, and ``distrusts``, the trust region's refusals."""
    from soft_arm_experiments.harness import load_setup_at_closest, run_experiment
    runs = {}
    for name, feedback, sets in (("blind", "estimate", overrides), ("hold", "mocap", overrides),
                                 ("hold_twin", "mocap", twin)):
        setup, moved = load_setup_at_closest(task, overrides=sets + SCENARIOS["blind"],
                                             arm_file=arm_file, feedback=feedback)
        runs[name] = run_experiment(setup, estimate=True, truth=True)
    blind = runs["blind"]
    return {**_figures(blind, lambda t: t >= 1.0), "targets_moved": len(moved),
            "finals": [m.final_error for m in blind.metrics],
            "online_steps": [g["online_steps"] for g in blind.goals],
            "distrusts": sum(g["distrusts"] for g in blind.goals),
            **{name: {"rms_error": runs[name].summary.rms_error,
                      "finals": [m.final_error for m in runs[name].metrics]}
               for name in ("hold", "hold_twin")}}


def _versus_hold(f: dict) -> tuple[float, int]:
    """(the largest amount [m] by which a transition of the blind run ``f`` (:func:`_blind`) ended
    further from its target than the worse of the two holds, the number of transitions whose holds
    ended more than ``FLIP`` apart)."""
    hold, twin = np.array(f["hold"]["finals"]), np.array(f["hold_twin"]["finals"])
    worse = float(np.max(np.array(f["finals"]) - np.maximum(hold, twin)))
    return worse, int(np.sum(np.abs(hold - twin) > FLIP))


def run_draw(spec: dict) -> dict:
    """One plant of the robustness campaign's draws (``seed``, with its mocap calibration error):
    the identification experiment simulated on it and fitted as ``soft-arm-identify`` fits it, then
    ``task`` blind (the tendons alone) with the controller's model, the estimator told the
    tolerances' spread (:func:`~soft_arm_experiments.campaigns.plants.estimator_priors`), and with
    the identified arm as soft-arm-identify writes it, the estimator told the identified payload's
    uncertainty (the report's ``estimator_priors``)."""
    import tempfile

    from soft_arm_experiments.campaigns.plants import (draw_frame, draw_plant, estimator_priors,
                                                       load_tolerances, plant_overrides)
    from soft_arm_experiments.excitation import Excitation, load_identification, parse_fit
    from soft_arm_experiments.harness import load_setup
    from soft_arm_experiments.identification_run import simulate_recording
    from soft_arm_experiments.identify_cli import composed_calibration, identify, write_identified_arm
    from soft_arm_drivers.mocap.bridge_config import load_mocap_config
    t0 = time.perf_counter()
    tolerances = load_tolerances()
    plant = {**draw_plant(spec["seed"], tolerances), **draw_frame(spec["seed"], tolerances)}
    process = [f"estimator.process_model={spec['process_model']}"]
    overrides = plant_overrides(plant) + process
    setup = load_setup("identification", overrides=overrides)
    rec = simulate_recording(setup, Excitation(setup.excitation, len(setup.arm.tendons)))
    result = identify(rec, setup.arm, parse_fit(load_identification()), workers=1)
    fit = result["static"]
    # what the estimator is told the plant may be: the tolerances' spread about the drawing, or (in
    # the identified arm's file) the identified payload's uncertainty
    twin = plant_overrides({**plant, "youngs_modulus_scale": plant["youngs_modulus_scale"] * (1.0 + TWIN)})
    twin += process
    priors = estimator_priors(tolerances, setup.arm)
    out = {"seed": spec["seed"], "task": spec["task"], "plant": plant,
           "model": _blind(spec["task"], overrides + priors, twin + priors)}
    out["identified_priors"] = priors = result["report"]["estimator_priors"]
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "arm.yaml")
        calibration = composed_calibration(fit.registration, load_mocap_config().calibration)
        write_identified_arm(path, fit.arm, calibration, priors=priors)
        out["identified"] = _blind(spec["task"], overrides, twin, path)
    return {**out, "wall_s": time.perf_counter() - t0}


def _tip(e: dict, worst: bool = False) -> str:
    """The tip's median/p95(/max) of :func:`_errors` [mm]."""
    if not e["frames"]:
        return "-"
    out = f"{1e3 * e['median'][-1]:.2f}/{1e3 * e['p95'][-1]:.2f}"
    return out + (f"/{1e3 * e['max'][-1]:.0f}" if worst else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["triangle", "coiling"])
    parser.add_argument("--feedbacks", nargs="+", default=["mocap", "fused", "estimate"])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2,
                        help="local Dask workers (default: the number of cores)")
    parser.add_argument("--draws", type=int, default=0,
                        help="instead: this many plants of the robustness campaign's draws (seeds 0..N-1), "
                             "each identified, then the first of --tasks blind with the controller's "
                             "model and with the identified arm (default output sensing_draws.json)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help="with the draws' output: these draws' seeds instead of 0..N-1")
    parser.add_argument("--process-model", choices=["static", "dynamic"], default=None,
                        help="the shape estimate's process model (default: config/estimator.yaml's)")
    parser.add_argument("--output", default=None)
    args = parser.parse_args(argv)
    if args.process_model is None:
        from soft_arm_control.shape_estimation import load_estimator_config
        args.process_model = load_estimator_config().process_model
    if args.draws or args.seeds:
        return _draws(args)
    args.output = args.output or results_path("sensing.json")
    from soft_arm_experiments.harness import load_setup, schedule
    specs = []
    for task, scenario, feedback in itertools.product(args.tasks, args.scenarios, args.feedbacks):
        lost_at = schedule(load_setup(task).task)[0][3]
        specs.append({"task": task, "scenario": scenario, "feedback": feedback,
                      "sets": _sets(task, scenario) + [f"estimator.process_model={args.process_model}"],
                      "lost_at": lost_at})
    # the filters compared: the first task, blind, its loop holding the precomputed references (on
    # the mocap, which sees nothing), so that every filter watches the same motion; a run the table
    # above already has is taken from it
    table = len(specs)
    index = {(s["task"], s["scenario"], s["feedback"], tuple(s["sets"])): i for i, s in enumerate(specs)}
    compared = {}
    for name, sets in FILTERS.items():
        spec = {"task": args.tasks[0], "scenario": "blind", "feedback": "mocap",
                "sets": SCENARIOS["blind"] + sets, "lost_at": 0.0}
        key = (spec["task"], "blind", "mocap", tuple(spec["sets"]))
        if key not in index:
            index[key] = len(specs)
            specs.append(spec)
        compared[name] = index[key]
    results = map_runs(f"{os.path.abspath(__file__)}:run_spec", specs, workers=args.workers)
    rows = results[:table]
    filters = {name: results[i] for name, i in compared.items()}
    print(f"{'task':9} {'scenario':10} {'feedback':9} {'RMS mm':>7} {'mocap':>6} {'mm band':>8} "
          f"{'v_mm m/s':>9} "
          f"{'tip est. rest mm (median/p95)':>30} {'moving (median/p95/max)':>24} {'NEES':>5}  statuses")
    for r in rows:
        rest, moving = r["estimate_at_rest"], r["estimate_moving"]
        v = "-" if r["velocity_mm"] is None else f"{r['velocity_mm']:.3f}"
        measured = r["measured"].get("rms_error")
        measured = "-" if measured is None else f"{1e3 * measured:.3f}"
        print(f"{r['task']:9} {r['scenario']:10} {r['feedback']:9} {1e3 * r['rms_error']:7.3f} {measured:>6} "
              f"{r['reached_mm']:>3}/{r['transitions']:<4} {v:>9} {_tip(rest):>30} "
              f"{_tip(moving, True):>24} "
              f"{r['tip_nees_mean']:5.2f}  {', '.join(r['statuses'])}")
    print(f"\n{args.tasks[0]}, blind, the references held: {'filter':22} "
          f"{'tip in motion mm (median/p95)':>30} {'at rest (median)':>17} {'NEES moving / at rest':>22}")
    for name, f in filters.items():
        print(f"{'':38}{name:22} {_tip(f['estimate_moving']):>30} "
              f"{1e3 * f['estimate_at_rest']['median'][-1]:17.2f} "
              f"{f['tip_nees_moving_mean']:>14.2f} / {f['tip_nees_rest_mean']:.2f}")
    write_results(args.output, {"runs": rows, "filters": filters, "rest_speed": REST_SPEED,
                                "process_model": args.process_model})
    return 0


def _draws(args) -> int:
    seeds = args.seeds or range(args.draws)
    specs = [{"seed": seed, "task": args.tasks[0], "process_model": args.process_model} for seed in seeds]
    rows = map_runs(f"{os.path.abspath(__file__)}:run_draw", specs, workers=args.workers)
    print(f"{'seed':>4} {'model':10} {'RMS mm':>7} {'hold mm':>7} {'worse':>6} {'flips':>5} {'refused':>7} "
          f"{'mm band':>8} {'tip est. rest mm (median/p95/max)':>34} {'NEES rest':>9} {'NEES all':>8}")
    for r in rows:
        for which in ("model", "identified"):
            f = r[which]
            nees = "-" if f["tip_nees_rest_mean"] is None else f"{f['tip_nees_rest_mean']:.2f}"
            worse, flips = _versus_hold(f)
            hold = f["hold"]["rms_error"]
            print(f"{r['seed']:>4} {which:10} {1e3 * f['rms_error']:7.3f} {1e3 * hold:7.3f} "
                  f"{1e3 * worse:6.2f} {flips:>5} {f['distrusts']:>7} "
                  f"{f['reached_mm']:>3}/{f['transitions']:<4} "
                  f"{_tip(f['estimate_at_rest'], True):>34} {nees:>9} {f['tip_nees_mean']:8.2f}")
    worst = {which: max(r[which]["estimate_at_rest"]["median"][-1] for r in rows)
             for which in ("model", "identified")}
    print("worst median tip error at rest [mm]: " + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in worst.items()))
    write_results(args.output or results_path("sensing_draws.json"),
                  {"draws": rows, "rest_speed": REST_SPEED, "process_model": args.process_model})
    return 0


if __name__ == "__main__":
    sys.exit(main())
