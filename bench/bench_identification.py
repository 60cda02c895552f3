"""Identification benchmark: the arm identified from the simulated identification experiment of
many randomly drawn plants, then the triangle task run with the identified arm as the controller's
model on the same plant. Prints a table per draw and the worst errors, writes JSON.

    python bench/bench_identification.py [--draws 4] [--seed 0] [--jobs 2]
                                         [--output bench/results/identification.json]

Plants: the robustness benchmark's draws (``bench_robustness.draw_plant``: E and viscosity +-20 %,
density +-5 %, angles +-3 deg, offsets 0.55-0.65, friction 0.05-0.2, order 3-5 with or without
shear, 0-5 g at the tip) with a mocap calibration error of up to 1.5 deg per axis and 5 mm per
axis, and the structurally different arm ``bench_robustness.STRUCTURAL_PLANT`` as draw ``structural``. The
experiment is ``identification.yaml``'s, played on the ROS-free simulated rig
(:func:`soft_arm_drivers.experiments.identification_run.simulate_recording`: the plant's dynamics,
encoder quantisation, mocap noise and latency; the graph records the same series, minutes slower),
fitted as ``soft-arm-identify`` fits it (one core per draw: ``--jobs`` draws at a time).
Reported per draw: the errors of E, viscosity, rotor mass, tip mass [g], friction, offsets,
tendon angles (relative to their mean: the common turn is the mocap frame's), the mocap frame
(rotation after removing that turn, translation), which basis gave the estimates (``fit``:
``identification.fit``'s, ``check``: the basis check's, the one with the lower weighted
residual), how many uncertainties (``/unc``: standard error
and basis shift together) and how many standard errors alone (``/se``) the worst of the E,
friction, offset and angle errors is, the fit's wall time, whether the plant can hold
the triangle's targets at all (``bench_robustness.plant_holds``: the triangle's goal is judged on
those plants only), and the triangle run with
the identified arm and its mocap calibration (``soft-arm-harness triangle --arm-file
--accept-closest``): RMS error, mm band, mm-band velocity, and how far the targets the identified
model cannot hold within ``control.clik.closest_margin`` of the tension limits were moved; then
the same run with the plant's true parameters (and true mocap calibration) as the controller's
model, on the controller's strain basis: what a perfect identification would give, so that a
figure the identified arm misses is told from one the plant itself cannot make.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from scipy.spatial.transform import Rotation

from bench_robustness import STRUCTURAL_PLANT, draw_plant, plant_holds
from timing import results_path, run_harness, write_results

FRAME_ROTATION_DEG = 1.5      # per axis, uniform
FRAME_TRANSLATION = 0.005     # m per axis, uniform
STRUCTURAL_FRAME = {"mocap.frame_error.rotation_deg": [0.0, 1.2, 1.6],
                    "mocap.frame_error.translation": [0.003, -0.004, 0.0]}


def draw_frame(rng: np.random.Generator) -> dict:
    return {"mocap.frame_error.rotation_deg": [round(float(a), 3) for a in rng.uniform(-1.5, 1.5, 3)],
            "mocap.frame_error.translation": [round(float(a), 4) for a in rng.uniform(-0.005, 0.005, 3)]}


def identify_one(plant: dict) -> dict:
    """Identification experiment, fit and errors on one plant; then the triangle with the fit."""
    from soft_arm_drivers.experiments.excitation import Excitation, load_identification, parse_fit
    from soft_arm_drivers.experiments.harness import load_setup
    from soft_arm_drivers.experiments.identification_run import simulate_recording
    from soft_arm_drivers.experiments.identify_cli import composed_calibration, identify
    from soft_arm_drivers.mocap.bridge_config import load_mocap_config

    overrides = [f"plant.{key}={json.dumps(value)}" for key, value in plant.items()]
    setup = load_setup("identification", overrides=overrides)
    truth = setup.plant.plant_arm(setup.arm)
    t0 = time.perf_counter()
    rec = simulate_recording(setup, Excitation(setup.excitation, len(setup.arm.tendons)))
    t1 = time.perf_counter()
    result = identify(rec, setup.arm, parse_fit(load_identification()), workers=1)
    fit_s = time.perf_counter() - t1
    fit, dyn = result["static"], result["dynamic"]
    turn = float(np.mean([a.start_angle - b.start_angle for a, b in zip(fit.arm.tendons, truth.tendons)]))
    undo = Rotation.from_rotvec([0.0, 0.0, turn]) * Rotation.from_rotvec(
        np.radians(plant["mocap.frame_error.rotation_deg"])).inv()
    frame_rot = (Rotation.from_matrix(fit.registration.rotation) * undo.inv()).magnitude()
    frame_t = np.linalg.norm(fit.registration.translation
                             + undo.apply(plant["mocap.frame_error.translation"]))
    errors = {
        "youngs_modulus": fit.arm.material.youngs_modulus / truth.material.youngs_modulus - 1,
        "viscosity": dyn.viscosity.value / truth.material.viscosity - 1,
        "rotor_mass": dyn.rotor_mass.value / setup.plant.rotor_mass - 1,
        "tip_mass_g": (fit.arm.tip_mass - truth.tip_mass) * 1e3,
        "friction": max(abs(a.friction - b.friction) for a, b in zip(fit.arm.tendons, truth.tendons)),
        "offset_fraction": max(abs(a.offset_fraction - b.offset_fraction)
                               for a, b in zip(fit.arm.tendons, truth.tendons)),
        "angle_deg": float(np.degrees(max(max(abs(a.start_angle - b.start_angle - turn),
                                              abs(a.end_angle - b.end_angle - turn))
                                          for a, b in zip(fit.arm.tendons, truth.tendons)))),
        "frame_rotation_deg": float(np.degrees(frame_rot)), "frame_translation_mm": float(frame_t * 1e3),
    }
    # how many uncertainties (standard error and basis shift) and how many standard errors alone
    # the worst of the E, friction, offset and angle errors is
    ratios = [(abs(fit.arm.material.youngs_modulus - truth.material.youngs_modulus),
               fit.estimates["youngs_modulus"])]
    for group, shifted in (("friction", 0.0), ("offset_fraction", 0.0), ("start_angle", turn),
                           ("end_angle", turn)):
        ratios += [(abs(getattr(a, group) - getattr(b, group) - shifted), fit.estimates[f"{group}[{a.name}]"])
                   for a, b in zip(fit.arm.tendons, truth.tendons)]
    errors["per_uncertainty"] = max(err / e.uncertainty for err, e in ratios)
    errors["per_standard_error"] = max(err / e.standard_error for err, e in ratios)
    check = result["report"]["basis_check"]
    out = {"experiment_s": t1 - t0, "fit_s": fit_s, "errors": errors,
           "basis_kept": "check" if check.get("kept") else "fit" if "kept" in check else "failed",
           "tip_rms_mm": float(fit.marker_rms[-1] * 1e3),
           "plant_holds": plant_holds("triangle", overrides)["plant_holds"]}
    calibration = composed_calibration(fit.registration, load_mocap_config().calibration)
    out["triangle"] = triangle_with(fit.arm, calibration, overrides)
    # the same run with the plant's true parameters (on the controller's basis, the one the fit
    # returns) and its true mocap calibration: what a perfect identification would give, so that
    # a figure the identified arm misses is told from one the plant itself cannot make
    true_arm = dataclasses.replace(truth, discretisation=setup.arm.discretisation)
    out["triangle_true"] = triangle_with(true_arm, composed_calibration(true_registration(plant),
                                                                        load_mocap_config().calibration),
                                         overrides)
    return out


def true_registration(plant: dict):
    """The mocap frame to arm_base of a plant whose markers arrive as R p + t (its frame error)."""
    from soft_arm_model.identification import Registration
    R = Rotation.from_rotvec(np.radians(plant["mocap.frame_error.rotation_deg"])).as_matrix()
    return Registration(R.T, -R.T @ np.asarray(plant["mocap.frame_error.translation"], dtype=float))


def triangle_with(arm, calibration, overrides: list) -> dict:
    """The triangle on the plant of ``overrides`` with ``arm`` and its mocap ``calibration`` as the
    controller's model (``soft-arm-harness triangle --arm-file --accept-closest``)."""
    from soft_arm_drivers.experiments.identify_cli import write_identified_arm
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "arm.yaml")
        write_identified_arm(path, arm, calibration)
        t0 = time.perf_counter()
        proc = run_harness("triangle", overrides, "--arm-file", path, "--accept-closest")
        elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"ok": False, "error": proc.stderr.strip().splitlines()[-1:], "run_s": elapsed}
    s = json.loads(proc.stdout)["summary"]
    # targets the model cannot hold with control.clik.closest_margin, moved by --accept-closest: how far [mm]
    moved = [float(m) for m in re.findall(r"\(([\d.]+) mm away", proc.stderr)]
    return {"ok": True, "rms_mm": s["rms_error"] * 1e3, "mm_band": s["reached_mm"],
            "transitions": s["transitions"], "velocity_mm_band": s["velocity_mm"],
            "velocity_cm_band": s["velocity_cm"], "targets_moved_mm": moved, "run_s": elapsed}


