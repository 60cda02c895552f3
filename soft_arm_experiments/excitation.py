"""The identification experiment's excitation, ROS-free: a schedule of tensions [N] against time [s].

In order: the hanging arm at ``tension_low``; quasi-static staircases on each tendon, then on each
pair (:func:`soft_arm_model.identification.staircase`: loaded and unloaded, so that friction shows
as hysteresis); a step on each tendon; a chirp on each chirp tendon; after every step and chirp the
hanging arm again for a full plateau. Every tension lies in [tension_low, tension_high] at every
instant, and those inside the controller's tension limits (checked on loading).
"""
from __future__ import annotations

import bisect
import os
from dataclasses import dataclass

import numpy as np

from soft_arm_model.identification import staircase
from soft_arm_model.parameters import ConfigError, default_config_dir, load_section

NAMESPACE = "identification"
SCHEMA = {
    "tension_low": ("float", lambda v: v >= 0, "a tension >= 0 N"),
    "tension_high": ("float", lambda v: v > 0, "a tension > 0 N"),
    "steps": ("int", lambda v: 1 <= v <= 10, "an integer in [1, 10]"),
    "pairs": ("ints", lambda v: len(v) % 2 == 0, "tendon numbers, two per pair"),
    "hold": ("float", lambda v: 0 < v <= 60, "a time in (0, 60] s"),
    "average": ("float", lambda v: v > 0, "a time > 0 s"),
    "step.tension": ("float", lambda v: v > 0, "a tension > 0 N"),
    "step.hold": ("float", lambda v: 0 < v <= 60, "a time in (0, 60] s"),
    "chirp.tendons": ("ints", None, "tendon numbers"),
    "chirp.amplitude": ("float", lambda v: v > 0, "a tension amplitude > 0 N"),
    "chirp.start_frequency": ("float", lambda v: 0 < v <= 50, "a frequency in (0, 50] Hz"),
    "chirp.end_frequency": ("float", lambda v: 0 < v <= 50, "a frequency in (0, 50] Hz"),
    "chirp.duration": ("float", lambda v: 0 < v <= 120, "a time in (0, 120] s"),
    "fit.min_plateau": ("float", lambda v: 0 < v <= 60, "a time in (0, 60] s"),
    "fit.rotor_mass": ("float", lambda v: 0 < v <= 100, "a mass in (0, 100] kg"),
    "fit.legendre_order": ("ints", lambda v: len(v) >= 1 and all(0 <= a <= 8 for a in v),
                           "Legendre orders in [0, 8], one per division of the arm"),
    "fit.shear": ("bool", None, "true or false (the two shear strains in the fit's model)"),
    "fit.dynamic_window": ("float", lambda v: 0 < v <= 60, "a time in (0, 60] s"),
    "fit.dynamic_timestep": ("float", lambda v: 1e-4 <= v <= 0.005, "a time step in [1e-4, 0.005] s"),
    "fit.max_evaluations": ("int", lambda v: 2 <= v <= 1000, "an integer in [2, 1000]"),
    "fit.basis_check.legendre_order": ("ints", lambda v: len(v) >= 1 and all(0 <= a <= 8 for a in v),
                                       "Legendre orders in [0, 8], one per division of the arm"),
    "fit.basis_check.shear": ("bool", None, "true or false"),
    "fit.basis_check.max_evaluations": ("int", lambda v: 0 <= v <= 1000,
                                        "an integer in [0, 1000] (0: no check)"),
}


@dataclass(frozen=True)
class Segment:
    """One part of the schedule: ``kind`` plateau, step or chirp, from ``start`` for ``duration``
    [s]; ``tension`` (n_t,) [N]: the constant tensions (plateau, step) or the others' tension during
    a chirp on ``tendon`` (0-based)."""
    kind: str
    start: float
    duration: float
    tension: np.ndarray
    tendon: int = -1


@dataclass(frozen=True)
class ExcitationConfig:
    """identification.yaml, checked (tendons 0-based)."""
    low: float
    high: float
    steps: int
    pairs: tuple
    hold: float
    average: float
    step_tension: float
    step_hold: float
    chirp_tendons: tuple
    chirp_amplitude: float
    chirp_f0: float
    chirp_f1: float
    chirp_duration: float


@dataclass(frozen=True)
class FitConfig:
    """identification.fit: how ``soft-arm-identify`` reads a recording (times [s], mass [kg]) and
    the static fit's strain basis (Legendre order per division, shear), and the basis its result
    is refitted on to see how far the basis moves it (``check_evaluations`` 0: not refitted)."""
    min_plateau: float
    average: float
    legendre_order: tuple
    shear: bool
    rotor_mass: float
    dynamic_window: float
    dynamic_timestep: float
    max_evaluations: int
    check_legendre_order: tuple
    check_shear: bool
    check_evaluations: int


def parse_fit(v: dict) -> FitConfig:
    """identification.fit (with identification.average: the settled end of a plateau), checked."""
    if v["average"] > v["fit.min_plateau"]:
        raise ConfigError(f"{NAMESPACE}.fit.min_plateau = {v['fit.min_plateau']!r} is not valid: "
                          f"expected a time >= identification.average = {v['average']:g} s")
    return FitConfig(v["fit.min_plateau"], v["average"], v["fit.legendre_order"], v["fit.shear"],
                     v["fit.rotor_mass"], v["fit.dynamic_window"],
                     v["fit.dynamic_timestep"], v["fit.max_evaluations"],
                     v["fit.basis_check.legendre_order"], v["fit.basis_check.shear"],
                     v["fit.basis_check.max_evaluations"])


