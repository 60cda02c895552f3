"""``soft-arm-campaign``: many simulations of the arm on Dask, resumable, with progress and a summary.

Examples::

    soft-arm-campaign robustness --draws 100 --tasks triangle coiling --output DIR
    soft-arm-campaign identification --draws 20 --output DIR      (or --bags DIR)
    soft-arm-campaign sweep --outcome workspace --output DIR \\
        --vary 'arm.tendons.offset_fraction=[[0.5,0.5,0.5,0.5],[0.7,0.7,0.7,0.7]]'

Every run is keyed by its specification (seed and overrides) and written to ``DIR/records.jsonl`` as
it finishes: the same command on the same folder runs only what is missing, and a larger
``--draws`` only the new draws. ``DIR`` gets ``summary.json``, ``summary.md`` and histograms. Runs go
to an embedded Dask ``LocalCluster`` on the local cores (``--workers``), or to an existing
cluster (``--scheduler tcp://host:8786``). Exit status: 0 every run done, 1 a run failed (listed),
2 bad input (nothing ran), 130 interrupted (what finished is kept; run the command again).
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from soft_arm_experiments.writable import writable_directory
from soft_arm_model.parameters import ConfigError

from . import engine
from .plants import STRUCTURAL_FRAME, STRUCTURAL_PLANT, draw_frame, draw_plant, load_tolerances
from .report import write_report

FUNCTIONS = {"robustness": "soft_arm_experiments.campaigns.runs:robustness",
             "identification": "soft_arm_experiments.campaigns.runs:identification",
             "sweep": "soft_arm_experiments.campaigns.runs:sweep"}


def robustness_specs(args) -> list:
    """Every task on the structurally different arm (unless ``--no-structural``) and on draws
    ``seed .. seed + draws - 1`` within the tolerances."""
    tolerances = load_tolerances(args.tolerances)
    draws = ([] if args.no_structural else [("structural", STRUCTURAL_PLANT)])
    draws += [(seed, draw_plant(seed, tolerances)) for seed in range(args.seed, args.seed + args.draws)]
    return [{"kind": "robustness", "task": task, "draw": draw, "plant": plant, "sets": args.sets}
            for draw, plant in draws for task in args.tasks]


def identification_specs(args) -> list:
    """Draws (with their mocap frame errors) as :func:`robustness_specs`, or every bag folder found
    under ``--bags`` (a run folder's ``excitation.json`` beside its bag is read as
    ``soft-arm-identify`` reads it)."""
    if args.bags:
        if not os.path.isdir(args.bags):
            raise ConfigError(f"--bags {args.bags}: not a directory")
        bags = sorted(folder for folder, _, files in os.walk(args.bags)
                      if "metadata.yaml" in files or any(f.endswith(".mcap") for f in files))
        if not bags:
            raise ConfigError(f"--bags {args.bags}: no bag folder in it (a folder with metadata.yaml or "
                              "an .mcap file, at any depth)")
        return [{"kind": "identification", "bag": os.path.abspath(b), "sets": args.sets} for b in bags]
    tolerances = load_tolerances(args.tolerances)
    draws = [] if args.no_structural else [("structural", {**STRUCTURAL_PLANT, **STRUCTURAL_FRAME})]
    draws += [(seed, {**draw_plant(seed, tolerances), **draw_frame(seed, tolerances)})
              for seed in range(args.seed, args.seed + args.draws)]
    return [{"kind": "identification", "draw": draw, "plant": plant, "sets": args.sets}
            for draw, plant in draws]


def sweep_specs(args) -> list:
    """The samples of the design: the grid of every ``--vary`` (all combinations) or ``--samples``
    uniform draws within every ``--range`` (seeded), each with every ``--outcome``."""
    if bool(args.vary) == bool(args.range):
        raise ConfigError("sweep: give --vary (a grid) or --range with --samples (a random design), not both")
    if args.vary:
        axes = []
        for item in args.vary:
            key, values = _pair(item, "--vary")
            try:
                values = json.loads(values)
            except ValueError:
                values = None
            if not isinstance(values, list) or not values:
                raise ConfigError(f"--vary {item!r}: expected KEY=[value, value, ...] (JSON)")
            axes.append([f"{key}={json.dumps(v)}" for v in values])
        samples = [list(combo) for combo in itertools.product(*axes)]
    else:
        if args.samples < 1:
            raise ConfigError(f"--samples {args.samples}: expected at least 1")
        bounds = []
        for item in args.range:
            key, values = _pair(item, "--range")
            low, sep, high = values.partition(":")
            try:
                low, high = float(low), float(high)
            except ValueError:
                low = high = math.nan
            if not sep or not low <= high:
                raise ConfigError(f"--range {item!r}: expected KEY=LOW:HIGH with LOW <= HIGH")
            bounds.append((key, low, high))
        samples = []
        for index in range(args.samples):
            rng = np.random.default_rng([args.seed, index])
            samples.append([f"{key}={float(rng.uniform(low, high)):.6g}" for key, low, high in bounds])
    specs = []
    for index, sample in enumerate(samples):
        for outcome in args.outcome:
            spec = {"kind": "sweep", "sample": index, "sets": sample + args.sets, "outcome": outcome}
            if outcome == "workspace":
                spec["levels"] = args.levels
            elif args.accept_closest:
                spec["accept_closest"] = True
            if args.range:
                spec["seed"] = args.seed
            specs.append(spec)
    return specs


def _pair(item: str, option: str) -> tuple:
    key, sep, value = item.partition("=")
    if not sep or "." not in key:
        raise ConfigError(f"{option} {item!r}: expected namespace.key=...")
    return key, value


def check_specs(specs: list):
    """Load every run's configuration before anything runs: ConfigError naming the key."""
    from soft_arm_experiments.harness import load_setup
    from soft_arm_model import load_arm_config
    from soft_arm_model.parameters import default_config_dir, split_overrides
    seen = set()
    for spec in specs:
        if "bag" in spec:
            from soft_arm_experiments.excitation import load_identification
            groups = split_overrides(list(spec["sets"]), ("arm", "identification"))
            load_arm_config(os.path.join(default_config_dir(), "arm.yaml"), groups["arm"])
            load_identification(overrides=groups["identification"])
            continue
        sets = [f"plant.{k}={json.dumps(v)}" for k, v in spec.get("plant", {}).items()] + list(spec["sets"])
        task = spec.get("task") or spec.get("outcome") or "identification"
        marker = (task, tuple(sets))
        if marker in seen:
            continue
        seen.add(marker)
        if task == "workspace":
            groups = split_overrides(sets, ("arm",))
            load_arm_config(os.path.join(default_config_dir(), "arm.yaml"), groups["arm"])
            if any(level < 0 for level in spec["levels"]):
                raise ConfigError(f"--levels {spec['levels']}: tensions must be >= 0 N")
        else:
            setup = load_setup(task, overrides=sets)
            if setup.task is None and spec["kind"] != "identification":
                raise ConfigError(f"{task} is not a task (the identification experiment: "
                                  "soft-arm-campaign identification)")


