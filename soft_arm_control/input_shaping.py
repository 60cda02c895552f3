"""Input shaping of the reference steps (Singer and Seering's zero-vibration shapers).

A step of the configuration reference (a replayed configuration, a precomputed CLIK solution)
moves the tendons in a fraction of a second, and the arm, its tendons held by the inner loop, is
left swinging in its slowest modes: for the triangle's poses 1.2-1.7 Hz with damping ratios near
0.1, which ring for seconds and keep a 1 s window out of the mm band. A shaper splits the step into
fractions given at delays chosen so that the vibrations they start in one mode (natural frequency
f [Hz], damping ratio zeta) cancel, with K = exp(-zeta pi / sqrt(1 - zeta^2)) and the damped period
T_d = 1 / (f sqrt(1 - zeta^2)):

- ``zv``: fractions (1, K) / (1 + K) at (0, T_d / 2): the shortest; the residual grows with the
  error of f (about a quarter of the step's at 10 %);
- ``zvd``: fractions (1, 2K, K^2) / (1 + K)^2 at (0, T_d / 2, T_d): twice as long, a flat zero (a
  few percent of residual at 20 % error of f);
- ``none``: the step itself (the paper's protocol).

The mode is the model's, at the step's destination q_d: the generalised eigenproblem of the static
stiffness under the inner loop (:func:`~.collocated.held_stiffness`, symmetric part) and the mass
matrix; its damping ratio from the material's damping and the inner loop's derivative gains on the
shortenings (``D + A0 K_D A0^T``). The mode shaped is the one whose free vibration after the step
stays longest above ``level`` [m] in task space: ln(A / level) / (zeta omega), A the amplitude of
the mode in the step projected on the task coordinates. A step is given unshaped when that time is
shorter than the shaper would take (a move whose vibration is small or well damped: the delay would
cost more than it saves). Rotor inertia and the inner loop's own dynamics are left out: the tendons
count as held.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from soft_arm_model import actuation_matrix
from soft_arm_model.dynamics import mass_matrix

from .clik import ClikPoint
from .collocated import CollocatedModel, held_stiffness
from .config import SHAPERS
from .task_space import TaskSpace


def impulses(shaper: str, frequency: float, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Delays [s] (ascending, the first 0) and fractions (summing to 1) of ``shaper`` for a mode of
    natural frequency ``frequency`` > 0 [Hz] and damping ratio ``damping`` >= 0. An overdamped mode
    (damping >= 1) and ``none`` give the step itself."""
    if shaper not in SHAPERS:
        raise ValueError(f"shaper {shaper!r} is not one of {list(SHAPERS)}")
    if not (frequency > 0 and np.isfinite(frequency) and damping >= 0):
        raise ValueError(f"a shaped mode needs a frequency > 0 Hz and a damping ratio >= 0, got "
                         f"{frequency} Hz, {damping}")
    if shaper == "none" or damping >= 1.0:
        return np.zeros(1), np.ones(1)
    root = np.sqrt(1.0 - damping ** 2)
    k = np.exp(-damping * np.pi / root)
    half = 0.5 / (frequency * root)
    if shaper == "zv":
        times, amplitudes = np.array([0.0, half]), np.array([1.0, k])
    else:
        times, amplitudes = np.array([0.0, half, 2 * half]), np.array([1.0, 2 * k, k * k])
    return times, amplitudes / amplitudes.sum()


@dataclass(frozen=True)
class Mode:
    """A vibration mode of the arm held by the inner loop: natural frequency [Hz], damping ratio and
    its amplitude in a step's free vibration, projected on the task coordinates [m]."""
    frequency: float
    damping: float
    amplitude: float

    def decay_time(self, level: float) -> float:
        """How long [s] the vibration's envelope stays above ``level`` > 0 [m] (0 if it starts
        below it; inf for an undamped mode above it)."""
        if self.amplitude <= level:
            return 0.0
        rate = self.damping * 2 * np.pi * self.frequency
        return np.log(self.amplitude / level) / rate if rate > 0 else np.inf


