"""The simulated encoders: readings quantised as the motors' firmware reports them."""
from dataclasses import replace

import numpy as np
import pytest

from soft_arm_drivers.sim.plant_config import load_plant_config
from soft_arm_drivers.sim.simulated_rig import Encoders
from soft_arm_model import load_arm_config


@pytest.fixture(scope="module")
def plant():
    return load_plant_config(load_arm_config())


def _in_numpy(encoders, s_true, s_dot_true):
    """The reading as its docstring says it: angle and rate rounded (numpy's half to even) to their
    steps, none for a step of zero."""
    def quantise(v, step):
        return v if step == 0 else np.round(v / step) * step
    angle = quantise((s_true - encoders.zero) / encoders.r, encoders.res)
    rate = quantise(s_dot_true / encoders.r, encoders.vres)
    return angle * encoders.r + encoders.offset, rate * encoders.r


@pytest.mark.parametrize("steps", [None, (0.0, 0.0), (0.25, 0.5)])
def test_a_reading_is_the_quantised_angle_and_rate_to_the_last_bit(plant, steps):
    """On random shortenings and rates the compiled reading is the numpy expression's, bit for bit."""
    if steps is not None:
        plant = replace(plant, encoder_resolution=steps[0], velocity_resolution=steps[1])
    rng = np.random.default_rng(7)
    encoders = Encoders(plant, rng.normal(0, 0.01, 4), rng.normal(0, 0.01, 4))
    cases = [(rng.normal(0, 0.05, 4), rng.normal(0, 0.5, 4)) for _ in range(200)]
    for s_true, s_dot_true in cases:
        mine = encoders.read(s_true, s_dot_true)
        for a, b in zip(mine, _in_numpy(encoders, s_true, s_dot_true)):
            assert np.array_equal(a, b)


def test_half_a_step_reads_as_the_even_step(plant):
    """A radius and steps that are powers of two make the halves exact: each goes to the even step."""
    plant = replace(plant, pulley_radius=0.5, encoder_resolution=0.25, velocity_resolution=0.5)
    encoders = Encoders(plant, np.zeros(4), np.zeros(4))
    halves = np.array([0.5, 1.5, 2.5, -0.5])
    s, rate = encoders.read(halves * 0.25 * 0.5, halves * 0.5 * 0.5)
    assert np.array_equal(s / (0.5 * 0.25), [0, 2, 2, 0]) and np.array_equal(rate / (0.5 * 0.5), [0, 2, 2, 0])
