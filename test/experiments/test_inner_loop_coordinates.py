"""What the inner loop regulates: on the shortenings it goes where its reference is; on the paper's
thetabar_a it can whip the arm and stop elsewhere (docs/decisions/0021).

The arm: one identified from a recording of robustness draw 1 (``data/identified_draw1_arm.yaml``),
controlling draw 1's plant, the reference that the triangle's second target asked of it (its
shortenings, and the tensions that hold the plant there as feedforward) from the first target's rest.
"""
import os
from dataclasses import replace

import numpy as np
import pytest

from soft_arm_control.actuation_map import ActuationMap, actuation_map_for
from soft_arm_control.inner_loop import tendon_controller_for
from soft_arm_drivers.sim.simulated_rig import Plant
from soft_arm_experiments.campaigns.plants import draw_frame, draw_plant, load_tolerances, plant_overrides
from soft_arm_experiments.harness import load_setup
from soft_arm_model import build_model

ARM = os.path.join(os.path.dirname(__file__), "data", "identified_draw1_arm.yaml")
START_TENSIONS = np.array([0.6, 1.55, 0.32, 0.74])          # N: the plant at rest on target 1
REFERENCE = np.array([36.6, 29.9, 36.6, 39.5]) * 1e-3        # m: target 2's shortenings
FEEDFORWARD = np.array([2.89, 1.47, 0.05, 1.23])             # N: what holds the plant there


@pytest.fixture(scope="module")
def draw1():
    tolerances = load_tolerances()
    plant = {**draw_plant(1, tolerances), **draw_frame(1, tolerances)}
    setup = load_setup("triangle", overrides=plant_overrides(plant), arm_file=ARM)
    return setup, build_model(setup.arm), build_model(setup.plant.plant_arm(setup.arm))


def _step(setup, model, plant_model, actuation_map: ActuationMap, duration=8.0):
    """The inner loop alone at its rate on the plant at 1 ms: (largest tip speed [m/s], final
    shortenings [m], fraction of updates with every tension at a limit)."""
    ctl = setup.control
    plant = Plant(plant_model, setup.plant.timestep, setup.plant.rotor_mass)
    plant.settle(START_TENSIONS)
    loop = tendon_controller_for(model.n_tendons, ctl, (0, 1, 2, 3), actuation_map)
    loop.set_reference(REFERENCE, FEEDFORWARD)
    every = int(round(1.0 / (ctl.inner_rate * setup.plant.timestep)))
    u, speed, banged, updates = START_TENSIONS, 0.0, 0, 0
    for i in range(int(round(duration / setup.plant.timestep))):
        plant.sense(markers=True)
        s, s_dot = plant.tendons()
        if i % every == 0:
            u = loop.update(i * setup.plant.timestep, s, s_dot)
            updates += 1
            banged += np.all((u >= ctl.tension_max - 1e-9) | (u <= ctl.tension_min + 1e-9))
        speed = max(speed, plant.markers()[1])
        plant.step(u)
    return speed, s, banged / updates


def test_the_loop_on_the_shortenings_goes_to_its_reference(draw1):
    setup, model, plant_model = draw1
    assert setup.control.inner_coordinates == "shortenings"
    assert actuation_map_for(model, setup.control).coef is None
    speed, s, banged = _step(setup, model, plant_model, ActuationMap.identity())
    assert np.abs(s - REFERENCE).max() < 0.1e-3
    assert speed < 1.2 and banged < 0.01


def test_the_loop_on_thetabar_whips_the_arm_and_stops_elsewhere(draw1):
    """The same step on the paper's coordinates: the tensions bang between their limits, the tip
    whips at metres per second, and the loop comes to rest with thetabar_a at its reference and the
    shortenings millimetres from theirs."""
    setup, model, plant_model = draw1
    amap = actuation_map_for(model, replace(setup.control, inner_coordinates="actuation_map"))
    assert amap.coef is not None and amap.slope_margin < 0
    speed, s, banged = _step(setup, model, plant_model, amap)
    assert np.abs(amap(s) - amap(REFERENCE)).max() < 0.1e-3
    assert np.abs(s - REFERENCE).max() > 3e-3
    assert speed > 2.0 and banged > 0.05
