"""The identification experiment on the simulated rig: tension plateaus through the plant's own
dynamics, encoders and noisy mocap, then the static fit."""
import numpy as np

from soft_arm_drivers.experiments.harness import load_setup
from soft_arm_drivers.experiments.identification_run import record_plateaus, sample_noise
from soft_arm_model.identification import identify_static, staircase


def test_the_declared_plant_is_identified_from_the_simulated_rig():
    """plant.yaml's arm (E x1.15, friction 0.12 against the controller's 1.5e5 Pa and 0.1) from
    6 s plateaus: within the issue's tolerances (E 3 %, friction 0.02, offsets 0.02, angles 1 deg)."""
    setup = load_setup("coiling")
    truth = setup.plant.plant_arm(setup.arm)
    tensions = staircase(4, 0.05, 2.5, steps=2, pairs=[(0, 1), (2, 3), (0, 2), (1, 3)])
    fit = identify_static(setup.arm, record_plateaus(setup, tensions), *sample_noise(setup))
    assert abs(fit.arm.material.youngs_modulus / truth.material.youngs_modulus - 1) < 0.03
    assert abs(setup.arm.material.youngs_modulus / truth.material.youngs_modulus - 1) > 0.1
    for t_fit, t in zip(fit.arm.tendons, truth.tendons):
        assert abs(t_fit.friction - t.friction) < 0.02
        assert abs(t_fit.offset_fraction - t.offset_fraction) < 0.02
        assert abs(t_fit.start_angle - t.start_angle) < np.radians(1.0)
        assert abs(t_fit.end_angle - t.end_angle) < np.radians(1.0)
    assert fit.marker_rms[-1] < 2e-3
