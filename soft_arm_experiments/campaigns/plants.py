"""The plants a campaign draws: within casting tolerances (``config/campaign.yaml``, or the user's own
file), as ``plant.*`` overrides of ``plant.yaml``; and whether a drawn plant can hold a task's targets
at all.

A drawn plant differs from the controller's arm (``arm.yaml``) the way a cast silicone arm differs from
its drawing: Young's modulus and viscosity, density, each tendon's angles at the base and at its end,
its offset and friction, the strain order and shear of the plant's own discretisation, and a payload at
the tip the controller does not know of. Everything is uniform within the tolerances and seeded by the
draw's own seed, so a draw is the same whatever else the campaign holds.
"""
from __future__ import annotations

import json
import math
import os
from typing import Optional

import numpy as np

from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

NAMESPACE = "campaign.tolerances"
N_TENDONS = 4


def _interval(low=-math.inf, high=math.inf):
    return lambda v: len(v) == 2 and low <= v[0] <= v[1] <= high


SCHEMA = {
    "youngs_modulus_scale": ("floats", _interval(0.1, 10), "an interval [low, high] within [0.1, 10]"),
    "viscosity_scale": ("floats", _interval(0, 10), "an interval [low, high] within [0, 10]"),
    "density_scale": ("floats", _interval(0.5, 2), "an interval [low, high] within [0.5, 2]"),
    "angle_error_deg": ("float", lambda v: 0 <= v <= 20, "an angle in [0, 20] deg (+- per tendon)"),
    "offset_fraction": ("floats", _interval(0.01, 0.99), "an interval [low, high] within [0.01, 0.99]"),
    "friction": ("floats", _interval(0, 10), "an interval [low, high] within [0, 10]"),
    "legendre_order": ("ints", _interval(0, 8), "an interval [low, high] of orders within [0, 8]"),
    "shear": ("bools", lambda v: 1 <= len(v) == len(set(v)),
              "the choices of shear: [false], [true] or [false, true]"),
    "tip_payload": ("floats", _interval(0, 0.1), "an interval [low, high] within [0, 0.1] kg"),
    "mocap_rotation_deg": ("float", lambda v: 0 <= v <= 10, "an angle in [0, 10] deg per axis"),
    "mocap_translation": ("float", lambda v: 0 <= v <= 0.1, "a length in [0, 0.1] m per axis"),
}

# A structurally different arm, outside the distribution: E -12 %, viscosity +30 %, density +5 %,
# offsets 0.57-0.64, base angles off by 2-3 deg, uneven friction, order 4 with shear.
STRUCTURAL_PLANT = {
    "youngs_modulus_scale": 0.88, "viscosity_scale": 1.3, "density_scale": 1.05,
    "friction": [0.09, 0.16, 0.12, 0.1], "tendon.offset_fraction": [0.57, 0.64, 0.6, 0.62],
    "tendon.start_angle_error": [0.04, -0.05, 0.03, -0.04], "tendon.end_angle_error": [0.0, 0.0, 0.0, 0.0],
    "discretisation.legendre_order": [4, 0], "discretisation.shear": True, "tip_payload": 0.0,
}
# and its mocap calibration error (identification campaigns)
STRUCTURAL_FRAME = {"mocap.frame_error.rotation_deg": [0.0, 1.2, 1.6],
                    "mocap.frame_error.translation": [0.003, -0.004, 0.0]}


def load_tolerances(path: Optional[str] = None) -> dict:
    """The tolerances of ``path`` (default: the package's ``config/campaign.yaml``), validated:
    ConfigError naming the file and the key."""
    path = path or os.path.join(default_config_dir(), "campaign.yaml")
    return load_section(path, NAMESPACE, SCHEMA)


def draw_plant(seed: int, tolerances: dict) -> dict:
    """The plant of draw ``seed``, as ``plant.*`` values (key without the namespace -> value)."""
    t = tolerances
    rng = np.random.default_rng(seed)
    angle = math.radians(t["angle_error_deg"])
    return {
        "youngs_modulus_scale": round(float(rng.uniform(*t["youngs_modulus_scale"])), 4),
        "viscosity_scale": round(float(rng.uniform(*t["viscosity_scale"])), 4),
        "density_scale": round(float(rng.uniform(*t["density_scale"])), 4),
        "friction": [round(float(f), 4) for f in rng.uniform(*t["friction"], N_TENDONS)],
        "tendon.offset_fraction": [round(float(f), 4) for f in rng.uniform(*t["offset_fraction"], N_TENDONS)],
        "tendon.start_angle_error": [round(float(a), 5) for a in rng.uniform(-angle, angle, N_TENDONS)],
        "tendon.end_angle_error": [round(float(a), 5) for a in rng.uniform(-angle, angle, N_TENDONS)],
        "discretisation.legendre_order": [int(rng.integers(t["legendre_order"][0],
                                                           t["legendre_order"][1] + 1)), 0],
        "discretisation.shear": bool(t["shear"][int(rng.integers(0, len(t["shear"])))]),
        "tip_payload": round(float(rng.uniform(*t["tip_payload"])), 5),
    }