def step_modes(cm: CollocatedModel, task: TaskSpace, proportional, derivative, start: ClikPoint,
               end: ClikPoint) -> list:
    """The stable modes of the arm at ``end.q`` held by the inner loop (gains ``proportional``
    [N/m] and ``derivative`` [N s/m], one per actuated tendon) with the amplitudes a step from
    ``start`` excites, lowest frequency first."""
    model, cols = cm.model, list(cm.active)
    q = np.asarray(end.q, dtype=float)
    stiffness = held_stiffness(cm, q, end.u_ff, proportional)
    mass = mass_matrix(model, q)
    a0 = actuation_matrix(model, q, False)[:, cols]
    damping = model.D + a0 @ np.diag(np.asarray(derivative, dtype=float)) @ a0.T
    w2, shapes = scipy.linalg.eigh(0.5 * (stiffness + stiffness.T), mass)   # M-orthonormal shapes
    keep = w2 > 0
    w2, shapes = w2[keep], shapes[:, keep]
    omega = np.sqrt(w2)
    participation = shapes.T @ mass @ (np.asarray(start.q, dtype=float) - q)
    _, jx = task.evaluate(model, q)
    amplitude = np.linalg.norm(jx @ shapes, axis=0) * np.abs(participation)
    ratio = np.einsum("ij,ik,kj->j", shapes, damping, shapes) / (2 * omega)
    return [Mode(float(w / (2 * np.pi)), float(z), float(a)) for w, z, a in zip(omega, ratio, amplitude)]


def dominant_mode(modes, level: float) -> Mode | None:
    """The mode whose free vibration stays longest above ``level`` [m] in task space
    (:meth:`Mode.decay_time`); None when every mode starts below it."""
    mode = max(modes, key=lambda m: m.decay_time(level), default=None)
    return mode if mode is not None and mode.decay_time(level) > 0 else None


@dataclass(frozen=True)
class ShapedStep:
    """A reference step from ``start`` to ``end`` taken at t0 [s] in fractions: the reference at t
    is start + (sum of the fractions whose delay has passed) (end - start), on q, the shortenings,
    the feedforward tensions and the model task coordinates alike. ``mode``: the mode shaped (None:
    an unshaped step)."""
    start: ClikPoint
    end: ClikPoint
    t0: float
    times: np.ndarray
    fractions: np.ndarray
    mode: Mode | None = None

    @property
    def end_time(self) -> float:
        """When the last fraction is given [s]."""
        return self.t0 + float(self.times[-1])

    def fraction(self, t: float) -> float:
        """The part of the step given by time t [s] (1 from :attr:`end_time` on)."""
        if t >= self.end_time - 1e-9:
            return 1.0
        return float(self.fractions[self.times <= t - self.t0 + 1e-9].sum())

    def at(self, t: float) -> ClikPoint:
        """The reference at time t [s]."""
        p = self.fraction(t)
        if p >= 1.0:
            return self.end
        a, b = self.start, self.end
        return ClikPoint(*(u + p * (v - u) for u, v in ((a.q, b.q), (a.shortening, b.shortening),
                                                        (a.u_ff, b.u_ff), (a.x, b.x))))


class StepShaper:
    """Shapes reference steps on one collocated model and task (``shaper``: one of
    :data:`SHAPERS`; the inner loop's gains of the actuated tendons; ``level`` [m]: the vibration a
    step may leave, see the module docstring)."""

    def __init__(self, cm: CollocatedModel, task: TaskSpace, shaper: str, proportional, derivative,
                 level: float):
        if shaper not in SHAPERS:
            raise ValueError(f"shaper {shaper!r} is not one of {list(SHAPERS)}")
        if not level > 0:
            raise ValueError(f"the vibration level must be > 0 m, got {level}")
        self.cm, self.task, self.shaper, self.level = cm, task, shaper, float(level)
        self.proportional = np.asarray(proportional, dtype=float)
        self.derivative = np.asarray(derivative, dtype=float)

    def shape(self, t0: float, start: ClikPoint, end: ClikPoint) -> ShapedStep:
        """The step from ``start`` to ``end`` at t0 [s], shaped for its dominant mode, or unshaped
        when that mode's vibration falls below the level before the shaper would end."""
        step = ShapedStep(start, end, float(t0), np.zeros(1), np.ones(1))
        if self.shaper == "none":
            return step
        mode = dominant_mode(step_modes(self.cm, self.task, self.proportional, self.derivative,
                                        start, end), self.level)
        if mode is None:
            return step
        times, fractions = impulses(self.shaper, mode.frequency, mode.damping)
        if mode.decay_time(self.level) <= times[-1]:
            return step
        return ShapedStep(start, end, float(t0), times, fractions, mode)
