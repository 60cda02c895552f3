"""The quasi-static identification experiment on the simulated rig (ROS-free).

Tension plateaus (:func:`soft_arm_model.identification.staircase`: each tendon, then pairs,
loaded and unloaded) are applied open loop, in tension, to the plant of ``plant.yaml``; the
encoders and the motion capture record as on the rig, and the settled end of each plateau becomes
one :class:`~soft_arm_model.identification.StaticSample`.
"""
from __future__ import annotations

import numpy as np

from soft_arm_drivers.sim.simulated_rig import SimulatedRig
from soft_arm_model import build_model
from soft_arm_model.identification import plateau_samples

HOLD = 6.0         # s per plateau: the slowest mode of the arm settles to ~0.1 mm
AVERAGE = 2.0      # s at its end averaged into a sample


def record_plateaus(setup, tensions, hold: float = HOLD, average: float = AVERAGE) -> list:
    """Apply each row of ``tensions`` (k, n_t) [N] for ``hold`` [s] to the plant of ``setup``
    (:class:`~soft_arm_drivers.experiments.harness.Setup`), starting from the arm hanging under
    the first row; the samples of :func:`~soft_arm_model.identification.plateau_samples`."""
    tensions = np.asarray(tensions, dtype=float)
    plant = setup.plant
    rig = SimulatedRig(build_model(plant.plant_arm(setup.arm)), plant, np.zeros(tensions.shape[1]),
                       tensions[0])
    steps = int(round(hold / plant.timestep))
    t_s, s, t_m, markers, starts = [], [], [], [], []
    for u in tensions:
        starts.append(rig.t)
        for _ in range(steps):
            frame, _ = rig.begin_step()
            if frame is not None:
                t_m.append(frame.stamp)
                markers.append(frame.markers)
            t_s.append(rig.t)
            s.append(rig.tendons()[0])
            rig.end_step(u)
    return plateau_samples(t_s, s, t_m, markers, tensions, starts, hold, average)


def sample_noise(setup, average: float = AVERAGE) -> tuple[float, float]:
    """The standard deviations [m] of one sample's markers and shortenings: the mocap noise over the
    frames averaged, and the encoder quantisation (uniform over one step of the pulley's arc)."""
    plant = setup.plant
    marker = plant.mocap_noise / np.sqrt(max(1.0, plant.mocap_rate * average))
    shortening = max(plant.encoder_resolution * plant.pulley_radius / np.sqrt(12.0), 1e-7)
    return float(max(marker, 1e-6)), float(shortening)
