"""``soft-arm-identify BAG_DIR``: the arm identified from a recorded identification experiment.

Reads only what a rig records (``tendon/state``: shortenings and applied tensions;
``tendon/command``: where tensions were held; ``mocap/markers``) and the arm description it starts
from (``--arm-file``, default the configuration's ``arm.yaml``). The quasi-static plateaus give
Young's modulus, density, the mass at the tip, per-tendon friction, offsets and angles, the encoder
zeros and the mocap registration (:func:`soft_arm_model.identification.identify_static`); the
steps and chirps between plateaus give the viscosity and the rotors' reflected mass
(:func:`soft_arm_model.dynamic_identification.identify_dynamics`). Prints every estimate with its
standard error (the noise's share), its basis shift (how far refitting on the richer basis of
``identification.fit.basis_check`` moves it: the model's share) and the residual RMS per marker;
``--output FILE`` writes the identified arm (the schema of ``arm.yaml``, with
``rig.mocap.calibration`` corrected, and ``estimator.prior``: the tip mass's uncertainty,
:func:`identified_priors`) for ``--arm-file`` and ``--params-file``; ``--json`` prints the report
as JSON; ``--plot DIR`` draws measured against predicted markers and shortenings, the hysteresis
loops and the dynamic segments. Exit status 2 for a bag or a configuration that cannot give a fit
(what is missing is said).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from soft_arm_control.shape_estimation import ESTIMATOR_SCHEMA
from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_model import load_arm_config
from soft_arm_model.config import with_basis, write_arm_file
from soft_arm_model.dynamic_identification import identify_dynamics
from soft_arm_model.identification import IdentificationError, Registration, identify_static, with_basis_shift
from soft_arm_model.parameters import ConfigError, allowed_interval, default_config_dir, split_overrides
from soft_arm_model.recording import (SETTLED_LEAD, Recording, dynamic_segments, noise_levels,
                                      plateaus, static_samples)

from soft_arm_drivers.recording.rosbag_writer import BagError

from .bag_arrays import joint_state_arrays, pose_array_positions, read_raw
from .excitation import load_identification, parse_fit
from .writable import writable_directory

TOPICS = ("tendon/state", "tendon/command", "mocap/markers")


def read_recording(bag_dir: str, names) -> Recording:
    """The identification series of a bag (tendons in the order of ``names``); IdentificationError
    naming the topics it lacks. Topics of one message layout are decoded as arrays
    (:mod:`.bag_arrays`), others message by message."""
    if not os.path.isdir(bag_dir):
        raise IdentificationError(f"{bag_dir} is not a bag directory")
    schedule = os.path.join(os.path.dirname(os.path.abspath(bag_dir)), "excitation.json")
    if os.path.exists(schedule):
        with open(schedule, encoding="utf-8") as fh:
            played = json.load(fh)
        if played.get("valid") is False:
            raise IdentificationError(f"the run of {bag_dir} is marked invalid in {schedule} "
                                      f"({played.get('failure', 'no reason given')}): record it again")
    try:
        raw = read_raw(bag_dir, TOPICS)
    except BagError as exc:
        raise IdentificationError(str(exc)) from None
    missing = [t for t in TOPICS if len(raw.get(t, ("", []))[1]) < 2]
    if missing:
        raise IdentificationError(f"the bag lacks {', '.join(missing)} (it has "
                                  f"{', '.join(sorted(raw)) or 'no messages'}): an identification "
                                  "experiment records tendon states, commands and mocap markers")
    state = joint_state_arrays(raw["tendon/state"][1], names)
    command = joint_state_arrays(raw["tendon/command"][1], names, fields=("effort",))
    frames = pose_array_positions(raw["mocap/markers"][1])
    if state is None or command is None or frames is None:
        return _read_by_message(bag_dir, names)
    (t, values), (t_c, commanded) = state, command
    return Recording(t, values["position"], values["effort"], t_c, commanded["effort"], *frames)


def _read_by_message(bag_dir: str, names) -> Recording:
    """:func:`read_recording` for topics whose messages change layout: each message decoded, the
    states lacking one of ``names`` or a value skipped."""
    from .figures import read_series
    series = read_series(bag_dir, TOPICS)

    def tendon_values(topic, field):
        t, values = [], []
        for stamp, msg in series[topic]:
            index = {n: i for i, n in enumerate(msg.name)}
            row = getattr(msg, field)
            if any(n not in index for n in names) or len(row) != len(msg.name):
                continue
            t.append(stamp)
            values.append([row[index[n]] for n in names])
        if len(t) < 2:
            raise IdentificationError(f"{topic} has no {field} for the tendons {list(names)}")
        return np.array(t), np.array(values, dtype=float)

    t, s = tendon_values("tendon/state", "position")
    t_u, u = tendon_values("tendon/state", "effort")
    if len(t_u) != len(t):
        raise IdentificationError("tendon/state lacks the applied tensions (effort) of some states")
    t_c, c = tendon_values("tendon/command", "effort")
    frames = series["mocap/markers"]
    t_m = np.array([stamp for stamp, _ in frames])
    markers = np.array([[[p.position.x, p.position.y, p.position.z] for p in msg.poses] for _, msg in frames])
    return Recording(t, s, u, t_c, c, t_m, markers)


def composed_calibration(registration: Registration, recorded) -> tuple:
    """The mocap calibration (rotation matrix, translation [m]) that puts Motive's points where the
    fit says arm_base is: the registration after ``recorded``, the calibration the bag was recorded
    with (:class:`~soft_arm_drivers.mocap.bridge_config.Calibration`)."""
    R = registration.rotation @ recorded.rotation
    return R, registration.rotation @ recorded.translation + registration.translation


def identified_priors(estimates: dict) -> dict:
    """What an identification tells the shape estimator of its arm (``estimator.prior.*`` of
    estimator.yaml, dotted keys under ``estimator``): the tip mass's uncertainty [kg] (both shares,
    :attr:`~soft_arm_model.identification.Estimate.uncertainty`) as ``prior.payload``, within the
    interval the estimator accepts (beyond its end, the end).

    Not the stiffness's, friction's or routing's: the estimator learns the stiffness and friction
    to take up what its model lacks, and its routing prior has to cover the configuration error of
    the controller's strain basis too, which the fit's uncertainties (the parameters' within the
    fit's basis) do not (decision 0018: narrowed to them, the blind loop on a drawn plant ran up
    to 77 mm further than holding)."""
    key = "prior.payload"
    return {key: float(np.clip(estimates["tip_mass"].uncertainty, 0.0,
                               allowed_interval(ESTIMATOR_SCHEMA[key][2])[1]))}


def write_identified_arm(path: str, arm, calibration: tuple, header: str = "", priors: dict | None = None):
    """The identified arm with its mocap calibration (rotation matrix, translation [m]) as
    ``rig.mocap.calibration`` in mocap.yaml's layout, and ``priors`` (:func:`identified_priors`)
    as ``estimator.prior``: what ``--arm-file``, the bridge and the shape estimator take."""
    R, t = calibration
    extra = {"rig": {"mocap": {"calibration": {
        "translation": [float(v) for v in t],
        "rotation": [float(v) for v in Rotation.from_matrix(R).as_quat()]}}}}
    if priors:
        extra["estimator"] = {"prior": {key.split(".", 1)[1]: value for key, value in priors.items()}}
    write_arm_file(path, arm, header, extra)


def identify(rec: Recording, arm, fit_config, workers: int | None = None) -> dict:
    """Both fits on a recording: a report (JSON-ready) and the fits themselves (keys ``static``,
    ``dynamic``; ``dynamic`` None without a step or chirp). The static fit runs on the basis of
    ``fit_config``, and is refitted from its result on the basis check's: the one with the lower
    weighted residual gives the estimates, their distance from the other's each estimate's basis
    shift; the arm it returns has ``arm``'s basis (the controller's). IdentificationError when
    the data cannot determine the static fit."""
    held = plateaus(rec, fit_config.min_plateau)
    samples = static_samples(rec, held, fit_config.average)
    marker_sigma, shortening_sigma = noise_levels(rec, held, fit_config.average)
    for key, orders in (("legendre_order", fit_config.legendre_order),
                        ("basis_check.legendre_order", fit_config.check_legendre_order)):
        if len(orders) != len(arm.discretisation.division_ends):
            raise ConfigError(f"identification.fit.{key} = {list(orders)} is not valid: expected "
                              f"{len(arm.discretisation.division_ends)} orders, one per division")
    start = time.perf_counter()
    static = identify_static(with_basis(arm, fit_config.legendre_order, shear=fit_config.shear), samples,
                             marker_sigma, shortening_sigma, max_evaluations=fit_config.max_evaluations)
    static_s = time.perf_counter() - start
    check = None
    if fit_config.check_evaluations:
        start = time.perf_counter()
        check_arm = with_basis(arm, fit_config.check_legendre_order, shear=fit_config.check_shear)
        check = {"legendre_order": list(fit_config.check_legendre_order), "shear": fit_config.check_shear}
        try:
            refit = identify_static(check_arm, samples, marker_sigma, shortening_sigma,
                                    max_evaluations=fit_config.check_evaluations, start=static)
        except IdentificationError as exc:       # the fit stands; its uncertainties are the noise's
            check["failed"] = str(exc)
        else:                # the basis the data prefer gives the estimates, the other their shift
            kept = refit.cost < static.cost
            check.update(evaluations=refit.evaluations, marker_rms=refit.marker_rms.tolist(),
                         cost=refit.cost, fit_cost=static.cost, kept=kept)
            static = with_basis_shift(refit, static) if kept else with_basis_shift(static, refit)
        check["seconds"] = time.perf_counter() - start
    static = replace(static, arm=replace(static.arm, discretisation=arm.discretisation))
    segments = dynamic_segments(held, SETTLED_LEAD, fit_config.dynamic_window)
    dynamic, dynamic_s = None, 0.0
    if segments:
        start = time.perf_counter()
        dynamic = identify_dynamics(static.arm, fit_config.rotor_mass, rec, segments, static.registration,
                                    *noise_levels(rec, held, fit_config.average, per_reading=True),
                                    timestep=fit_config.dynamic_timestep, workers=workers)
        dynamic_s = time.perf_counter() - start
        static = replace(static, arm=replace(static.arm, material=replace(
            static.arm.material, viscosity=dynamic.viscosity.value)))
    report = {
        "plateaus": len(held), "dynamic_segments": len(segments),
        "noise": {"marker": marker_sigma, "shortening": shortening_sigma},
        "estimates": {k: {**vars(e), "uncertainty": e.uncertainty} for k, e in static.estimates.items()},
        "estimator_priors": identified_priors(static.estimates),
        "marker_rms": static.marker_rms.tolist(), "shortening_rms": static.shortening_rms.tolist(),
        "static": {"evaluations": static.evaluations, "seconds": static_s}, "basis_check": check,
        "dynamic": None if dynamic is None else {
            "viscosity": vars(dynamic.viscosity), "rotor_mass": vars(dynamic.rotor_mass),
            "marker_rms": dynamic.marker_rms.tolist(), "shortening_rms": dynamic.shortening_rms.tolist(),
            "evaluations": dynamic.evaluations, "seconds": dynamic_s},
    }
    return {"report": report, "static": static, "dynamic": dynamic, "samples": samples}


def _print_report(report: dict, registration: Registration):
    print(f"{report['plateaus']} plateaus, {report['dynamic_segments']} dynamic segments; noise of a "
          f"sample: markers {report['noise']['marker'] * 1e6:.0f} um, shortenings "
          f"{report['noise']['shortening'] * 1e6:.1f} um")
    print(f"{'parameter':34s} {'value':>12s} {'std. error':>12s} {'basis shift':>12s}")
    rows = list(report["estimates"].items())
    if report["dynamic"] is not None:
        rows += [(k, report["dynamic"][k]) for k in ("viscosity", "rotor_mass")]
    for name, e in rows:
        scale, unit = (180 / np.pi, "deg") if e["unit"] == "rad" else (1.0, e["unit"])
        checked = report["basis_check"] and "failed" not in report["basis_check"]
        shift = (f"{e['basis_shift'] * scale:12.2g}" if checked and name in report["estimates"]
                 else f"{'-':>12s}")
        print(f"{name:34s} {e['value'] * scale:12.5g} {e['standard_error'] * scale:12.2g} {shift} {unit}")
    check = report["basis_check"]
    if check and "failed" in check:
        print(f"basis check failed ({check['failed']}): the uncertainties are the standard errors alone")
    elif check:
        basis = f"order {check['legendre_order']}{' with shear' if check['shear'] else ''}"
        print(f"estimates from the {'basis check (' + basis + ')' if check['kept'] else 'fit basis'}: "
              f"weighted residual {min(check['cost'], check['fit_cost']):.4g} against "
              f"{max(check['cost'], check['fit_cost']):.4g}")
    print(f"shape estimator told: payload {report['estimator_priors']['prior.payload'] * 1e3:.2g} g")
    print(f"mocap registration: {np.degrees(registration.angle):.2f} deg, "
          f"{np.linalg.norm(registration.translation) * 1e3:.1f} mm")
    print("static residual RMS per marker [mm]: "
          + ", ".join(f"{v * 1e3:.2f}" for v in report["marker_rms"]))
    if report["dynamic"] is not None:
        print("dynamic residual RMS per marker [mm]: "
              + ", ".join(f"{v * 1e3:.2f}" for v in report["dynamic"]["marker_rms"]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="soft-arm-identify", description=__doc__.splitlines()[0])
    parser.add_argument("bag", metavar="BAG_DIR", help="bag of an identification experiment")
    parser.add_argument("--output", metavar="FILE", help="write the identified arm description here")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--plot", metavar="DIR", help="draw the fit's figures into DIR")
    parser.add_argument("--arm-file", metavar="FILE", help="the arm description to start from "
                        "(default: the configuration's arm.yaml)")
    parser.add_argument("--config", metavar="DIR", help="directory with the parameter files")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE",
                        help="override an arm or identification parameter (repeatable), e.g. "
                             "identification.fit.rotor_mass=0.3")
    args = parser.parse_args(argv)
    d = args.config or default_config_dir()
    for option, path in (("--output", args.output and os.path.dirname(os.path.abspath(args.output))),
                         ("--plot", args.plot and os.path.abspath(args.plot))):
        problem = path and writable_directory(path)
        if problem:
            print(f"soft-arm-identify: {option} {path}: {problem}", file=sys.stderr)
            return 2
    try:
        groups = split_overrides(args.sets, ("arm", "identification"))
        arm = load_arm_config(args.arm_file or os.path.join(d, "arm.yaml"), groups["arm"])
        fit_config = parse_fit(load_identification(os.path.join(d, "identification.yaml"),
                                                   groups["identification"]))
        mocap = load_mocap_config(os.path.join(d, "mocap.yaml")).calibration
        rec = read_recording(args.bag, [t.name for t in arm.tendons])
        result = identify(rec, arm, fit_config)
    except (ConfigError, IdentificationError) as exc:
        print(f"soft-arm-identify: {exc}", file=sys.stderr)
        return 2
    static, report = result["static"], result["report"]
    calibration = composed_calibration(static.registration, mocap)
    report["mocap_calibration"] = {"rotation_matrix": calibration[0].tolist(),
                                   "translation": calibration[1].tolist()}
    if args.output:
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        dyn = report["dynamic"]
        header = (f"Identified by soft-arm-identify from {os.path.abspath(args.bag)} ({stamp}).\n"
                  f"{report['plateaus']} plateaus; tip residual RMS {static.marker_rms[-1] * 1e3:.2f} mm.\n"
                  + (f"Rotors' reflected mass {dyn['rotor_mass']['value']:.4g} kg (plant.motor.rotor_inertia"
                     " = this x pulley_radius^2 to simulate this rig).\n" if dyn else
                     "No step or chirp in the bag: the viscosity is the starting arm's.\n")
                  + "estimator.prior: the payload's uncertainty, for the shape estimator.\n"
                  + "Use: --arm-file FILE, or --params-file FILE after mocap.yaml and estimator.yaml.")
        write_identified_arm(args.output, static.arm, calibration, header, report["estimator_priors"])
    if args.plot:
        from .identification_figures import identification_figures
        report["figures"] = identification_figures(result, args.plot)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_report(report, static.registration)
        if args.output:
            print(f"arm:      {args.output}")
        for path in report.get("figures", []):
            print(f"figure:   {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
