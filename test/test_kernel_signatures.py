"""Each compiled kernel that Python calls is compiled once, for the model's read-only, contiguous
arrays. A caller passing a writable, strided or Fortran-ordered array compiles it again: up to half a
minute for the model's largest kernels, in every process whose cache lacks it (a node starting on
the rig, a test worker). The paths a run takes, in a process of their own (a test process holds
whatever earlier tests compiled), each with the kind of array its callers pass, then the
specialisations counted."""
import json
import subprocess
import sys

# (module, kernel): the kernels that Python code calls directly
ENTRY_KERNELS = [("soft_arm_model.kernels", "evaluate"), ("soft_arm_model.kernels", "static_tangent"),
                 ("soft_arm_model.kernels", "tendon_rate_bias"),
                 ("soft_arm_model.routing", "routing_arrays"),
                 ("soft_arm_model.routing", "routing_derivatives"),
                 ("soft_arm_control.collocated", "_collocated_terms"),
                 ("soft_arm_control.dynamic_estimator_steps", "predict_step"),
                 ("soft_arm_control.dynamic_estimator_steps", "tendon_rows"),
                 ("soft_arm_control.dynamic_estimator_steps", "gain_update"),
                 ("soft_arm_model.dynamic_identification", "_simulate_segment"),
                 ("soft_arm_drivers.sim.pendulum", "_swing"), ("soft_arm_drivers.sim.pendulum", "_closest"),
                 ("soft_arm_drivers.sim.simulated_rig", "_surface"),
                 ("soft_arm_control.trust_region", "_judgement")]

SCRIPT = r"""
import importlib
import json
import sys

import numpy as np

from soft_arm_control.collocated import (CollocatedData, build_collocated, coordinate_selector,
                                         evaluate_collocated)
from soft_arm_control.dynamic_estimation import DynamicShapeEstimator
from soft_arm_control.shape_estimation import load_estimator_config
from soft_arm_model import build_model, frame_at, marker_positions, solve_equilibrium, tendon_lengths
from soft_arm_model.dynamic_identification import SegmentData, simulate_changes
from soft_arm_model.statics import static_tangents

model = build_model()
u = np.array([1.2, 0.3, 0.8, 0.5])
q = solve_equilibrium(model, u).q
static_tangents(model, q, u)
frame_at(model, q, 0.2)
# a selector as a user may hand it over: Fortran-ordered
selector = np.asfortranarray(coordinate_selector(model, (0, 1, 2, 3)))
cm = build_collocated(model, (0, 1, 2, 3), selector=selector)
evaluate_collocated(cm, CollocatedData(cm), q)
# the dynamic estimate, with markers (its routing moves), then without
estimator = DynamicShapeEstimator(model, load_estimator_config(), 0.6)
estimator.start(0.0, u)
s = model.rest_tendon_lengths - tendon_lengths(model, q)
for k in range(3):
    estimator.update(0.004 * (k + 1), s, np.zeros(4), u, marker_positions(model, q) + 2e-4)
estimator.update(0.016, s, np.zeros(4), u)          # and on the tendons alone
# an identification segment whose samples are every other one of a recording's (strided views)
t = np.arange(1, 9) * 0.002
n_markers = len(model.config.marker_positions)
segment = SegmentData(t_input=np.zeros(1), tension=u[None, :], t_start=0.0, u_start=u, t_s=t[::2],
                      ds=np.zeros((4, 4)), t_m=t[1::2], dp=np.zeros((4, n_markers, 3)))
simulate_changes(model.config, 0.6, segment, 0.002, q)
# the online CLIK's trust region judging an estimate, on a fixed target and along a periodic path
from soft_arm_control.trust_region import TrustRegion
from soft_arm_experiments.harness import load_setup
region = TrustRegion(load_setup("coiling").control.trust)
for period in (None, 0.5):
    region.new_goal(period)
    for k in range(600):
        region.judge(k / 240, np.full(2, 1e-3), np.zeros(2))
# the strike: the pendulum swung on the simulated rig, its free swing, a closest approach
from soft_arm_drivers.sim.pendulum import closest_capsule
from soft_arm_drivers.sim.simulated_rig import SimulatedRig
from soft_arm_experiments.strike import free_swing, marker_backbone
strike = load_setup("pendulum")
rig = SimulatedRig(model, strike.plant, np.zeros(4), u, pendulum=strike.task.pendulum)
rig.release_pendulum()
for k in range(3):
    rig.begin_step()
    rig.end_step(u)
free_swing(strike.task.pendulum, [0.001])
closest_capsule(*marker_backbone(strike.arm, marker_positions(model, q)), strike.task.pendulum.lowest_point)
counts = {f"{m}.{k}": [str(s) for s in getattr(importlib.import_module(m), k).signatures]
          for m, k in json.loads(sys.argv[1])}
print(json.dumps(counts))
"""


def test_every_kernel_python_calls_has_one_specialisation():
    out = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(ENTRY_KERNELS)], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    signatures = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(signatures.values()), f"a kernel was never called: {signatures}"
    several = {k: v for k, v in signatures.items() if len(v) > 1}
    assert not several, "compiled more than once (the arguments' types differ):\n" + "\n".join(
        f"{k}:\n  " + "\n  ".join(v) for k, v in several.items())
