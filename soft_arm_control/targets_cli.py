"""``soft-arm-targets <task>``: are a task's targets robust to the arm not being the model?

For each target of the task (``tasks.yaml``, or ``--target`` coordinates), the precomputed CLIK
solves it on variants of the controller's arm (Young's modulus scales ``--stiffness``, extra tip
masses ``--payload`` [kg]) and prints the task tendons' equilibrium tensions [N] and their margin from
the tension limits of ``control.yaml``. A target is robust when every variant holds it with at least
``--min-margin`` [N] and, on each, is a stable equilibrium under the inner loop (a loaded, curled
arm buckles sideways). Exit status: 0 all robust, 1 some are not, 2 bad input.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from soft_arm_model import load_arm_config
from soft_arm_model.parameters import ConfigError, default_config_dir, split_overrides

from .clik import TargetError
from .config import load_control_config, load_task_config
from .target_margin import (MIN_MARGIN, STIFFNESS_SCALES, TIP_PAYLOADS, MarginChecker, default_variants,
                            is_robust, worst_margin)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="soft-arm-targets", description=__doc__.splitlines()[0])
    parser.add_argument("task", help="task name in tasks.yaml (e.g. triangle, coiling)")
    parser.add_argument("--target", type=float, nargs="+", action="append", metavar="X",
                        help="a candidate target in the task's coordinates [m] (repeatable); "
                             "default: the task's targets")
    parser.add_argument("--stiffness", type=float, nargs="+", default=list(STIFFNESS_SCALES),
                        help="Young's modulus scales of the variants (default: %(default)s)")
    parser.add_argument("--payload", type=float, nargs="+", default=list(TIP_PAYLOADS),
                        help="extra tip masses [kg] of the variants (default: %(default)s)")
    parser.add_argument("--min-margin", type=float, default=MIN_MARGIN,
                        help="the margin [N] a robust target keeps on every variant (default: %(default)s)")
    parser.add_argument("--config", metavar="DIR", help="directory with the parameter files")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE",
                        help="override one parameter (namespaces arm, control, tasks)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    d = args.config or default_config_dir()
    try:
        groups = split_overrides(args.sets, ("arm", "control", "tasks"))
        arm = load_arm_config(os.path.join(d, "arm.yaml"), groups["arm"])
        control = load_control_config(arm, os.path.join(d, "control.yaml"), groups["control"])
        task = load_task_config(args.task, arm, os.path.join(d, "tasks.yaml"), groups["tasks"])
        if any(s <= 0 for s in args.stiffness) or any(p < 0 for p in args.payload):
            raise ConfigError("--stiffness scales must be > 0 and --payload masses >= 0 kg")
        targets = [tuple(t) for t in args.target] if args.target else list(task.targets)
        for t in targets:
            if len(t) != task.space.m:
                raise ConfigError(f"--target {list(t)}: the task {args.task} has {task.space.m} "
                                  f"coordinates ({', '.join(task.space.labels())})")
    except ConfigError as exc:
        print(f"soft-arm-targets: {exc}", file=sys.stderr)
        return 2
    checker = MarginChecker(arm, control, task, default_variants(args.stiffness, args.payload))
    report, robust = [], True
    for t in targets:
        try:
            results = checker.check(t)
        except TargetError as exc:
            report.append({"target": list(t), "worst_margin": None, "robust": False, "variants": [],
                           "reason": f"the model itself: {exc}"})
            robust = False
            continue
        worst = worst_margin(results)
        ok = is_robust(results, args.min_margin)
        robust &= ok
        report.append({"target": list(t), "worst_margin": worst, "robust": ok, "variants": [
            {"stiffness": r.variant.stiffness, "payload": r.variant.payload,
             "tensions": None if r.tensions is None else r.tensions.tolist(), "margin": r.margin,
             "stability": r.stability, "stable": r.stable, "reason": r.reason} for r in results]})
    if args.json:
        print(json.dumps({"task": args.task, "labels": task.space.labels(),
                          "tendons": [arm.tendons[k].name for k in task.tendons],
                          "limits": [control.tension_min, control.tension_max],
                          "min_margin": args.min_margin, "targets": report}, indent=2))
    else:
        _print(report, task, arm, control, args.min_margin)
    return 0 if robust else 1


def _print(report, task, arm, control, min_margin):
    names = ", ".join(arm.tendons[k].name for k in task.tendons)
    print(f"tensions [N] of {names} at equilibrium; limits [{control.tension_min}, {control.tension_max}] N; "
          f"a robust target keeps {min_margin} N on every variant and is a stable equilibrium of each "
          f"under the inner loop (smallest stiffness eigenvalue > 0)")
    for entry in report:
        coords = ", ".join(f"{lab}={v:+.4f}" for lab, v in zip(task.space.labels(), entry["target"]))
        print(f"\ntarget {coords} m")
        if "reason" in entry:
            print(f"  {entry['reason']}")
        for v in entry["variants"]:
            head = f"  E x{v['stiffness']:<5g} tip +{v['payload'] * 1e3:4.1f} g"
            if v["tensions"] is None:
                print(f"{head}  {v['reason']}")
            else:
                print(f"{head}  u = {np.array2string(np.array(v['tensions']), precision=2)}  "
                      f"margin {v['margin']:+.2f} N  {'stable' if v['stable'] else 'UNSTABLE'} "
                      f"({v['stability'] * 1e3:+.3f} mN m)")
        worst = entry["worst_margin"]
        verdict = "robust" if entry["robust"] else "NOT robust"
        if worst is not None and not all(v["stable"] for v in entry["variants"]):
            verdict += " (unstable on some arm)"
        margin = "none (no equilibrium on some arm)" if worst is None else f"{worst:.2f} N"
        print(f"  -> {verdict}: worst margin {margin}")


if __name__ == "__main__":
    sys.exit(main())
