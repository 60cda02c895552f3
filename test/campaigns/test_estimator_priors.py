"""What a drawn plant leaves unknown, told to the shape estimator: the priors of
``campaigns.plants.estimator_priors`` are the root-mean-square distances of the drawn plants'
stiffness, friction, routing and payload from the controller's arm."""
import math

import numpy as np
import pytest

from soft_arm_control.shape_estimation import load_estimator_config
from soft_arm_experiments.campaigns.plants import draw_plant, estimator_priors, load_tolerances
from soft_arm_model import load_arm_config


def _priors(sets: list) -> dict:
    return {s.split("=")[0].rsplit(".", 1)[1]: float(s.split("=")[1]) for s in sets}


@pytest.mark.parametrize("shift", [False, True])
def test_the_priors_are_the_drawn_plants_rms_distance_from_the_arm(shift):
    """Over 3,000 draws, the RMS of (drawn stiffness scale - 1), of (drawn friction and offset - the
    arm's, the worst tendon's), of the start and end angle errors and of the payload agree with the
    priors to 4 % (the sampling error is about 1.3 %); an offset interval that does not centre on
    the arm's (``shift``) is told as its larger RMS, not as its spread."""
    tolerances = load_tolerances()
    if shift:
        tolerances = {**tolerances, "offset_fraction": [0.6, 0.7], "tip_payload": [0.002, 0.003]}
    arm = load_arm_config()
    priors = _priors(estimator_priors(tolerances, arm))
    draws = [draw_plant(seed, tolerances) for seed in range(3000)]
    offsets = np.array([d["tendon.offset_fraction"] for d in draws])
    drawn = np.array([t.offset_fraction for t in arm.tendons])
    angles = np.array([d["tendon.start_angle_error"] + d["tendon.end_angle_error"] for d in draws])
    payload = np.array([d["tip_payload"] for d in draws])
    stiffness = np.array([d["youngs_modulus_scale"] for d in draws])
    friction = np.array([d["friction"] for d in draws]) - [t.friction for t in arm.tendons]
    for key, measured in (("stiffness", np.sqrt(np.mean((stiffness - 1.0) ** 2))),
                          ("friction", np.sqrt(np.mean(friction ** 2, axis=0)).max()),
                          ("tendon_offset", np.sqrt(np.mean((offsets - drawn) ** 2, axis=0)).max()),
                          ("tendon_angle", np.sqrt(np.mean(angles ** 2))),
                          ("payload", np.sqrt(np.mean(payload ** 2)))):
        assert priors[key] == pytest.approx(measured, rel=0.04), key
    spread = (tolerances["offset_fraction"][1] - tolerances["offset_fraction"][0]) / math.sqrt(12)
    assert (priors["tendon_offset"] > 1.5 * spread) == shift


def test_the_shipped_priors_are_the_campaigns_tolerances_but_the_payload():
    """config/estimator.yaml considers the casting tolerance's routing (to the 5 % its rounding
    allows) and no payload: the lab's arm carries none it does not know of; the campaign's plants
    do, and are told so. (Its stiffness and friction priors are where the learning starts, tighter
    than the campaign's draws: the declared plant is one of them.)"""
    config = load_estimator_config()
    priors = _priors(estimator_priors(load_tolerances(), load_arm_config()))
    assert config.prior_tendon_offset == pytest.approx(priors["tendon_offset"], rel=0.05)
    assert config.prior_tendon_angle == pytest.approx(priors["tendon_angle"], rel=0.05)
    assert config.prior_payload == 0.0 < priors["payload"]
