"""The simulated plant's parameters (``config/plant.yaml``, namespace ``plant``): how the simulated
arm differs from the controller's model, its time step, motors, encoders and motion capture.

Only the simulated rig reads this file: the controller never sees the plant it is tested on.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace

from soft_arm_model.config import ArmConfig
from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

PLANT_SCHEMA = {
    "youngs_modulus_scale": ("float", lambda v: 0.1 <= v <= 10, "a factor in [0.1, 10]"),
    "viscosity_scale": ("float", lambda v: 0 <= v <= 10, "a factor in [0, 10]"),
    "friction": ("floats", lambda v: all(0 <= a <= 10 for a in v),
                 "friction coefficients in [0, 10], one per tendon"),
    "timestep": ("float", lambda v: 1e-5 <= v <= 0.01, "a time step in [1e-5, 0.01] s"),
    "motor.rotor_inertia": ("float", lambda v: 0 <= v <= 1, "an inertia in [0, 1] kg m^2"),
    "encoder.pulley_radius": ("float", lambda v: 0 < v <= 1, "a radius in (0, 1] m"),
    "encoder.resolution": ("float", lambda v: 0 <= v <= 1, "an angle step in [0, 1] rad"),
    "encoder.velocity_resolution": ("float", lambda v: 0 <= v <= 10, "a rate step in [0, 10] rad/s"),
    "mocap.rate": ("float", lambda v: 1 <= v <= 2000, "a frame rate in [1, 2000] Hz"),
    "mocap.noise": ("float", lambda v: 0 <= v <= 0.1, "a standard deviation in [0, 0.1] m"),
    "mocap.latency": ("float", lambda v: 0 <= v <= 1, "a latency in [0, 1] s"),
    "mocap.seed": ("int", lambda v: v >= 0, "a seed >= 0"),
}


@dataclass(frozen=True)
class PlantConfig:
    """The simulated plant: material scale factors and friction relative to the controller's arm,
    the time step [s], the motor rotor inertia [kg m^2], the encoder (pulley radius [m], angle and
    rate resolution [rad], [rad/s]) and the mocap (frame rate [Hz], noise standard deviation [m],
    latency [s], seed)."""
    youngs_modulus_scale: float
    viscosity_scale: float
    friction: tuple
    timestep: float
    rotor_inertia: float
    pulley_radius: float
    encoder_resolution: float
    velocity_resolution: float
    mocap_rate: float
    mocap_noise: float
    mocap_latency: float
    mocap_seed: int

    def plant_arm(self, arm: ArmConfig) -> ArmConfig:
        """The plant's arm: the controller's description with E and viscosity scaled and the
        plant's friction coefficients."""
        material = replace(arm.material,
                           youngs_modulus=arm.material.youngs_modulus * self.youngs_modulus_scale,
                           viscosity=arm.material.viscosity * self.viscosity_scale)
        tendons = tuple(replace(t, friction=f) for t, f in zip(arm.tendons, self.friction))
        return replace(arm, material=material, tendons=tendons)

    @property
    def rotor_mass(self) -> float:
        """The rotor inertia reflected onto the tendon: J / r^2 [kg]."""
        return self.rotor_inertia / self.pulley_radius ** 2


def parse_plant(v: dict, arm: ArmConfig) -> PlantConfig:
    """Cross-checks of the ``plant`` values against the arm (one friction coefficient per tendon)."""
    if len(v["friction"]) != len(arm.tendons):
        raise ConfigError(f"plant.friction = {list(v['friction'])} is not valid: expected "
                          f"{len(arm.tendons)} values, one per tendon in arm.tendons.names")
    return PlantConfig(v["youngs_modulus_scale"], v["viscosity_scale"], v["friction"], v["timestep"],
                       v["motor.rotor_inertia"], v["encoder.pulley_radius"], v["encoder.resolution"],
                       v["encoder.velocity_resolution"], v["mocap.rate"], v["mocap.noise"],
                       v["mocap.latency"], v["mocap.seed"])


def load_plant_config(arm: ArmConfig, path: str | None = None, overrides=None) -> PlantConfig:
    """Load ``plant.yaml`` (default: the package's) and check it against ``arm``."""
    path = path or os.path.join(default_config_dir(), "plant.yaml")
    return parse_plant(load_section(path, "plant", PLANT_SCHEMA, overrides), arm)


def plant_of(params, arm: ArmConfig) -> PlantConfig:
    """``plant`` of a node's parameters (:class:`soft_arm_ros.parameters.NodeParameters`)."""
    return parse_plant(params.section("plant", PLANT_SCHEMA), arm)
