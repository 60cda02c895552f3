"""What one run of a campaign is: the functions the workers call, one JSON-ready specification in, one
JSON-ready result out. They run in the worker's process (no subprocess per run), so the compiled
kernels, the models and the fitted actuation maps a worker built for one run serve the next.

- :func:`robustness`: a task on a drawn plant, with the controller unchanged;
- :func:`identification`: the identification experiment simulated on a drawn plant (or a recorded
  bag), fitted, and the triangle run with the identified arm;
- :func:`sweep`: any ``--set`` overrides, with a task's metrics or the arm's workspace as outcome.

A run raises for what it cannot do (a target its model cannot hold, a bag without the topics): the
engine records it as failed with that error.
"""
from __future__ import annotations

import dataclasses
import os
import re
import tempfile
import time

import numpy as np

from .plants import plant_holds, plant_overrides


def task_outcome(result) -> dict:
    """A task run's figures (:class:`~soft_arm_experiments.harness.RunResult`): steady-state
    RMS task error [mm], transitions in the mm band, mm- and cm-band task velocities [m/s], the
    online CLIK's infeasible steps, each goal's status, the track windows' RMS, maximum and
    last-period RMS [mm], and the pendulum's strike."""
    from soft_arm_control.outer_loop import STATUSES
    s = result.summary
    goals = [g for g in result.goals if g["online_steps"]]
    return {"rms_mm": s.rms_error * 1e3, "mm_band": s.reached_mm, "transitions": s.transitions,
            "velocity_mm_band": s.velocity_mm, "velocity_cm_band": s.velocity_cm,
            "infeasible_steps": sum(g["infeasible_steps"] for g in goals),
            "statuses": [g["status"] for g in goals],
            "status_counts": {status: sum(g["status"] == status for g in goals) for status in STATUSES},
            "tracking_rms_mm": [r.rms_error * 1e3 for r in result.tracking],
            "tracking_max_mm": [r.max_error * 1e3 for r in result.tracking],
            "tracking_last_period_rms_mm": [None if r.last_period_rms_error is None
                                            else r.last_period_rms_error * 1e3 for r in result.tracking],
            "strike": None if result.strike is None else {"simulated": result.strike["simulated"]}}


def run_task(task: str, overrides: list, arm_file: str | None = None, accept_closest: bool = False) -> dict:
    """``task`` on the simulated rig with ``overrides`` (``ns.key=value``), as ``soft-arm-harness``
    runs it: :func:`task_outcome`, the run's wall time [s] and, with ``accept_closest``, how far
    [mm] the targets the controller's model cannot hold were moved."""
    from soft_arm_experiments.harness import load_setup, load_setup_at_closest, run_experiment
    moved = []
    if accept_closest:
        setup, notes = load_setup_at_closest(task, overrides=overrides, arm_file=arm_file)
        moved = [float(m) for note in notes for m in re.findall(r"\(([\d.]+) mm away", note)]
    else:
        setup = load_setup(task, overrides=overrides, arm_file=arm_file)
    t0 = time.perf_counter()
    result = run_experiment(setup)
    return {**task_outcome(result), "targets_moved_mm": moved, "simulated_s": result.transitions[-1].end,
            "task_s": time.perf_counter() - t0}


def robustness(spec: dict) -> dict:
    """``spec``: ``task``, ``plant`` (``plant.*`` values of a drawn plant), ``sets`` (further
    overrides). The task with the controller unchanged, and whether the plant itself can hold the
    task's targets (:func:`~.plants.plant_holds`)."""
    overrides = plant_overrides(spec["plant"]) + list(spec.get("sets", ()))
    return {**run_task(spec["task"], overrides), **plant_holds(spec["task"], overrides)}