def parse_excitation(v: dict, n_tendons: int, tension_min: float, tension_max: float) -> ExcitationConfig:
    """Cross-checks of identification.yaml's values against the arm's tendons and the controller's
    tension limits [N]."""
    def bad(key, allowed):
        return ConfigError(f"{NAMESPACE}.{key} = {v[key]!r} is not valid: expected {allowed}")

    low, high = v["tension_low"], v["tension_high"]
    if not tension_min <= low < high:
        raise bad("tension_low", f"a tension in [control.tension_min = {tension_min:g}, tension_high) N")
    if high > tension_max:
        raise bad("tension_high", f"a tension <= control.tension_max = {tension_max:g} N")
    flat = v["pairs"]
    pairs = tuple((flat[i] - 1, flat[i + 1] - 1) for i in range(0, len(flat), 2))
    if any(not (0 <= a < n_tendons and 0 <= b < n_tendons) or a == b for a, b in pairs):
        raise bad("pairs", f"pairs of two different tendon numbers in 1..{n_tendons}")
    if v["average"] > v["hold"]:
        raise bad("average", f"a time <= identification.hold = {v['hold']:g} s")
    if not low < v["step.tension"] <= high:
        raise bad("step.tension", f"a tension in (tension_low, tension_high] = ({low:g}, {high:g}] N")
    if any(not 1 <= k <= n_tendons for k in v["chirp.tendons"]):
        raise bad("chirp.tendons", f"tendon numbers in 1..{n_tendons}")
    if low + 2.0 * v["chirp.amplitude"] > high:
        raise bad("chirp.amplitude", f"an amplitude <= (tension_high - tension_low) / 2 = "
                                     f"{(high - low) / 2:g} N (the chirp peaks at low + 2 amplitude)")
    return ExcitationConfig(low, high, v["steps"], pairs, v["hold"], v["average"], v["step.tension"],
                            v["step.hold"], tuple(k - 1 for k in v["chirp.tendons"]),
                            v["chirp.amplitude"], v["chirp.start_frequency"], v["chirp.end_frequency"],
                            v["chirp.duration"])


def load_identification(path: str | None = None, overrides=None) -> dict:
    """identification.yaml's values (default: the package's file) with dotted ``overrides``."""
    path = path or os.path.join(default_config_dir(), "identification.yaml")
    return load_section(path, NAMESPACE, SCHEMA, overrides)


def load_excitation(n_tendons: int, tension_min: float, tension_max: float, path: str | None = None,
                    overrides=None) -> ExcitationConfig:
    """identification.yaml's excitation, checked against the tendons and the tension limits [N]."""
    return parse_excitation(load_identification(path, overrides), n_tendons, tension_min, tension_max)


class Excitation:
    """The schedule of ``config`` for ``n_tendons`` tendons: :meth:`tension` at any time."""

    def __init__(self, config: ExcitationConfig, n_tendons: int):
        self.config = c = config
        self.n_t = n_tendons
        rest = np.full(n_tendons, c.low)
        segments, t = [], 0.0

        def add(kind, duration, tension, tendon=-1):
            nonlocal t
            segments.append(Segment(kind, t, duration, np.asarray(tension, dtype=float), tendon))
            t += duration

        for u in staircase(n_tendons, c.low, c.high, c.steps, list(c.pairs)):
            add("plateau", c.hold, u)
        for k in range(n_tendons):
            u = rest.copy()
            u[k] = c.step_tension
            add("step", c.step_hold, u)
            add("plateau", c.hold, rest)
        for k in c.chirp_tendons:
            add("chirp", c.chirp_duration, rest, k)
            add("plateau", c.hold, rest)
        self.segments = segments
        self._starts = [s.start for s in segments]
        self.duration = t

    def segment(self, t: float) -> Segment:
        """The segment playing at t [s] (the last one from its end on)."""
        return self.segments[max(0, bisect.bisect_right(self._starts, t) - 1)]

    def tension(self, t: float) -> np.ndarray:
        """Tensions (n_t,) [N] at t [s] from the start; the hanging arm's before and after."""
        if not 0.0 <= t < self.duration:
            return np.full(self.n_t, self.config.low)
        s = self.segment(t)
        u = s.tension.copy()
        if s.kind == "chirp":
            c = self.config
            tau = t - s.start
            sweep = 0.5 * (c.chirp_f1 - c.chirp_f0) / c.chirp_duration     # Hz/s over 2
            phase = 2.0 * np.pi * (c.chirp_f0 * tau + sweep * tau ** 2)
            u[s.tendon] = c.low + c.chirp_amplitude * (1.0 - np.cos(phase))
        return u

    def summary(self) -> dict:
        """The schedule as JSON-ready data: duration [s] and every segment."""
        return {"duration": self.duration,
                "segments": [{"kind": s.kind, "start": s.start, "duration": s.duration,
                              "tension": s.tension.tolist(),
                              **({"tendon": s.tendon + 1} if s.tendon >= 0 else {})}
                             for s in self.segments]}