class ProgressBar:
    """One line on a terminal: runs done of all, running, failed, the ETA and the dashboard."""

    def __init__(self, stream):
        self.stream = stream
        self.shown_link = False

    def __call__(self, state: dict):
        if not self.shown_link:
            print(f"soft-arm-campaign: dashboard {state['dashboard']}", file=self.stream)
            self.shown_link = True
        total = max(1, state["total"])
        filled = int(30 * state["done"] / total)
        eta = state["eta_s"]
        eta_text = ("-" if math.isnan(eta)
                    else f"{int(eta // 3600)}:{int(eta % 3600 // 60):02d}:{int(eta % 60):02d}")
        line = (f"\r[{'#' * filled}{'.' * (30 - filled)}] {state['done']}/{state['total']} done, "
                f"{state['running']} running, {state['failed']} failed, ETA {eta_text}  ")
        end = "\n" if state["done"] == state["total"] else ""
        print(line, end=end, file=self.stream, flush=True)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="soft-arm-campaign", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[2:]))
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--output", required=True, metavar="DIR",
                        help="the campaign's folder (records, summary, plots); rerun on it to resume")
    common.add_argument("--workers", type=int, metavar="N",
                        help="worker processes of the embedded cluster (default: the cores)")
    common.add_argument("--scheduler", metavar="ADDRESS",
                        help="run on an existing Dask cluster, e.g. tcp://host:8786 (instead of --workers)")
    common.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE",
                        help="an override for every run (repeatable), as soft-arm-harness --set")
    common.add_argument("--retry-failed", action="store_true", help="run again the runs recorded as failed")
    common.add_argument("--quiet", action="store_true", help="no progress bar")
    drawn = argparse.ArgumentParser(add_help=False)
    drawn.add_argument("--draws", type=int, default=10, help="plants to draw (default 10)")
    drawn.add_argument("--seed", type=int, default=0, help="the first draw's seed; draw k has seed SEED + k")
    drawn.add_argument("--tolerances", metavar="FILE",
                       help="casting tolerances to draw within (default: the package's campaign.yaml)")
    drawn.add_argument("--no-structural", action="store_true",
                       help="leave out the structurally different arm (run by default, reported apart)")
    sub = parser.add_subparsers(dest="command", required=True)
    rob = sub.add_parser("robustness", parents=[common, drawn], help="the tasks on drawn plants")
    rob.add_argument("--tasks", nargs="+", default=["triangle", "coiling"], metavar="TASK")
    ide = sub.add_parser("identification", parents=[common, drawn],
                         help="identification on drawn plants, or of recorded bags")
    ide.add_argument("--bags", metavar="DIR", help="fit every bag folder in DIR instead of drawing plants")
    swp = sub.add_parser("sweep", parents=[common], help="any --set key over a grid or a random design")
    swp.add_argument("--vary", action="append", default=[], metavar="KEY=[V,...]",
                     help="a grid axis: the values of KEY as a JSON list (repeatable: all combinations)")
    swp.add_argument("--range", action="append", default=[], metavar="KEY=LOW:HIGH",
                     help="a random design's interval of KEY (repeatable), with --samples")
    swp.add_argument("--samples", type=int, default=10, help="samples of the random design (default 10)")
    swp.add_argument("--seed", type=int, default=0, help="the random design's seed")
    swp.add_argument("--outcome", nargs="+", default=["workspace"], metavar="TASK|workspace",
                     help="what each sample is judged by: tasks, or the tip workspace (default)")
    swp.add_argument("--levels", type=float, nargs="+", default=[0.0, 2.5, 5.0], metavar="N",
                     help="workspace: tension levels per tendon [N] (default 0 2.5 5)")
    swp.add_argument("--accept-closest", action="store_true",
                     help="tasks: run a target the sample's model cannot hold at the closest point it can")
    return parser


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.scheduler and args.workers:
            raise ConfigError("--scheduler and --workers: the cluster of --scheduler has its own workers")
        if args.workers is not None and args.workers < 1:
            raise ConfigError(f"--workers {args.workers}: expected at least 1")
        if getattr(args, "draws", 1) < 0:
            raise ConfigError(f"--draws {args.draws}: expected 0 or more")
        specs = {"robustness": robustness_specs, "identification": identification_specs,
                 "sweep": sweep_specs}[args.command](args)
        if not specs:
            raise ConfigError("nothing to run: --draws 0 and --no-structural")
        check_specs(specs)
        problem = writable_directory(args.output)
        if problem:
            raise ConfigError(f"--output {args.output}: {problem}")
    except (ConfigError, ValueError) as exc:
        print(f"soft-arm-campaign: {exc}", file=sys.stderr)
        return 2
    describe = {"kind": args.command}
    if args.command in ("robustness", "identification") and not getattr(args, "bags", None):
        describe["tolerances"] = load_tolerances(args.tolerances)
    progress = None if args.quiet or not sys.stderr.isatty() else ProgressBar(sys.stderr)
    try:
        outcome = engine.run_campaign(args.output, FUNCTIONS[args.command], specs, scheduler=args.scheduler,
                                      workers=args.workers, describe=json.loads(json.dumps(describe)),
                                      progress=progress, retry_failed=args.retry_failed)
    except ValueError as exc:                       # a folder of another campaign
        print(f"soft-arm-campaign: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:                          # a scheduler that does not answer
        print(f"soft-arm-campaign: {exc}", file=sys.stderr)
        return 2
    summary = write_report(args.output, outcome.records, describe, outcome)
    print((Path(args.output) / "summary.md").read_text(encoding="utf-8"))
    done = len(outcome.records)
    print(f"soft-arm-campaign: {done}/{len(specs)} runs recorded ({outcome.ran} now, "
          f"{done - outcome.ran} before), {outcome.failed} failed; summary {args.output}/summary.md",
          file=sys.stderr)
    for failure in summary["failures"]:
        print(f"soft-arm-campaign: failed {json.dumps(failure['spec'])}: {failure['error']}", file=sys.stderr)
    if outcome.interrupted:
        print("soft-arm-campaign: interrupted; run the same command again to finish", file=sys.stderr)
        return 130
    return 1 if outcome.failed else 0


if __name__ == "__main__":
    sys.exit(main())
