"""``soft-arm-warmup``: compile every numba kernel of the package into its cache, once, and its
modules to bytecode.

The model's, the integrator's, the inner loop's, the actuation map's, the shape estimator's, the
strike pendulum's and the mocap bridge's kernels are compiled on their first call and cached beside
their modules (numba's ``cache=True``). On a fresh machine that first call takes about a minute, and
it would otherwise come in the middle of a run: harmless on the simulator, but on the emulated rig
(or the rig) a node that compiles while its neighbours time out looks like a fault. This command
makes the calls a run makes, says what it compiles and how long each took, and is quick once the
cache is warm. It first clears the kernels that changed sources made stale (:mod:`.kernel_cache`).

Every node is a process of its own, and a run starts ten of them: each imports the package's
modules, compiled from source at every start where ``PYTHONDONTWRITEBYTECODE`` is set (containers
often set it), some 0.1 s of CPU each. The warm-up writes their bytecode (``__pycache__``) as it
writes the kernels' cache, whatever that variable says; a module edited since is compiled from
source again, as Python checks the source's time stamp.
Exit status 0, or 1 with the reason when a kernel cannot be compiled.
"""
from __future__ import annotations

import argparse
import compileall
import importlib.util
import sys
import time

import numpy as np

from .kernel_cache import PACKAGES as PROJECT_PACKAGES, clear_stale

# One target of coiling for a fraction of a second: the plant, the inner loop, the precomputed and the
# online CLIK and the shape estimator (on each of its process models) all run at least once.
SHORT_RUN = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[1]",
             "tasks.coiling.phase.upward.window=0.6"]


# The packages whose modules a node imports: the project's and its messages (generated into the
# environment by soft_arm_interfaces/build_pypi.py).
PACKAGES = PROJECT_PACKAGES + ("soft_arm_interfaces",)


def compile_bytecode(packages=PACKAGES) -> list:
    """Write the bytecode of every module of ``packages`` (importable names) beside its source; the
    directories it could not write (read-only installs, whose bytecode their installer wrote), or
    whose package is not installed."""
    missed = []
    for name in packages:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            missed.append(name)
            continue
        missed += [path for path in spec.submodule_search_locations
                   if not compileall.compile_dir(path, quiet=2)]
    return missed


def _model():
    from soft_arm_model import build_model, simulate, solve_equilibrium
    from soft_arm_model.dynamics import CORIOLIS, evaluate
    from soft_arm_model.model import ArmData
    model = build_model()
    evaluate(model, ArmData(model), np.zeros(model.n), np.zeros(model.n), CORIOLIS, markers=True)
    eq = solve_equilibrium(model, [0.5, 0.0, 0.5, 0.0])
    for method in ("imex", "ros2"):
        simulate(model, eq.q, np.zeros(model.n), lambda t: [0.5, 0.0, 0.5, 0.0], 0.01, dt=1e-3,
                 method=method)
    # the identification's compiled segment loop, on a segment of two steps
    from soft_arm_model.dynamic_identification import SegmentData, simulate_changes
    u = np.array([[0.5, 0.0, 0.5, 0.0]])
    n_markers = len(model.config.marker_positions)
    segment = SegmentData(t_input=np.zeros(1), tension=u, t_start=0.0, u_start=u[0],
                          t_s=np.array([0.002, 0.004]), ds=np.zeros((2, 4)), t_m=np.array([0.004]),
                          dp=np.zeros((1, n_markers, 3)))
    simulate_changes(model.config, 0.5, segment, 0.002)
    from .fork_server import make_target_context      # the node fork server's one kernel call
    make_target_context()


def _controller_and_plant():
    from soft_arm_control.actuation_map import fit_actuation_map
    from soft_arm_experiments.harness import load_setup, run_experiment
    from soft_arm_model import build_model
    for process_model in ("static", "dynamic"):
        setup = load_setup("coiling", overrides=SHORT_RUN + [f"estimator.process_model={process_model}"])
        run_experiment(setup, estimate=True)
    fit_actuation_map(build_model(), (0.0, 5.0), 1, 2)     # thetabar_a, for an inner loop asked to use it
    from soft_arm_control.trust_region import TrustRegion       # judges an estimated feedback only
    TrustRegion(setup.control.trust).judge(0.0, np.zeros(2), np.zeros(2))


def _pendulum():
    from soft_arm_drivers.sim.pendulum import ArmSurface, Pendulum
    from soft_arm_experiments.harness import load_setup
    config = load_setup("pendulum").task.pendulum
    ball = Pendulum(config, 1.0e5)
    ball.release()
    column = config.lowest_point + np.array([[0.0, 0.0, 0.1], [0.0, 0.0, -0.1]])
    ball.advance(1e-3, ArmSurface(column, np.zeros((2, 3)), np.full(2, 0.01), np.zeros((2, 3, 1))))
    from soft_arm_drivers.sim.simulated_rig import _surface     # the plant surface a contact takes
    _surface(np.arange(2, dtype=np.int64), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3, 3)),
             np.zeros((1, 3, 3)), np.zeros((1, 6, 2)), np.zeros((1, 6, 2)), np.zeros(2))


def _mocap():
    from soft_arm_drivers.mocap.natnet_scan import warm_up
    warm_up()


STEPS = (("the model's kernels (kinematics to Coriolis, statics, the IMEX and ROS2 steps, the "
          "identification's segment loop)", _model),
         ("the plant, the inner loop, the actuation map, the CLIK, its trust region and the shape "
          "estimator (a short coiling run on each of its process models)",
          _controller_and_plant),
         ("the strike's pendulum and its contact", _pendulum),
         ("the mocap bridge's frame reader", _mocap))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="soft-arm-warmup", description=__doc__.splitlines()[0])
    parser.parse_args(argv)
    start = time.monotonic()
    removed = clear_stale()
    if removed:
        print(f"soft-arm-warmup: sources changed since the kernels were cached: {removed} cached kernel "
              "files of the modules that reach them removed", file=sys.stderr)
    missed = compile_bytecode()
    if missed:
        print(f"soft-arm-warmup: no bytecode written in {', '.join(missed)} (not writable or not "
              "installed): their modules are compiled at each start", file=sys.stderr)
    for what, step in STEPS:
        print(f"soft-arm-warmup: compiling {what} ...", end="", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - any failure here is reported, not a traceback
            print(f" failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            return 1
        print(f" {time.monotonic() - t0:.1f} s", file=sys.stderr)
    print(f"soft-arm-warmup: every kernel is in the cache ({time.monotonic() - start:.1f} s)",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
