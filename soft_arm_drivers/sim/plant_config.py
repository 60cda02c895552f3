"""The simulated plant's parameters (``config/plant.yaml``, namespace ``plant``): how the simulated
arm differs from the controller's model, its time step, motors, encoders and motion capture.

Only the simulated rig reads this file: the controller never sees the plant it is tested on.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, replace

import numpy as np

from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_model.config import ArmConfig, load_arm_config, with_basis
from soft_arm_model.lie import expmap
from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

from .occlusion import OcclusionConfig

PLANT_SCHEMA = {
    "plant_file": ("str", None, "the path of a complete arm description in the schema of arm.yaml, "
                                "or an empty string (the controller's arm with the differences below)"),
    "youngs_modulus_scale": ("float", lambda v: 0.1 <= v <= 10, "a factor in [0.1, 10]"),
    "viscosity_scale": ("float", lambda v: 0 <= v <= 10, "a factor in [0, 10]"),
    "density_scale": ("float", lambda v: 0.5 <= v <= 2, "a factor in [0.5, 2]"),
    "friction": ("floats", lambda v: all(0 <= a <= 10 for a in v),
                 "friction coefficients in [0, 10], one per tendon"),
    "tendon.offset_fraction": ("floats", lambda v: all(0 < a < 1 for a in v),
                               "fractions of the local radius in (0, 1), one per tendon"),
    "tendon.start_angle_error": ("floats", lambda v: all(abs(a) <= 0.5 for a in v),
                                 "angle errors in [-0.5, 0.5] rad at the base, one per tendon"),
    "tendon.end_angle_error": ("floats", lambda v: all(abs(a) <= 0.5 for a in v),
                               "angle errors in [-0.5, 0.5] rad at the tendon end, one per tendon"),
    "tip_payload": ("float", lambda v: 0 <= v <= 0.1,
                    "a mass in [0, 0.1] kg fixed at the tip, added to arm.tip_mass"),
    "discretisation.legendre_order": ("ints", lambda v: all(0 <= a <= 8 for a in v),
                                      "Legendre orders in [0, 8], one per division of the arm"),
    "discretisation.gauss_points": ("ints", lambda v: all(1 <= a <= 20 for a in v),
                                    "Gauss points in [1, 20], one per division of the arm"),
    "discretisation.shear": ("bool", None, "true or false (the two shear strains)"),
    "timestep": ("float", lambda v: 1e-5 <= v <= 0.01, "a time step in [1e-5, 0.01] s"),
    "motor.rotor_inertia": ("float", lambda v: 0 <= v <= 1, "an inertia in [0, 1] kg m^2"),
    "encoder.pulley_radius": ("float", lambda v: 0 < v <= 1, "a radius in (0, 1] m"),
    "encoder.resolution": ("float", lambda v: 0 <= v <= 1, "an angle step in [0, 1] rad"),
    "encoder.velocity_resolution": ("float", lambda v: 0 <= v <= 10, "a rate step in [0, 10] rad/s"),
    "mocap.rate": ("float", lambda v: 1 <= v <= 2000, "a frame rate in [1, 2000] Hz"),
    "mocap.noise": ("float", lambda v: 0 <= v <= 0.1, "a standard deviation in [0, 0.1] m"),
    "mocap.latency": ("float", lambda v: 0 <= v <= 1, "a latency in [0, 1] s"),
    "mocap.seed": ("int", lambda v: v >= 0, "a seed >= 0"),
    "mocap.frame_error.rotation_deg": ("floats", lambda v: len(v) == 3 and all(abs(a) <= 10 for a in v),
                                       "a rotation vector of 3 components in [-10, 10] deg"),
    "mocap.frame_error.translation": ("floats", lambda v: len(v) == 3 and all(abs(a) <= 0.1 for a in v),
                                      "a translation of 3 components in [-0.1, 0.1] m"),
    "mocap.occlusion.enabled": ("bool", None, "true or false (false: every marker in every frame)"),
    "mocap.occlusion.cameras.positions": (
        "floats", lambda v: len(v) >= 3 and len(v) % 3 == 0 and all(abs(a) <= 50 for a in v),
        "camera positions [m] in arm_base, x y z of each camera in turn, components in [-50, 50]"),
    "mocap.occlusion.cameras.aim": ("floats", lambda v: len(v) == 3 and all(abs(a) <= 50 for a in v),
                                    "the point [m] every camera looks at, 3 components in [-50, 50]"),
    "mocap.occlusion.cameras.field_of_view_deg": ("float", lambda v: 0 < v < 180,
                                                  "a full cone angle in (0, 180) deg"),
    "mocap.occlusion.min_cameras": ("int", lambda v: v >= 1,
                                    "a number of cameras >= 1 (and at most the cameras given)"),
    "mocap.occlusion.self_occlusion": ("bool", None, "true or false (the arm's body hides markers)"),
    "mocap.occlusion.dropout": ("float", lambda v: 0 <= v <= 0.5,
                                "a probability per marker per frame in [0, 0.5]"),
    "mocap.occlusion.bursts.fraction": ("floats", lambda v: all(0 <= a <= 0.95 for a in v),
                                        "fractions of time in [0, 0.95], one per marker"),
    "mocap.occlusion.bursts.duration": ("float", lambda v: 0.001 <= v <= 60,
                                        "a mean burst duration in [0.001, 60] s"),
    "mocap.occlusion.blackout": ("floats", lambda v: len(v) == 2 and 0 <= v[0] <= v[1],
                                 "[start, end] s with 0 <= start <= end: no marker is seen in between "
                                 "(equal: never)"),
}
# the keys that describe the plant's arm (ignored when plant_file names a complete description)
ARM_KEYS = ("youngs_modulus_scale", "viscosity_scale", "density_scale", "friction",
            "tendon.offset_fraction", "tendon.start_angle_error", "tendon.end_angle_error",
            "tip_payload", "discretisation.legendre_order", "discretisation.gauss_points",
            "discretisation.shear")
_PER_TENDON = ("friction", "tendon.offset_fraction", "tendon.start_angle_error", "tendon.end_angle_error")
_PER_DIVISION = ("discretisation.legendre_order", "discretisation.gauss_points")


@dataclass(frozen=True)
class PlantConfig:
    """The simulated plant: its arm (``arm_values``: the plant's differences from the controller's
    arm, by key of :data:`PLANT_SCHEMA`, or ``plant_file``: a complete arm description), the time
    step [s], the motor rotor inertia [kg m^2], the encoder (pulley radius
    [m], angle and rate resolution [rad], [rad/s]) and the mocap (frame rate [Hz], noise standard
    deviation [m], latency [s], seed, and the error of its calibration: the markers arrive as
    R p + t for p in arm_base, ``mocap_frame_error`` = (rotation vector R [rad] (3,), t [m] (3,));
    ``occlusion``: its cameras and losses, :class:`~.occlusion.OcclusionConfig`, None: every marker
    is seen in every frame).

    ``bridge_correction`` = (rotation matrix (3, 3), translation [m] (3,)): what a mocap bridge
    whose calibration differs from ``mocap.yaml``'s (the one ``mocap_frame_error`` is the error of)
    does on top of it, for the rigs that have no bridge (:func:`with_bridge_calibration`).

    ``drawing``: the arm the differences apply to, when the controller's arm is not the package's
    (an identified arm file: the plant stays the arm it was identified on); None: the controller's."""
    plant_file: str
    arm_values: dict
    timestep: float
    rotor_inertia: float
    pulley_radius: float
    encoder_resolution: float
    velocity_resolution: float
    mocap_rate: float
    mocap_noise: float
    mocap_latency: float
    mocap_seed: int
    mocap_frame_error: tuple = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    occlusion: OcclusionConfig | None = None
    bridge_correction: tuple = (((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), (0.0, 0.0, 0.0))
    drawing: ArmConfig | None = None

    def plant_arm(self, arm: ArmConfig) -> ArmConfig:
        """The plant's arm: the description of ``plant_file``, or the ``drawing`` (default: the
        controller's ``arm``) with E, viscosity and density scaled, the plant's tendon geometry and
        friction, the tip payload added to its tip mass, and its own strain basis. ConfigError if it
        does not fit the controller's arm (tendons, markers)."""
        if self.plant_file:
            plant, source = load_arm_config(self.plant_file), f"plant.plant_file = {self.plant_file!r}"
        else:
            plant, source = self._differing(self.drawing or arm), "the plant (plant.yaml over arm.yaml)"
        if [t.name for t in plant.tendons] != [t.name for t in arm.tendons]:
            raise ConfigError(f"{source} is not valid: its tendons.names must be the controller's "
                              f"{[t.name for t in arm.tendons]}")
        if len(plant.marker_positions) != len(arm.marker_positions):
            raise ConfigError(f"{source} is not valid: expected {len(arm.marker_positions)} markers, "
                              "as in the controller's arm")
        return plant

    def _differing(self, arm: ArmConfig) -> ArmConfig:
        """``arm`` with the differences of ``arm_values``."""
        v = self.arm_values
        material = replace(arm.material,
                           youngs_modulus=arm.material.youngs_modulus * v["youngs_modulus_scale"],
                           viscosity=arm.material.viscosity * v["viscosity_scale"],
                           density=arm.material.density * v["density_scale"])
        tendons = tuple(replace(t, friction=f, offset_fraction=d, start_angle=t.start_angle + a0,
                                end_angle=t.end_angle + a1)
                        for t, f, d, a0, a1 in zip(arm.tendons, *(v[k] for k in _PER_TENDON)))
        arm = replace(arm, material=material, tendons=tendons, tip_mass=arm.tip_mass + v["tip_payload"])
        return with_basis(arm,
                          v["discretisation.legendre_order"], v["discretisation.gauss_points"],
                          v["discretisation.shear"])

    def as_mocap_reports(self, points) -> np.ndarray:
        """Points (..., 3) [m] in arm_base as the miscalibrated mocap reports them: R p + t of
        ``mocap_frame_error``, then the ``bridge_correction`` (noise not included)."""
        A, b = self._mocap_report_transform
        return np.asarray(points, dtype=float) @ A.T + b

    @functools.cached_property
    def _mocap_report_transform(self) -> tuple:
        """(A (3, 3), b [m] (3,)): ``mocap_frame_error`` then ``bridge_correction`` as one affine map
        p -> A p + b, composed once (every simulated mocap frame applies it)."""
        rotvec, translation = self.mocap_frame_error
        # the rotation vector's exponential by the model's own kernel: scipy's Rotation would cost
        # every simulator and emulated-rig process 0.1-0.2 s to import
        R, _ = np.empty((3, 3)), np.empty(3)
        expmap(np.concatenate([np.asarray(rotvec, dtype=float), np.zeros(3)]), R, _)
        rotation, shift = (np.asarray(a, dtype=float) for a in self.bridge_correction)
        return rotation @ R, rotation @ np.asarray(translation, dtype=float) + shift

    @property
    def rotor_mass(self) -> float:
        """The rotor inertia reflected onto the tendon: J / r^2 [kg]."""
        return self.rotor_inertia / self.pulley_radius ** 2


def with_bridge_calibration(plant: PlantConfig, mocap_path: str, calibration: dict) -> PlantConfig:
    """The plant whose markers arrive as a mocap bridge calibrated with ``calibration`` would
    publish them (``rig.mocap.calibration`` overrides relative to ``rig``, e.g. those of an arm
    file written by soft-arm-identify: :func:`~soft_arm_drivers.mocap.bridge_config.calibration_overrides`),
    Motive's points being those of the rig's calibration in ``mocap_path`` (``mocap.yaml``, whose
    error ``plant.mocap.frame_error`` is). No overrides: the plant unchanged."""
    if not calibration:
        return plant
    rig = load_mocap_config(mocap_path).calibration
    bridge = load_mocap_config(mocap_path, calibration).calibration
    R = bridge.rotation @ rig.rotation.T
    t = bridge.translation - R @ rig.translation
    return replace(plant, bridge_correction=(tuple(map(tuple, R.tolist())), tuple(t.tolist())))


def parse_plant(v: dict, arm: ArmConfig) -> PlantConfig:
    """Cross-checks of the ``plant`` values against the arm: one value per tendon, one per division."""
    expect = {**{k: (len(arm.tendons), "one per tendon in arm.tendons.names") for k in _PER_TENDON},
              **{k: (len(arm.discretisation.division_ends),
                     "one per division in arm.discretisation.division_ends") for k in _PER_DIVISION}}
    expect["mocap.occlusion.bursts.fraction"] = (len(arm.marker_positions),
                                                 "one per marker in arm.markers.positions")
    for key, (n, what) in expect.items():
        if len(v[key]) != n:
            raise ConfigError(f"plant.{key} = {list(v[key])} is not valid: expected {n} values, {what}")
    return PlantConfig(v["plant_file"], {k: v[k] for k in ARM_KEYS}, v["timestep"],
                       v["motor.rotor_inertia"], v["encoder.pulley_radius"], v["encoder.resolution"],
                       v["encoder.velocity_resolution"], v["mocap.rate"], v["mocap.noise"],
                       v["mocap.latency"], v["mocap.seed"],
                       (tuple(math.radians(a) for a in v["mocap.frame_error.rotation_deg"]),
                        v["mocap.frame_error.translation"]), _occlusion(v))


def _occlusion(v: dict) -> OcclusionConfig | None:
    """``plant.mocap.occlusion`` (None when not enabled)."""
    if not v["mocap.occlusion.enabled"]:
        return None
    flat = v["mocap.occlusion.cameras.positions"]
    cameras = tuple(tuple(flat[i:i + 3]) for i in range(0, len(flat), 3))
    aim = tuple(v["mocap.occlusion.cameras.aim"])
    if any(math.dist(c, aim) < 0.1 for c in cameras):
        raise ConfigError(f"plant.mocap.occlusion.cameras.positions = {list(flat)} is not valid: every "
                          f"camera must stand at least 0.1 m from the aim point {list(aim)}")
    if v["mocap.occlusion.min_cameras"] > len(cameras):
        raise ConfigError(f"plant.mocap.occlusion.min_cameras = {v['mocap.occlusion.min_cameras']} is not "
                          f"valid: at most the {len(cameras)} cameras of cameras.positions")
    return OcclusionConfig(cameras, aim, math.radians(v["mocap.occlusion.cameras.field_of_view_deg"]),
                           v["mocap.occlusion.min_cameras"], v["mocap.occlusion.self_occlusion"],
                           v["mocap.occlusion.dropout"], tuple(v["mocap.occlusion.bursts.fraction"]),
                           v["mocap.occlusion.bursts.duration"], tuple(v["mocap.occlusion.blackout"]))


def load_plant_config(arm: ArmConfig, path: str | None = None, overrides=None) -> PlantConfig:
    """Load ``plant.yaml`` (default: the package's) and check it against ``arm``."""
    path = path or os.path.join(default_config_dir(), "plant.yaml")
    return parse_plant(load_section(path, "plant", PLANT_SCHEMA, overrides), arm)


def plant_of(params, arm: ArmConfig) -> PlantConfig:
    """``plant`` of a node's parameters (:class:`soft_arm_ros.parameters.NodeParameters`)."""
    return parse_plant(params.section("plant", PLANT_SCHEMA), arm)


def describe_plant(plant: PlantConfig) -> str:
    """One line saying how the plant differs from the controller's arm (for a node's start-up log)."""
    if plant.plant_file:
        return f"the arm of {plant.plant_file}"
    v = plant.arm_values
    return (f"E x{v['youngs_modulus_scale']}, viscosity x{v['viscosity_scale']}, density "
            f"x{v['density_scale']}, friction {list(v['friction'])}, offsets "
            f"{list(v['tendon.offset_fraction'])}, strain order {list(v['discretisation.legendre_order'])}"
            f"{' with shear' if v['discretisation.shear'] else ''}, tip payload {v['tip_payload']} kg")
