"""The identification experiment on the simulated rig, ROS-free: the excitation of
``identification.yaml`` (:class:`.excitation.Excitation`) applied open loop, in tension, to the
plant of ``plant.yaml``, recorded as the graph's bag records it (tendon states and commands at the
inner loop's rate, mocap frames with their noise and latency). The benchmark and the tests use it
where a run of the graph would take minutes; ``soft-arm-experiment identification`` records the
same series to a bag.
"""
from __future__ import annotations

import numpy as np

from soft_arm_drivers.sim.simulated_rig import SimulatedRig
from soft_arm_model import build_model, solve_equilibrium, tendon_lengths
from soft_arm_model.recording import Recording

from .excitation import Excitation


def simulate_recording(setup, excitation: Excitation) -> Recording:
    """Play ``excitation`` on the simulated rig of ``setup``
    (:class:`~soft_arm_experiments.harness.Setup`): the arm starts hanging under
    ``control.tension_min`` with the encoders zeroed there (as the simulator node starts it)."""
    plant, control = setup.plant, setup.control
    model = build_model(setup.arm)
    pretension = np.full(model.n_tendons, control.tension_min)
    offset = model.rest_tendon_lengths - tendon_lengths(model, solve_equilibrium(model, pretension).q)
    rig = SimulatedRig(build_model(plant.plant_arm(setup.arm)), plant, offset, pretension)
    per_command = max(1, int(round(1.0 / (control.inner_rate * plant.timestep))))
    t, s, u_applied, u_command, t_m, markers = [], [], [], [], [], []
    steps = int(np.ceil(excitation.duration / plant.timestep))
    u = pretension
    for k in range(steps):
        _, delivered = rig.begin_step()
        for frame in delivered:
            t_m.append(frame.stamp)
            markers.append(frame.markers)
        if k % per_command == 0:
            t.append(rig.t)
            s.append(rig.tendons()[0])
            u_applied.append(rig.tension)
            u = excitation.tension(rig.t)
            u_command.append(u)
        rig.end_step(u)
    t = np.array(t)
    return Recording(t, np.array(s), np.array(u_applied), t, np.array(u_command), np.array(t_m),
                     np.array(markers))