def identification(spec: dict) -> dict:
    """``spec`` with ``plant`` (a drawn plant with its mocap frame error): the identification
    experiment simulated on it, fitted as ``soft-arm-identify`` fits it, the errors of the estimates
    against the plant, and the triangle run with the identified arm and calibration as the
    controller's model (``--accept-closest``) next to the same run with the plant's true parameters.
    ``spec`` with ``bag`` (a recorded experiment's bag folder): its fit alone (estimates,
    uncertainties, residuals), the truth being unknown."""
    if "bag" in spec:
        return identify_bag(spec["bag"], spec.get("sets", ()))
    return identify_plant(spec["plant"], spec.get("sets", ()))


def identify_bag(bag: str, sets=()) -> dict:
    """The fit of one recorded identification experiment: every estimate with its standard error and
    uncertainty, the tip residual RMS [mm] and the fit's wall time [s]."""
    from soft_arm_experiments.excitation import load_identification, parse_fit
    from soft_arm_experiments.identify_cli import identify, read_recording
    from soft_arm_model import load_arm_config
    from soft_arm_model.parameters import default_config_dir, split_overrides
    groups = split_overrides(list(sets), ("arm", "identification"))
    arm = load_arm_config(os.path.join(default_config_dir(), "arm.yaml"), groups["arm"])
    rec = read_recording(bag, [t.name for t in arm.tendons])
    t0 = time.perf_counter()
    result = identify(rec, arm, parse_fit(load_identification(overrides=groups["identification"])), workers=1)
    fit = result["static"]
    return {"fit_s": time.perf_counter() - t0, "tip_rms_mm": float(fit.marker_rms[-1] * 1e3),
            "estimates": {name: {"value": e.value, "standard_error": e.standard_error,
                                 "uncertainty": e.uncertainty} for name, e in fit.estimates.items()}}


def identify_plant(plant: dict, sets=()) -> dict:
    """See :func:`identification`: errors are relative for E, viscosity and the rotor mass, [g] for the
    tip mass, absolute for friction and offsets, [deg] for the tendon angles (relative to their
    mean: the common turn is the mocap frame's) and the mocap frame (rotation after removing that
    turn, translation [mm]); ``per_uncertainty`` and ``per_standard_error``: how many of each the
    worst of the E, friction, offset and angle errors is."""
    from scipy.spatial.transform import Rotation

    from soft_arm_experiments.excitation import Excitation, load_identification, parse_fit
    from soft_arm_experiments.harness import load_setup
    from soft_arm_experiments.identification_run import simulate_recording
    from soft_arm_experiments.identify_cli import composed_calibration, identify
    from soft_arm_drivers.mocap.bridge_config import load_mocap_config

    overrides = plant_overrides(plant) + list(sets)
    setup = load_setup("identification", overrides=overrides)
    truth = setup.plant.plant_arm(setup.arm)
    t0 = time.perf_counter()
    rec = simulate_recording(setup, Excitation(setup.excitation, len(setup.arm.tendons)))
    t1 = time.perf_counter()
    result = identify(rec, setup.arm, parse_fit(load_identification()), workers=1)
    fit_s = time.perf_counter() - t1
    fit, dyn = result["static"], result["dynamic"]
    pairs = list(zip(fit.arm.tendons, truth.tendons))
    turn = float(np.mean([a.start_angle - b.start_angle for a, b in pairs]))
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
        "friction": max(abs(a.friction - b.friction) for a, b in pairs),
        "offset_fraction": max(abs(a.offset_fraction - b.offset_fraction) for a, b in pairs),
        "angle_deg": float(np.degrees(max(max(abs(a.start_angle - b.start_angle - turn),
                                              abs(a.end_angle - b.end_angle - turn)) for a, b in pairs))),
        "frame_rotation_deg": float(np.degrees(frame_rot)), "frame_translation_mm": float(frame_t * 1e3),
    }
    ratios = [(abs(fit.arm.material.youngs_modulus - truth.material.youngs_modulus),
               fit.estimates["youngs_modulus"])]
    for group, shifted in (("friction", 0.0), ("offset_fraction", 0.0), ("start_angle", turn),
                           ("end_angle", turn)):
        ratios += [(abs(getattr(a, group) - getattr(b, group) - shifted), fit.estimates[f"{group}[{a.name}]"])
                   for a, b in pairs]
    errors["per_uncertainty"] = max(err / e.uncertainty for err, e in ratios)
    errors["per_standard_error"] = max(err / e.standard_error for err, e in ratios)
    check = result["report"]["basis_check"]
    out = {"experiment_s": t1 - t0, "fit_s": fit_s, "errors": errors,
           "basis_kept": "check" if check.get("kept") else "fit" if "kept" in check else "failed",
           "tip_rms_mm": float(fit.marker_rms[-1] * 1e3),
           "plant_holds": plant_holds("triangle", overrides)["plant_holds"]}
    recorded = load_mocap_config().calibration
    out["triangle"] = _triangle_with(fit.arm, composed_calibration(fit.registration, recorded), overrides)
    # the plant's true parameters on the controller's strain basis (the fit's): what a perfect
    # identification would give, so that a figure the identified arm misses is told from one the
    # plant itself cannot make
    true_arm = dataclasses.replace(truth, discretisation=setup.arm.discretisation)
    out["triangle_true"] = _triangle_with(true_arm, composed_calibration(true_registration(plant), recorded),
                                          overrides)
    return out