def format_triangle(tri: dict) -> str:
    """RMS [mm], transitions in the mm band, mm-band velocity [m/s], farthest moved target [mm]."""
    if not tri["ok"]:
        return f" failed: {' '.join(tri['error'])}"
    return (f" {tri['rms_mm']:7.2f} {tri['mm_band']:4d}/{tri['transitions']:<3d} "
            f"{tri['velocity_mm_band'] or 0:6.3f} {max(tri['targets_moved_mm'], default=0.0):8.1f}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--output", default=results_path("identification.json"))
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    plants = [{**STRUCTURAL_PLANT, **STRUCTURAL_FRAME}]
    plants += [{**draw_plant(rng), **draw_frame(rng)} for _ in range(args.draws)]
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(identify_one, plants))
    runs = [{"draw": i - 1 if i else "structural", "plant": p, **r}
            for i, (p, r) in enumerate(zip(plants, results))]
    print(f"{'draw':>5s} {'E %':>6s} {'visc %':>6s} {'rotor %':>7s} {'tip g':>6s} {'fric':>6s} "
          f"{'offs':>6s} {'ang deg':>7s} {'frame deg':>9s} {'mm':>5s} {'basis':>6s} {'/unc':>5s} {'/se':>5s} "
          f"{'fit s':>6s} | "
          f"{'holds':>5s} {'RMS mm':>7s} {'mm band':>8s} {'v_mm':>6s} {'moved mm':>8s} | true parameters: "
          f"{'RMS mm':>7s} {'mm band':>8s} {'v_mm':>6s} {'moved mm':>8s}")
    for r in runs:
        e = r["errors"]
        print(f"{r['draw']!s:>5s} {e['youngs_modulus'] * 100:6.2f} {e['viscosity'] * 100:6.1f} "
              f"{e['rotor_mass'] * 100:7.2f} {e['tip_mass_g']:6.2f} {e['friction']:6.3f} "
              f"{e['offset_fraction']:6.3f} {e['angle_deg']:7.2f} {e['frame_rotation_deg']:9.2f} "
              f"{e['frame_translation_mm']:5.2f} {r['basis_kept']:>6s} {e['per_uncertainty']:5.1f} "
              f"{e['per_standard_error']:5.1f} {r['fit_s']:6.1f} | {'yes' if r['plant_holds'] else 'no':>5s}"
              + format_triangle(r["triangle"]) + " |" + " " * 17 + format_triangle(r["triangle_true"]))
    worst = {k: max(abs(r["errors"][k]) for r in runs) for k in runs[0]["errors"]}
    # the triangle's goal applies to the plants that can hold its targets at all (as in
    # bench_robustness): on the others no model makes the arm reach them
    holding = [r for r in runs if r["plant_holds"]]
    done = [r["triangle"] for r in holding if r["triangle"]["ok"]]
    # the identified arm against the plant's true parameters, run for run: mm-band velocity ratio
    paired = [(r["triangle"], r["triangle_true"]) for r in holding
              if r["triangle"]["ok"] and r["triangle_true"]["ok"]
              and r["triangle"]["velocity_mm_band"] and r["triangle_true"]["velocity_mm_band"]]
    summary = {"worst_errors": worst, "fit_s_max": max(r["fit_s"] for r in runs),
               "triangle_rms_mm_median": float(np.median([t["rms_mm"] for t in done])) if done else None,
               "triangle_rms_mm_worst": max((t["rms_mm"] for t in done), default=None),
               "triangle_mm_band_worst": min((t["mm_band"] for t in done), default=None),
               "triangle_velocity_mm_band_worst": min((t["velocity_mm_band"] or 0.0 for t in done),
                                                      default=None),
               "velocity_mm_band_identified_over_true_worst": min(
                   (a["velocity_mm_band"] / b["velocity_mm_band"] for a, b in paired), default=None),
               "triangle_failed": sum(not r["triangle"]["ok"] for r in runs),
               "plants_holding": len(holding)}
    print("worst: " + ", ".join(f"{k} {v:.4g}" for k, v in worst.items()))
    print(f"fit <= {summary['fit_s_max']:.1f} s; on the {summary['plants_holding']} plants that hold the "
          f"triangle's targets: triangle RMS median {summary['triangle_rms_mm_median']} mm, "
          f"worst {summary['triangle_rms_mm_worst']} mm, mm band worst {summary['triangle_mm_band_worst']}, "
          f"mm-band velocity worst {summary['triangle_velocity_mm_band_worst']} m/s "
          f"(identified / true parameters, worst: {summary['velocity_mm_band_identified_over_true_worst']}), "
          f"failed {summary['triangle_failed']}")
    write_results(args.output, {"seed": args.seed, "summary": summary, "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