def draw_frame(seed: int, tolerances: dict) -> dict:
    """The mocap calibration error of draw ``seed``, as ``plant.mocap.frame_error.*`` values."""
    rng = np.random.default_rng([seed, 1])
    rotation, translation = tolerances["mocap_rotation_deg"], tolerances["mocap_translation"]
    return {"mocap.frame_error.rotation_deg": [round(float(a), 3)
                                               for a in rng.uniform(-rotation, rotation, 3)],
            "mocap.frame_error.translation": [round(float(a), 4)
                                              for a in rng.uniform(-translation, translation, 3)]}


def plant_overrides(plant: dict) -> list:
    """``plant.key=value`` overrides of a plant's values (values as JSON)."""
    return [f"plant.{key}={json.dumps(value)}" for key, value in plant.items()]


def _rms_about(low: float, high: float, value: float) -> float:
    """The root-mean-square distance from ``value`` of a number uniform in [low, high]."""
    if high <= low:
        return abs(low - value)
    return math.sqrt(((high - value) ** 3 - (low - value) ** 3) / (3.0 * (high - low)))


def estimator_priors(tolerances: dict, arm) -> list:
    """``estimator.prior.*`` overrides that tell the shape estimator what the tolerances leave
    unknown of ``arm`` (an :class:`~soft_arm_model.config.ArmConfig`, the controller's): the
    stiffness scale (Young's modulus over the arm's) [-], the tendons' friction coefficients [-],
    offset fractions [-], start and end angles [rad] and the payload [kg] the plant carries at the
    tip beyond the arm's ``tip_mass``, each the root-mean-square distance of the drawn value from the
    arm's (the worst tendon's). The dynamic estimate considers the routing and the payload where the
    tendons cannot tell them, and a filter told less reports an uncertainty the drawn plants exceed
    (``docs/concepts/sensing.md``); the stiffness and friction both estimators learn from the
    tendons, and these are where the learning starts."""
    t = tolerances
    priors = {
        "stiffness": _rms_about(*t["youngs_modulus_scale"], 1.0),
        "friction": max(_rms_about(*t["friction"], tendon.friction) for tendon in arm.tendons),
        "tendon_offset": max(_rms_about(*t["offset_fraction"], tendon.offset_fraction)
                             for tendon in arm.tendons),
        "tendon_angle": math.radians(t["angle_error_deg"]) / math.sqrt(3.0),
        "payload": _rms_about(*t["tip_payload"], 0.0),     # on top of the arm's own tip mass
    }
    # the schema's floor: a tolerance of none still leaves the stiffness and friction a little freedom
    floors = {"stiffness": 1e-3, "friction": 1e-3}
    return [f"estimator.prior.{key}={max(value, floors.get(key, 0.0)):.6g}" for key, value in priors.items()]


def plant_holds(task: str, overrides: list) -> dict:
    """Whether the plant itself can hold the targets the run visits: the precomputed CLIK solved on
    the plant's own model, its margin [N] from the tension limits and its stability under the inner
    loop (:func:`soft_arm_control.target_margin.check_arm`), per visited target (``plant_targets``,
    1-based). A target it cannot hold no controller reaches; one the run never visits says nothing
    of the run."""
    from soft_arm_control.target_margin import check_arm, is_robust
    from soft_arm_experiments.harness import load_setup, schedule
    setup = load_setup(task, overrides=overrides)
    if setup.task is None:
        raise ConfigError(f"{task} has no targets to hold")
    visited = sorted({k for _, _, k, _ in schedule(setup.task)})
    results = check_arm(setup.plant.plant_arm(setup.arm), setup.control, setup.task,
                        [setup.task.targets[k] for k in visited])
    return {"plant_holds": is_robust(results, min_margin=0.0), "plant_targets": [k + 1 for k in visited],
            "plant_margins": [r.margin for r in results], "plant_stable": [r.stable for r in results]}