def true_registration(plant: dict):
    """The mocap frame to arm_base of a plant whose markers arrive as R p + t (its frame error)."""
    from scipy.spatial.transform import Rotation

    from soft_arm_model.identification import Registration
    R = Rotation.from_rotvec(np.radians(plant["mocap.frame_error.rotation_deg"])).as_matrix()
    return Registration(R.T, -R.T @ np.asarray(plant["mocap.frame_error.translation"], dtype=float))


def _triangle_with(arm, calibration, overrides: list) -> dict:
    """The triangle on the plant of ``overrides`` with ``arm`` and its mocap ``calibration`` as the
    controller's model (``--arm-file``, ``--accept-closest``); an error string when it cannot run."""
    from soft_arm_experiments.identify_cli import write_identified_arm
    from soft_arm_model.parameters import ConfigError
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "arm.yaml")
        write_identified_arm(path, arm, calibration)
        try:
            return {"ok": True, **run_task("triangle", overrides, arm_file=path, accept_closest=True)}
        except (ConfigError, ValueError) as exc:
            return {"ok": False, "error": str(exc)}


def sweep(spec: dict) -> dict:
    """``spec``: ``sets`` (the sample's overrides) and ``outcome``: a task's name (its figures, as
    :func:`robustness` reports them, with ``--accept-closest`` when ``accept_closest``), or
    ``workspace`` (the equilibria of the arm over ``levels`` [N] on every tendon:
    :func:`workspace_outcome`)."""
    sets = list(spec.get("sets", ()))
    if spec["outcome"] == "workspace":
        return workspace_outcome(sets, spec["levels"])
    return run_task(spec["outcome"], sets, accept_closest=spec.get("accept_closest", False))


def workspace_outcome(sets: list, levels) -> dict:
    """The tip workspace of the arm of ``arm.yaml`` with the ``arm.*`` overrides of ``sets``: the
    equilibria on the tension grid ``levels`` [N] per tendon (with friction), how many converged,
    the tip's extent per axis [m] in arm_base, its largest distance from the axis [m] and its
    highest point [m]."""
    from soft_arm_model import build_model, load_arm_config
    from soft_arm_model.parameters import default_config_dir, split_overrides
    from soft_arm_model.workspace import sample_workspace
    groups = split_overrides(sets, ("arm",))
    model = build_model(load_arm_config(os.path.join(default_config_dir(), "arm.yaml"), groups["arm"]))
    ws = sample_workspace(model, levels)
    tips = ws.tip[ws.converged]
    if not len(tips):
        raise ValueError(f"no equilibrium converged over the levels {list(levels)} N")
    return {"samples": int(ws.converged.size), "converged": int(ws.converged.sum()),
            "tip_min_m": tips.min(axis=0).tolist(), "tip_max_m": tips.max(axis=0).tolist(),
            "reach_m": float(np.hypot(tips[:, 0], tips[:, 1]).max()), "highest_m": float(tips[:, 2].max())}
