"""The arm description (``config/arm.yaml``, namespace ``arm``): its schema, the frozen
:class:`ArmConfig` and its cross-checks, loaded through :mod:`soft_arm_model.parameters`.

The file holds ``<node>: {ros__parameters: {arm: {...}}}``; ``/**`` applies to every node. Every key is
required: a value is never silently defaulted. Every value is checked, and a bad one raises
:class:`ConfigError` naming the dotted key, the value and what is allowed.

Overrides use dotted keys relative to ``arm`` (``material.youngs_modulus=2e5``) and are applied before
validation, so an override is checked like a value from the file.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from typing import Any, Mapping

import yaml

from .parameters import (ConfigError, apply_overrides, default_config_dir, flatten_tree, read_parameters,
                         validate_tree)

NAMESPACE = "arm"
STRAIN_MODES = ("torsion", "bending_y", "bending_z", "axial", "shear_y", "shear_z")
AXIAL_LAWS = ("linear", "neo_hookean")


@dataclass(frozen=True)
class Geometry:
    """Cone geometry [m]: arc length ``length``, radii at the base and at the tip."""
    length: float
    base_radius: float
    tip_radius: float


@dataclass(frozen=True)
class Material:
    """Material: density [kg/m^3], Young's modulus [Pa], Poisson ratio [-], Kelvin-Voigt viscosity
    [Pa s], and the axial constitutive law (``linear`` or incompressible ``neo_hookean``)."""
    density: float
    youngs_modulus: float
    poisson_ratio: float
    viscosity: float
    axial_law: str


@dataclass(frozen=True)
class Tendon:
    """One tendon, attached at the base (X = 0) and ending at ``end`` [m].

    Its section angle [rad] varies linearly from ``start_angle`` (X = 0) to ``end_angle`` (X = end),
    measured about the arm axis from +x towards +y of ``arm_base``; its distance from the axis is
    ``offset_fraction`` times the local radius. ``friction`` is the paper's mubar [-].
    """
    name: str
    start_angle: float
    end_angle: float
    end: float
    offset_fraction: float
    friction: float


@dataclass(frozen=True)
class Discretisation:
    """Strain basis: divisions ending at ``division_ends`` [m], a Legendre order and a number of Gauss
    points per division, the enabled strain modes (ordered as ``STRAIN_MODES``)."""
    division_ends: tuple
    legendre_order: tuple
    gauss_points: tuple
    modes: tuple
    allow_tendon_end_inside_division: bool


@dataclass(frozen=True)
class ArmConfig:
    """The validated arm description; ``gravity`` [m/s^2] in ``arm_base``, ``marker_positions`` [m]
    are arc lengths of the tracked markers (base to tip), ``friction_smoothing`` [rad/m] smooths the
    norm in the friction integrand near zero turning rate, ``tip_mass`` [kg] is a point mass fixed
    at the tip (an end effector or a payload; 0 for the bare arm)."""
    geometry: Geometry
    material: Material
    tendons: tuple
    discretisation: Discretisation
    gravity: tuple
    marker_positions: tuple
    friction_smoothing: float
    tip_mass: float

    @property
    def enabled_modes(self) -> tuple:
        return tuple(m for m, on in zip(STRAIN_MODES, self.discretisation.modes) if on)


# ---------------------------------------------------------------------------------------------------
# Schema: dotted key -> (kind, check). Kinds: float, int, bool, str, floats, ints, strs.

def _finite(v):
    return math.isfinite(v)


ARM_SCHEMA: dict[str, tuple[str, Any, str]] = {
    "geometry.length": ("float", lambda v: 0 < v <= 10, "a length in (0, 10] m"),
    "geometry.base_radius": ("float", lambda v: 0 < v <= 1, "a radius in (0, 1] m"),
    "geometry.tip_radius": ("float", lambda v: 0 < v <= 1, "a radius in (0, 1] m"),
    "material.density": ("float", lambda v: 0 < v <= 1e5, "a density in (0, 1e5] kg/m^3"),
    "material.youngs_modulus": ("float", lambda v: 0 < v <= 1e12, "a modulus in (0, 1e12] Pa"),
    "material.poisson_ratio": ("float", lambda v: 0 <= v <= 0.5, "a ratio in [0, 0.5]"),
    "material.viscosity": ("float", lambda v: 0 <= v <= 1e9, "a viscosity in [0, 1e9] Pa s"),
    "material.axial_law": ("str", lambda v: v in AXIAL_LAWS, f"one of {list(AXIAL_LAWS)}"),
    "tendons.names": ("strs", lambda v: len(v) >= 1 and len(set(v)) == len(v) and all(v),
                      "one or more distinct, non-empty names"),
    "tendons.start_angle_deg": ("floats", lambda v: all(-360 <= a <= 360 for a in v),
                                "angles in [-360, 360] deg, one per tendon"),
    "tendons.end_angle_deg": ("floats", lambda v: all(-360 <= a <= 360 for a in v),
                              "angles in [-360, 360] deg, one per tendon"),
    "tendons.end": ("floats", lambda v: all(a > 0 for a in v), "arc lengths > 0 m, one per tendon"),
    "tendons.offset_fraction": ("floats", lambda v: all(0 <= a < 1 for a in v),
                                "fractions of the local radius in [0, 1), one per tendon"),
    "tendons.friction": ("floats", lambda v: all(0 <= a <= 10 for a in v),
                         "friction coefficients in [0, 10], one per tendon"),
    "tendons.friction_smoothing": ("float", lambda v: 0 < v <= 1e3, "a rate in (0, 1e3] rad/m"),
    "discretisation.division_ends": ("floats", lambda v: len(v) >= 1 and all(
        b > a for a, b in zip([0.0] + list(v[:-1]), v)), "strictly increasing arc lengths > 0 m"),
    "discretisation.legendre_order": ("ints", lambda v: all(0 <= a <= 12 for a in v),
                                      "orders in [0, 12], one per division"),
    "discretisation.gauss_points": ("ints", lambda v: all(1 <= a <= 40 for a in v),
                                    "counts in [1, 40], one per division"),
    "discretisation.allow_tendon_end_inside_division": ("bool", None, "true or false"),
    "gravity": ("floats", lambda v: len(v) == 3 and math.sqrt(sum(a * a for a in v)) <= 100,
                "three components [m/s^2] with norm <= 100"),
    "tip_mass": ("float", lambda v: 0 <= v <= 1, "a mass in [0, 1] kg"),
    "markers.positions": ("floats",
                          lambda v: len(v) >= 1 and all(b > a for a, b in zip([0.0] + list(v[:-1]), v)),
                          "one or more strictly increasing arc lengths > 0 m (the tracked markers: "
                          "without one there is nothing to control)"),
}
for _mode in STRAIN_MODES:
    ARM_SCHEMA[f"discretisation.modes.{_mode}"] = ("bool", None, "true or false")


def parse_arm_config(params: Mapping) -> ArmConfig:
    """Validate an ``arm`` parameter tree (the mapping under ``ros__parameters.arm``)."""
    flat = flatten_tree(params)
    v = validate_tree(params, ARM_SCHEMA, NAMESPACE)

    def require(ok, key, allowed):
        if not ok:
            raise ConfigError(f"{NAMESPACE}.{key} = {flat[key]!r} is not valid: expected {allowed}")

    length = v["geometry.length"]
    require(v["geometry.tip_radius"] <= v["geometry.base_radius"], "geometry.tip_radius",
            f"a radius no larger than geometry.base_radius ({v['geometry.base_radius']})")
    require(v["geometry.base_radius"] < 0.5 * length, "geometry.base_radius",
            f"a slender rod: radius < half of geometry.length ({length})")
    n_t = len(v["tendons.names"])
    for key in ("tendons.start_angle_deg", "tendons.end_angle_deg", "tendons.end",
                "tendons.offset_fraction", "tendons.friction"):
        require(len(v[key]) == n_t, key, f"{n_t} values, one per tendon in tendons.names")
    require(all(e <= length + 1e-12 for e in v["tendons.end"]), "tendons.end",
            f"arc lengths within geometry.length ({length})")
    ends = v["discretisation.division_ends"]
    require(abs(ends[-1] - length) <= 1e-9, "discretisation.division_ends",
            f"a list whose last value is geometry.length ({length})")
    n_d = len(ends)
    require(len(v["discretisation.legendre_order"]) == n_d, "discretisation.legendre_order",
            f"{n_d} values, one per division")
    require(len(v["discretisation.gauss_points"]) == n_d, "discretisation.gauss_points",
            f"{n_d} values, one per division")
    for i, (order, pts) in enumerate(zip(v["discretisation.legendre_order"],
                                         v["discretisation.gauss_points"])):
        require(pts >= order + 1, "discretisation.gauss_points",
                f"at least legendre_order + 1 points per division (division {i + 1} has order {order})")
    modes = tuple(v[f"discretisation.modes.{m}"] for m in STRAIN_MODES)
    require(any(modes), "discretisation.modes.torsion", "at least one enabled strain mode")
    if not v["discretisation.allow_tendon_end_inside_division"]:
        for name, end in zip(v["tendons.names"], v["tendons.end"]):
            require(any(abs(end - e) <= 1e-9 for e in ends), "discretisation.division_ends",
                    f"a division boundary at the end of {name} ({end} m): the strain jumps there "
                    "(set discretisation.allow_tendon_end_inside_division only for convergence studies)")
    require(all(p <= length + 1e-12 for p in v["markers.positions"]), "markers.positions",
            f"arc lengths within geometry.length ({length})")

    tendons = tuple(
        Tendon(name=v["tendons.names"][i],
               start_angle=math.radians(v["tendons.start_angle_deg"][i]),
               end_angle=math.radians(v["tendons.end_angle_deg"][i]),
               end=v["tendons.end"][i],
               offset_fraction=v["tendons.offset_fraction"][i],
               friction=v["tendons.friction"][i])
        for i in range(n_t))
    return ArmConfig(
        geometry=Geometry(length, v["geometry.base_radius"], v["geometry.tip_radius"]),
        material=Material(v["material.density"], v["material.youngs_modulus"],
                          v["material.poisson_ratio"], v["material.viscosity"],
                          v["material.axial_law"]),
        tendons=tendons,
        discretisation=Discretisation(ends, v["discretisation.legendre_order"],
                                      v["discretisation.gauss_points"], modes,
                                      v["discretisation.allow_tendon_end_inside_division"]),
        gravity=v["gravity"],
        marker_positions=v["markers.positions"],
        friction_smoothing=v["tendons.friction_smoothing"],
        tip_mass=v["tip_mass"],
    )


def load_arm_config(path: str | None = None, overrides: Mapping[str, Any] | None = None,
                    node: str = "/**") -> ArmConfig:
    """Load, override and validate the arm description (default: the package's ``arm.yaml``)."""
    path = path or os.path.join(default_config_dir(), "arm.yaml")
    params = read_parameters(path, node)
    if NAMESPACE not in params or not isinstance(params[NAMESPACE], dict):
        raise ConfigError(f"{path}: no '{NAMESPACE}' parameters under {node}.ros__parameters")
    try:
        return parse_arm_config(apply_overrides(params[NAMESPACE], overrides, ARM_SCHEMA, NAMESPACE))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def with_basis(arm: ArmConfig, legendre_order, gauss_points=None, shear: bool | None = None) -> ArmConfig:
    """``arm`` with another strain basis: Legendre orders (and Gauss points) per division, the two
    shear strains on or off (None: as they are). The physical parameters are the same arm's."""
    modes = list(arm.discretisation.modes)
    if shear is not None:
        for name in ("shear_y", "shear_z"):
            modes[STRAIN_MODES.index(name)] = bool(shear)
    basis = replace(arm.discretisation, legendre_order=tuple(legendre_order),
                    gauss_points=tuple(gauss_points or arm.discretisation.gauss_points), modes=tuple(modes))
    return replace(arm, discretisation=basis)


def arm_parameters(arm: ArmConfig) -> dict:
    """The ``arm`` parameter tree of ``arm`` (the inverse of :func:`parse_arm_config`)."""
    d, t = arm.discretisation, arm.tendons
    return {
        "geometry": {"length": arm.geometry.length, "base_radius": arm.geometry.base_radius,
                     "tip_radius": arm.geometry.tip_radius},
        "material": {"density": arm.material.density, "youngs_modulus": arm.material.youngs_modulus,
                     "poisson_ratio": arm.material.poisson_ratio, "viscosity": arm.material.viscosity,
                     "axial_law": arm.material.axial_law},
        "tendons": {"names": [x.name for x in t],
                    "start_angle_deg": [math.degrees(x.start_angle) for x in t],
                    "end_angle_deg": [math.degrees(x.end_angle) for x in t],
                    "end": [x.end for x in t], "offset_fraction": [x.offset_fraction for x in t],
                    "friction": [x.friction for x in t], "friction_smoothing": arm.friction_smoothing},
        "discretisation": {"division_ends": list(d.division_ends), "legendre_order": list(d.legendre_order),
                           "gauss_points": list(d.gauss_points),
                           "allow_tendon_end_inside_division": d.allow_tendon_end_inside_division,
                           "modes": dict(zip(STRAIN_MODES, d.modes))},
        "gravity": list(arm.gravity),
        "tip_mass": arm.tip_mass,
        "markers": {"positions": list(arm.marker_positions)},
    }


def write_arm_file(path: str, arm: ArmConfig, header: str = "", extra: dict | None = None):
    """Write ``arm`` as a complete arm description in the layout of ``arm.yaml`` (every node reads
    it; ``header``: comment lines on top; ``extra``: other namespaces' trees, e.g. a mocap
    calibration), written whole or not at all."""
    def plain(v):             # numpy floats (a fit's results) as Python floats
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return float(v) if isinstance(v, float) else v

    text = "".join(f"# {line}\n" for line in header.splitlines())
    tree = plain({NAMESPACE: arm_parameters(arm), **(extra or {})})
    text += yaml.safe_dump({"/**": {"ros__parameters": tree}},
                           sort_keys=False, default_flow_style=None)
    partial = path + ".partial"
    with open(partial, "w", encoding="utf-8") as fh:
        fh.write(text)
    os.replace(partial, path)
