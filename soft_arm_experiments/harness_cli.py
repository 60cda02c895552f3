"""``soft-arm-harness <task>``: run one of the paper's experiments on the ROS-free closed-loop harness.

Loads ``arm.yaml``, ``control.yaml``, ``plant.yaml`` and ``tasks.yaml`` from ``--config DIR`` (default:
the package's), applies repeated ``--set namespace.key=value`` overrides (namespaces arm, control,
plant, tasks), runs the protocol and prints the per-transition table and the paper-style summary
(``--json``: the metrics as JSON on stdout). Errors in the configuration or an unreachable target
exit with status 2 and a message; nothing is simulated then. The message names the closest point the
model reaches within the tension limits; ``--accept-closest`` runs the task with it. ``--live
[HOST:]PORT`` serves the run to the Foxglove app while it runs (:class:`~.live_launch.HarnessView`).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict

from soft_arm_control.clik import TargetError
from soft_arm_model.parameters import ConfigError

from .harness import (add_setup_arguments, goal_warning, load_setup, load_setup_at_closest, run_experiment,
                      setup_overrides)
from .live_launch import HarnessView, add_live_argument
from .metrics import format_table, format_tracking, to_json
from .strike import format_strike


def _progress(t, total):
    print(f"\r  simulated {t:6.1f} / {total:.1f} s", end="", file=sys.stderr, flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="soft-arm-harness", description=__doc__.splitlines()[0])
    parser.add_argument("task", help="task name in tasks.yaml (e.g. triangle, coiling)")
    add_setup_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress line on stderr")
    add_live_argument(parser, "while the harness runs")
    args = parser.parse_args(argv)
    try:
        setup = load_setup(args.task, args.config, setup_overrides(args), args.arm_file, args.feedback)
        if setup.task is None:
            raise ConfigError("the identification experiment is a run of the graph: "
                              "soft-arm-experiment identification")
        if args.accept_closest:
            setup, notes = load_setup_at_closest(args.task, args.config, setup_overrides(args),
                                                 args.arm_file, args.feedback)
            for note in notes:
                print(f"soft-arm-harness: {note}", file=sys.stderr)
    except (ConfigError, ValueError) as exc:          # TargetError is a ValueError
        print(f"soft-arm-harness: {exc}", file=sys.stderr)
        return 2
    live = None
    if args.live is not None:
        try:
            live = HarnessView(args.live, setup.arm, setup.task.space.labels())
        except (ValueError, RuntimeError) as exc:
            print(f"soft-arm-harness: --live {args.live}: {exc}", file=sys.stderr)
            return 2
        print(f"soft-arm-harness: live view on {live.address} (Foxglove app: Open connection, "
              "Foxglove WebSocket; layout config/foxglove_layout.json)", file=sys.stderr)
    start = time.perf_counter()
    try:
        result = run_experiment(setup, None if args.quiet else _progress, observer=live)
    except TargetError as exc:
        print(f"\nsoft-arm-harness: {exc}", file=sys.stderr)
        return 2
    finally:
        if live is not None:
            live.close()
    wall = time.perf_counter() - start
    if not args.quiet:
        print(file=sys.stderr)
    simulated = result.transitions[-1].end if result.transitions else 0.0
    if args.json:
        out = to_json(result.metrics, result.summary)
        out.update(task=args.task, paper_peak_speed=setup.task.paper_peak_speed, simulated_s=simulated,
                   wall_s=wall, targets=result.goals, inner_loop=result.actuation_map.report())
        if result.strike is not None:
            out["strike"] = result.strike
        if result.tracking:
            out["tracking"] = [asdict(r) for r in result.tracking]
        print(json.dumps(out, indent=2))
    else:
        print(format_table(result.metrics, result.summary, setup.task.paper_peak_speed))
        if result.strike is not None:
            print("\n" + format_strike(result.strike))
        if result.tracking:
            print("\n" + format_tracking(result.tracking))
        print(f"\ninner loop on {result.actuation_map.describe()}")
        print(f"simulated {simulated:.1f} s in {wall:.1f} s (real-time factor {simulated / wall:.1f})")
    if result.strike is not None and result.strike["plan"]["arm_time"] is None:
        print(f"soft-arm-harness: the rehearsed arm never touched the ball at its lowest point (it passed "
              f"{result.strike['plan']['rehearsed_gap'] * 1e3:.1f} mm away): the model says the strike "
              "misses", file=sys.stderr)
    for goal in result.goals:
        if goal["status"] != "ok":
            print(f"soft-arm-harness: {goal_warning(goal)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
