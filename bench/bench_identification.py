"""What a lab waits for after an identification experiment: ``soft-arm-identify``'s bag read and
its fits, timed part by part over repeated runs. Prints a table and writes JSON.

    python bench/bench_identification.py [--bag DIR] [--repeats 3]
                                         [--output bench/results/identification.json]

``--bag``: an identification experiment's bag; without it, the default experiment is recorded on
the simulator first (``soft-arm-experiment identification``, about a minute, not timed). Each
repeat reads the bag (:func:`soft_arm_experiments.identify_cli.read_recording`) and fits it as
``soft-arm-identify`` does (:func:`soft_arm_experiments.identify_cli.identify`: the static fit,
its basis check, the dynamic fit on every core), the compiled kernels already loaded by a first,
untimed fit. The table gives each part's fastest, median and slowest run [s], and the fit's
identified viscosity and rotor mass, which every run must repeat to the bit.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from timing import results_path, write_results

PARTS = ("read", "static", "basis_check", "dynamic", "fit")


def record(directory: str) -> str:
    """The default identification experiment recorded on the simulator into ``directory``; its bag."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-m", "soft_arm_experiments.experiment", "identification",
                          "--output", directory], env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"the identification experiment failed:\n{out.stderr[-2000:]}")
    return os.path.join(directory, "bag")


def timed_run(bag: str, arm, fit_config) -> dict:
    """One read and fit of ``bag``: each part's wall time [s] and the dynamic estimates."""
    from soft_arm_experiments.identify_cli import identify, read_recording
    start = time.perf_counter()
    rec = read_recording(bag, [t.name for t in arm.tendons])
    read = time.perf_counter() - start
    report = identify(rec, arm, fit_config)["report"]
    parts = {"read": read, "static": report["static"]["seconds"],
             "basis_check": (report["basis_check"] or {}).get("seconds", 0.0),
             "dynamic": report["dynamic"]["seconds"] if report["dynamic"] else 0.0}
    parts["fit"] = parts["static"] + parts["basis_check"] + parts["dynamic"]
    dynamic = report["dynamic"] or {}
    return {**parts, "viscosity": dynamic.get("viscosity", {}).get("value"),
            "rotor_mass": dynamic.get("rotor_mass", {}).get("value"),
            "dynamic_evaluations": dynamic.get("evaluations")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", help="an identification experiment's bag (default: record one)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", default=results_path("identification.json"))
    args = parser.parse_args(argv)
    from soft_arm_experiments.excitation import load_identification, parse_fit
    from soft_arm_model import load_arm_config
    arm, fit_config = load_arm_config(), parse_fit(load_identification())
    with tempfile.TemporaryDirectory() as scratch:
        bag = args.bag or record(scratch)
        timed_run(bag, arm, fit_config)                    # loads the kernels; not counted
        runs = [timed_run(bag, arm, fit_config) for _ in range(args.repeats)]
    if len({(r["viscosity"], r["rotor_mass"]) for r in runs}) != 1:
        print("the runs identified different values: "
              + str([(r["viscosity"], r["rotor_mass"]) for r in runs]))
        return 1
    summary = {p: {"min": float(np.min([r[p] for r in runs])),
                   "median": float(np.median([r[p] for r in runs])),
                   "max": float(np.max([r[p] for r in runs]))} for p in PARTS}
    print(f"soft-arm-identify on {os.cpu_count()} cores, {args.repeats} runs "
          f"({runs[0]['dynamic_evaluations']} simulations in the dynamic fit) [s]")
    print(f"{'part':>12s} {'fastest':>8s} {'median':>8s} {'slowest':>8s}")
    for p in PARTS:
        s = summary[p]
        print(f"{p:>12s} {s['min']:8.2f} {s['median']:8.2f} {s['max']:8.2f}")
    print(f"identified: viscosity {runs[0]['viscosity']:.6g} Pa s, rotor mass {runs[0]['rotor_mass']:.6g} kg")
    write_results(args.output, {"cores": os.cpu_count(), "repeats": args.repeats, "seconds": summary,
                                "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
