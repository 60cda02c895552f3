"""Controller and task parameters (``config/control.yaml``, ``tasks.yaml``).

Each file is in ROS 2 parameter layout (``/**: ros__parameters: <namespace>: ...``) and is validated
like the arm description: every key required, every value checked, a bad value raises
:class:`~soft_arm_model.config.ConfigError` naming ``namespace.key``, the value and what is allowed.
Overrides are dotted keys relative to the namespace.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from soft_arm_model.config import ArmConfig
from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

from .pendulum_geometry import PendulumConfig
from .trajectories import SHAPES, Trajectory
from .task_space import AXES, TaskSpace
from .trust_region import TrustConfig

PHASE_MODES = ("clik", "replay", "precomputed", "online", "track")
FEEDBACKS = ("mocap", "fused", "estimate")   # what the online CLIK closes its loop on
SHAPED_MODES = ("clik", "replay", "precomputed")   # the goal modes that start with a reference step
# The input shapers (:mod:`.input_shaping`), named here so that loading the configuration does not
# import the shaping, the CLIK and scipy's linear algebra.
SHAPERS = ("none", "zv", "zvd")
RATE_MODES = ("clik", "online", "track")           # the goal modes that move the reference online
INNER_COORDINATES = ("shortenings", "actuation_map")  # what the inner loop regulates


def _positive(v):
    return v > 0


def _nonneg_list(v):
    return len(v) >= 1 and all(math.isfinite(a) and a >= 0 for a in v)


CONTROL_SCHEMA = {
    "friction": ("bool", None, "true or false"),
    "rotor_mass": ("float", lambda v: 0 <= v <= 100, "a reflected mass in [0, 100] kg"),
    "tension_min": ("float", lambda v: 0 <= v <= 100, "a pretension in [0, 100] N"),
    "tension_max": ("float", lambda v: 0 < v <= 100, "a tension in (0, 100] N"),
    "actuation_map.degree": ("int", lambda v: 1 <= v <= 4, "a polynomial degree in [1, 4]"),
    "actuation_map.levels": ("floats", lambda v: len(v) >= 2 and all(0 <= a <= 100 for a in v),
                             "two or more tensions in [0, 100] N"),
    "actuation_map.validation_samples": ("int", lambda v: 1 <= v <= 10000, "a count in [1, 10000]"),
    "inner_loop.rate": ("float", lambda v: 1 <= v <= 10000, "a rate in [1, 10000] Hz"),
    "inner_loop.coordinates": ("str", lambda v: v in INNER_COORDINATES, f"one of {list(INNER_COORDINATES)}"),
    "inner_loop.proportional": ("floats", _nonneg_list, "gains >= 0 N/m, one per tendon"),
    "inner_loop.derivative": ("floats", _nonneg_list, "gains >= 0 N s/m, one per tendon"),
    "inner_loop.integral": ("floats", _nonneg_list, "gains >= 0 N/(m s), one per tendon"),
    "inner_loop.integral_saturation": ("float", lambda v: 0 < v <= 10, "a length in (0, 10] m"),
    "inner_loop.tension_rate_limit": ("float", lambda v: 0 <= v <= 1e6,
                                      "a rate in [0, 1e6] N/s (0 disables the limit)"),
    "inner_loop.feedforward": ("bool", None, "true or false"),
    "inner_loop.max_time_step": ("float", lambda v: 0 < v <= 10,
                                 "a time in (0, 10] s: a state stamped more than this after the last "
                                 "one, or before it, is a clock step (counted, integrated over as one "
                                 "period)"),
    "clik.task_gain": ("float", lambda v: 0 < v <= 1000, "a gain in (0, 1000] 1/s"),
    "clik.equilibrium_gain": ("float", lambda v: 0 < v <= 1000, "a gain in (0, 1000] 1/s"),
    "clik.singular_threshold": ("float", lambda v: 0 < v < 1, "a relative singular value in (0, 1)"),
    "clik.rate": ("float", lambda v: 1 <= v <= 10000, "a rate in [1, 10000] Hz"),
    "clik.jacobian_rate": ("float", lambda v: 0 < v <= 10000,
                           "a rate in (0, 10000] Hz, at most clik.rate"),
    "clik.switch_delay": ("float", lambda v: 0 <= v <= 3600,
                          "a delay in [0, 3600] s from a target change to online refinement"),
    "clik.tolerance": ("float", lambda v: 0 < v <= 0.01, "a task tolerance in (0, 0.01] m"),
    "clik.reach_tolerance": ("float", lambda v: 0 < v <= 0.1, "a task error norm in (0, 0.1] m"),
    "clik.max_time_step": ("float", lambda v: 0 < v <= 60,
                           "a time in (0, 60] s: a mocap frame stamped more than this after the last "
                           "one, or before it, is a clock step (counted; the CLIK's time advances one "
                           "frame period)"),
    "clik.stall_time": ("float", lambda v: 0 < v <= 3600, "a time in (0, 3600] s"),
    "clik.seed_levels": ("floats", lambda v: all(0 <= a <= 100 for a in v),
                         "tensions in [0, 100] N (may be empty)"),
    "clik.closest_margin": ("float", lambda v: 0 <= v <= 100,
                            "a tension margin in [0, 100] N, less than half of the tension range"),
    "clik.track_feedforward": ("bool", None, "true or false"),
    "clik.track_dynamics": ("bool", None, "true or false"),
    "clik.track_learning.gain": ("float", lambda v: 0 <= v <= 1,
                                 "a learning gain in [0, 1] (0: no learning)"),
    "clik.track_learning.harmonics": ("int", lambda v: 1 <= v <= 10, "a number of harmonics in [1, 10]"),
    "clik.track_learning.settle_time": ("float", lambda v: 0 <= v <= 3600, "a time in [0, 3600] s"),
    "clik.rate_modes": ("strs", lambda v: set(v) <= set(RATE_MODES),
                        f"none or more of {list(RATE_MODES)}"),
    "clik.min_frequency": ("float", lambda v: 0 <= v <= 100,
                           "a frequency in [0, 100] Hz (0: no check)"),
    "clik.feedback": ("str", lambda v: v in FEEDBACKS,
                      f"one of {list(FEEDBACKS)}: what mocap/markers carries to the clik node (fused and "
                      "estimate: the shape estimator's, judged by the trust region)"),
    "clik.trust.enabled": ("bool", None, "true or false (false: every estimate is stepped on, as a "
                           "measurement would be)"),
    "clik.trust.radius": ("float", lambda v: 0 < v <= 1,
                          "a task distance in (0, 1] m: the largest model error an estimate may show"),
    "clik.trust.drift": ("float", lambda v: 0 < v <= 1,
                         "a task distance in (0, 1] m: the largest unexplained move of the estimate's "
                         "offset from the model over clik.trust.window"),
    "clik.trust.window": ("float", lambda v: 0 < v <= 10, "a time in (0, 10] s"),
    "clik.trust.recover": ("float", lambda v: 0 <= v <= 60,
                           "a time in [0, 60] s of trusted frames before online steps resume"),
    "clik.trust.confidence": ("float", lambda v: 0 <= v <= 10,
                              "a number of standard deviations in [0, 10]: the bias an estimate may "
                              "carry on each task coordinate (0: its offset is taken whole)"),
    "clik.shaping.shaper": ("str", lambda v: v in SHAPERS, f"one of {list(SHAPERS)}"),
    "clik.shaping.level": ("float", lambda v: 0 < v <= 1, "a vibration amplitude in (0, 1] m"),
    "clik.shaping.modes": ("strs", lambda v: len(v) >= 1 and set(v) <= set(SHAPED_MODES),
                           f"one or more of {list(SHAPED_MODES)}"),
}

# When the strike's reference is sent: with the release (the paper's protocol), or when the model's
# rehearsal of the move says the tip will meet the ball at its speed peak (rehearsed: the
# precomputed step; planned: the fastest tension profile planned on the model, followed by the inner
# loop, soft_arm_control.strike_planner)
STRIKE_TIMINGS = ("release", "rehearsed", "planned")
PENDULUM_KEYS = ("pivot", "length", "mass", "ball_radius", "release_angle_deg", "direction",
                 "restitution", "timing")

TASK_SCHEMA = {
    "*.tendons": ("strs", lambda v: len(v) >= 1 and len(set(v)) == len(v),
                  "one or more distinct tendon names"),
    "*.markers": ("ints", lambda v: len(v) >= 1 and all(a >= 1 for a in v),
                  "marker numbers >= 1 (1 = nearest the base), one per coordinate"),
    "*.axes": ("strs", lambda v: all(a in AXES for a in v), "axes among x, y, z, one per coordinate"),
    "*.targets": ("floats", lambda v: len(v) >= 1, "task coordinates [m], one group per target"),
    "*.steady_time": ("float", lambda v: 0 < v <= 3600, "a time in (0, 3600] s"),
    "*.phases": ("strs", lambda v: len(v) >= 1, "one or more phase names"),
    "*.phase.*.mode": ("str", lambda v: v in PHASE_MODES, f"one of {list(PHASE_MODES)}"),
    "*.phase.*.window": ("float", lambda v: 0 < v <= 3600, "a window in (0, 3600] s"),
    "*.phase.*.sequence": ("ints", lambda v: len(v) >= 1 and all(a >= 1 for a in v),
                           "target numbers >= 1, in the order they are visited"),
    # a track phase's path from each target of its sequence (trajectories.Trajectory)
    "*.phase.*.trajectory.shape": ("str", lambda v: v in SHAPES, f"one of {list(SHAPES)}"),
    "*.phase.*.trajectory.size": ("float", lambda v: 0 < v <= 1, "a size in (0, 1] m"),
    "*.phase.*.trajectory.period": ("float", lambda v: 0 < v <= 3600, "a period in (0, 3600] s"),
    "*.phase.*.trajectory.plane": ("ints", lambda v: len(v) == 2 and v[0] != v[1] and min(v) >= 1,
                                   "two distinct task coordinate numbers >= 1 (1 = the first)"),
    "*.payload.masses": ("floats", lambda v: all(0 <= a <= 1 for a in v),
                         "tip masses in [0, 1] kg (optional: an unmodelled load on the plant)"),
    "*.payload.attach_times": ("floats", lambda v: all(0 <= a for a in v),
                               "times >= 0 s from the start, one per payload mass"),
    "*.paper_peak_speed": ("float", lambda v: 0 < v <= 100,
                           "the peak tip speed the paper reports for the task, in (0, 100] m/s (optional)"),
    # the strike experiment's pendulum (optional; pendulum_geometry.PendulumConfig)
    "*.pendulum.pivot": ("floats", lambda v: len(v) == 3, "the pivot's x, y, z [m] in arm_base"),
    "*.pendulum.length": ("float", lambda v: 0 < v <= 2, "a rod length in (0, 2] m"),
    "*.pendulum.mass": ("float", lambda v: 0 < v <= 1, "a ball mass in (0, 1] kg"),
    "*.pendulum.ball_radius": ("float", lambda v: 0 < v <= 0.1, "a ball radius in (0, 0.1] m"),
    "*.pendulum.release_angle_deg": ("float", lambda v: 0 < v < 180,
                                     "an angle from the vertical in (0, 180) deg"),
    "*.pendulum.direction": ("floats", lambda v: len(v) == 2 and (v[0] ** 2 + v[1] ** 2) > 0,
                             "the held ball's horizontal direction from below the pivot, [x, y] (not zero)"),
    "*.pendulum.restitution": ("float", lambda v: 0 <= v <= 1, "a coefficient of restitution in [0, 1]"),
    "*.pendulum.timing": ("str", lambda v: v in STRIKE_TIMINGS, f"one of {list(STRIKE_TIMINGS)}"),
}


@dataclass(frozen=True)
class ControlConfig:
    """Validated ``control`` parameters; gains are per tendon of the arm (all of them)."""
    friction: bool
    rotor_mass: float
    tension_min: float
    tension_max: float
    map_degree: int
    map_levels: tuple
    map_validation_samples: int
    inner_rate: float
    proportional: tuple
    derivative: tuple
    integral: tuple
    integral_saturation: float
    tension_rate_limit: float
    feedforward: bool
    task_gain: float
    equilibrium_gain: float
    singular_threshold: float
    clik_rate: float
    jacobian_rate: float
    switch_delay: float
    tolerance: float
    seed_levels: tuple
    reach_tolerance: float
    stall_time: float
    closest_margin: float
    shaper: str
    shaping_level: float
    shaped_modes: tuple
    track_feedforward: bool
    min_frequency: float
    rate_modes: tuple
    track_dynamics: bool
    track_learning: float
    track_harmonics: int
    track_settle_time: float
    inner_loop_max_time_step: float = 0.1
    clik_max_time_step: float = 1.0
    feedback: str = "mocap"
    trust: TrustConfig | None = None
    inner_coordinates: str = "shortenings"


def parse_control(v: dict, arm: ArmConfig) -> ControlConfig:
    """Cross-checks of the ``control`` values against the arm (one gain per tendon)."""
    n_t = len(arm.tendons)
    for key in ("inner_loop.proportional", "inner_loop.derivative", "inner_loop.integral"):
        if len(v[key]) != n_t:
            raise ConfigError(f"control.{key} = {list(v[key])} is not valid: expected {n_t} values, "
                              "one per tendon in arm.tendons.names")
    if v["clik.jacobian_rate"] > v["clik.rate"]:
        raise ConfigError(f"control.clik.jacobian_rate = {v['clik.jacobian_rate']} is not valid: "
                          f"expected a rate no higher than control.clik.rate ({v['clik.rate']})")
    if not v["tension_min"] < v["tension_max"]:
        raise ConfigError(f"control.tension_min = {v['tension_min']} is not valid: expected a "
                          f"pretension below control.tension_max ({v['tension_max']})")
    if not 2 * v["clik.closest_margin"] < v["tension_max"] - v["tension_min"]:
        raise ConfigError(f"control.clik.closest_margin = {v['clik.closest_margin']} is not valid: "
                          "expected a tension margin less than half of the tension range "
                          f"({v['tension_max'] - v['tension_min']:.4g} N)")
    return ControlConfig(
        v["friction"], v["rotor_mass"], v["tension_min"], v["tension_max"], v["actuation_map.degree"],
        v["actuation_map.levels"], v["actuation_map.validation_samples"], v["inner_loop.rate"],
        v["inner_loop.proportional"], v["inner_loop.derivative"], v["inner_loop.integral"],
        v["inner_loop.integral_saturation"], v["inner_loop.tension_rate_limit"],
        v["inner_loop.feedforward"], v["clik.task_gain"], v["clik.equilibrium_gain"],
        v["clik.singular_threshold"], v["clik.rate"], v["clik.jacobian_rate"],
        v["clik.switch_delay"], v["clik.tolerance"],
        v["clik.seed_levels"], v["clik.reach_tolerance"], v["clik.stall_time"],
        v["clik.closest_margin"], v["clik.shaping.shaper"], v["clik.shaping.level"],
        tuple(v["clik.shaping.modes"]), v["clik.track_feedforward"], v["clik.min_frequency"],
        tuple(v["clik.rate_modes"]), v["clik.track_dynamics"], v["clik.track_learning.gain"],
        v["clik.track_learning.harmonics"], v["clik.track_learning.settle_time"],
        v["inner_loop.max_time_step"], v["clik.max_time_step"], v["clik.feedback"], TrustConfig.of(v),
        v["inner_loop.coordinates"])


def load_control_config(arm: ArmConfig, path: str | None = None, overrides=None) -> ControlConfig:
    """Load ``control.yaml`` (default: the package's) and validate it against ``arm``."""
    path = path or os.path.join(default_config_dir(), "control.yaml")
    return parse_control(load_section(path, "control", CONTROL_SCHEMA, overrides), arm)


@dataclass(frozen=True)
class Phase:
    """A phase of an experiment: ``mode`` clik (CLIK to each target, storing the reached q_d) or
    replay (the stored q_d given straight to the inner loop), a window [s] per target and the
    sequence of target indices (0-based) visited; a ``track`` phase's trajectory, followed from
    each target of its sequence."""
    name: str
    mode: str
    window: float
    sequence: tuple
    trajectory: Trajectory | None = None

    def target_at(self, target, t: float) -> np.ndarray:
        """The task coordinates [m] this phase asks for ``t`` [s] into a window on ``target``: a
        track phase's trajectory from it, the target itself otherwise."""
        x = np.array(target, dtype=float)
        return x if self.trajectory is None else self.trajectory.at(x, t)[0]


@dataclass(frozen=True)
class TaskConfig:
    """An experiment: actuated tendons (0-based), task space, targets (k, m) [m], phases, the
    steady-state time [s] used by the metrics and the plant's unmodelled tip payload (masses [kg],
    attach times [s]); the strike experiment's pendulum (None without one) and when its strike's
    reference is sent (:data:`STRIKE_TIMINGS`); the peak tip speed the paper reports for it [m/s]
    (None if it gives none)."""
    name: str
    tendons: tuple
    space: TaskSpace
    targets: tuple
    phases: tuple
    steady_time: float
    payload: tuple = ((), ())
    pendulum: PendulumConfig | None = None
    strike_timing: str = "release"
    paper_peak_speed: float | None = None


# A marker at arc length s is at most about s from the base (the backbone barely stretches): a target
# further than REACH * s is beyond every shape of the arm.
REACH = 1.1


def parse_task(name: str, v: dict, arm: ArmConfig) -> TaskConfig:
    """Cross-checks of one task's values against the arm and themselves."""
    def get(key):
        full = f"{name}.{key}"
        if full not in v:
            raise ConfigError(f"missing key tasks.{full}")
        return v[full]

    def bad(key, allowed):
        return ConfigError(f"tasks.{name}.{key} = {get(key)!r} is not valid: expected {allowed}")

    names = [t.name for t in arm.tendons]
    if any(t not in names for t in get("tendons")):
        raise bad("tendons", f"names among {names}")
    tendons = tuple(names.index(t) for t in get("tendons"))
    markers, axes = get("markers"), get("axes")
    n_markers = len(arm.marker_positions)
    if len(markers) != len(tendons) or any(k > n_markers for k in markers):
        raise bad("markers", f"{len(tendons)} marker numbers in 1..{n_markers} "
                             "(the task controls as many coordinates as it actuates tendons)")
    if len(axes) != len(markers):
        raise bad("axes", f"{len(markers)} axes, one per marker")
    space = TaskSpace(tuple(k - 1 for k in markers), tuple(AXES.index(a) for a in axes))
    flat = get("targets")
    m = space.m
    if len(flat) % m:
        raise bad("targets", f"groups of {m} coordinates ({', '.join(space.labels())}) per target")
    targets = tuple(tuple(flat[i:i + m]) for i in range(0, len(flat), m))
    for k, target in enumerate(targets):
        for marker in set(space.markers):
            reach = REACH * arm.marker_positions[marker]
            distance = math.hypot(*(x for x, j in zip(target, space.markers) if j == marker))
            if distance > reach:
                raise bad("targets", f"targets within {REACH:g} times their marker's arc length of the "
                                     f"base (target {k + 1}: marker{marker + 1} {distance:.4g} m away, "
                                     f"its reach {reach:.4g} m; a target in mm, or in another frame?)")
    phases = []
    for pname in get("phases"):
        seq = get(f"phase.{pname}.sequence")
        if any(k > len(targets) for k in seq):
            raise bad(f"phase.{pname}.sequence", f"target numbers in 1..{len(targets)}")
        phases.append(Phase(pname, get(f"phase.{pname}.mode"), get(f"phase.{pname}.window"),
                            tuple(k - 1 for k in seq), _trajectory(name, pname, v, space)))
    seen_clik = set()
    for ph in phases:
        if ph.mode == "clik":
            seen_clik.update(ph.sequence)
        elif ph.mode == "replay" and any(k not in seen_clik for k in ph.sequence):
            raise bad(f"phase.{ph.name}.sequence",
                      "targets reached by an earlier clik phase (replay needs a stored configuration)")
    masses = v.get(f"{name}.payload.masses", ())
    times = v.get(f"{name}.payload.attach_times", ())
    if len(masses) != len(times):
        raise ConfigError(f"tasks.{name}.payload.attach_times = {list(times)!r} is not valid: "
                          f"expected {len(masses)} times, one per payload mass")
    pendulum, timing = _pendulum(name, v)
    if pendulum is not None and phases[0].mode not in ("precomputed", "clik"):
        raise bad(f"phase.{phases[0].name}.mode", "precomputed or clik: a task with a pendulum strikes in "
                  "its first window, with the precomputed reference")
    return TaskConfig(name, tendons, space, targets, tuple(phases), get("steady_time"),
                      (tuple(masses), tuple(times)), pendulum, timing, v.get(f"{name}.paper_peak_speed"))


def _trajectory(name: str, phase: str, v: dict, space: TaskSpace) -> Trajectory | None:
    """The trajectory of a track phase (None for the other modes, which must not give one)."""
    prefix = f"{name}.phase.{phase}"
    given = {k.rpartition(".")[2]: val for k, val in v.items() if k.startswith(prefix + ".trajectory.")}
    mode = v[f"{prefix}.mode"]
    if mode != "track":
        if given:
            raise ConfigError(f"tasks.{prefix}.trajectory is given, but only a track phase follows one "
                              f"(its mode is {mode})")
        return None
    missing = [k for k in ("shape", "size", "period") if k not in given]
    if missing:
        raise ConfigError(f"tasks.{prefix}.trajectory lacks {', '.join(missing)}: a track phase needs "
                          "shape, size and period (plane optional)")
    plane = tuple(k - 1 for k in given.get("plane", (1, 2)))
    if max(plane) >= space.m:
        raise ConfigError(f"tasks.{prefix}.trajectory.plane = {[k + 1 for k in plane]} is not valid: "
                          f"expected coordinate numbers in 1..{space.m}")
    return Trajectory(given["shape"], given["size"], given["period"], plane)


def _pendulum(name: str, v: dict) -> tuple:
    """The task's pendulum and strike timing (None, "release" without a ``pendulum`` block)."""
    given = {k: v[f"{name}.pendulum.{k}"] for k in PENDULUM_KEYS if f"{name}.pendulum.{k}" in v}
    if not given:
        return None, "release"
    missing = [k for k in PENDULUM_KEYS if k not in given]
    if missing:
        raise ConfigError(f"tasks.{name}.pendulum lacks {', '.join(missing)} (a pendulum needs "
                          f"{', '.join(PENDULUM_KEYS)})")
    direction = np.array([*given["direction"], 0.0], dtype=float)
    return PendulumConfig(np.array(given["pivot"], dtype=float), given["length"], given["mass"],
                          given["ball_radius"], np.deg2rad(given["release_angle_deg"]),
                          direction / np.linalg.norm(direction), given["restitution"]), given["timing"]


def load_task_config(name: str, arm: ArmConfig, path: str | None = None, overrides=None) -> TaskConfig:
    """Load task ``name`` from ``tasks.yaml``; an unknown name lists the known ones."""
    v = load_section(path or os.path.join(default_config_dir(), "tasks.yaml"), "tasks", TASK_SCHEMA,
                     overrides)
    known = sorted({k.split(".")[0] for k in v})
    if name not in known:
        raise ConfigError(f"unknown task {name!r}; the tasks are: {', '.join(known)}")
    return parse_task(name, v, arm)


def control_of(params, arm: ArmConfig) -> ControlConfig:
    """``control`` of a node's parameters (:class:`soft_arm_ros.parameters.NodeParameters`)."""
    return parse_control(params.section("control", CONTROL_SCHEMA), arm)


# graph.task of the identification experiment (identification.yaml, not a task of tasks.yaml)
IDENTIFICATION = "identification"


def task_of(params, arm: ArmConfig) -> TaskConfig:
    """The task ``graph.task`` names, from a node's parameters (``tasks.yaml`` + its own values)."""
    values = params.section("tasks", TASK_SCHEMA)
    return parse_task(params.task_name({k.split(".")[0] for k in values}), values, arm)


def pendulum_of(params, arm: ArmConfig) -> PendulumConfig | None:
    """The pendulum of the task ``graph.task`` (None without one, and in the identification
    experiment)."""
    if params.graph["task"] == IDENTIFICATION:
        return None
    return task_of(params, arm).pendulum


def payload_of(params, arm: ArmConfig) -> tuple:
    """The unmodelled tip payload (masses [kg], attach times [s]) of the task ``graph.task``; none
    in the identification experiment (the arm as it is)."""
    if params.graph["task"] == IDENTIFICATION:
        return ((), ())
    return task_of(params, arm).payload
