"""Learning a periodic path from the measured error, period by period (harmonic iterative learning),
ROS-free.

A track goal follows a periodic path x_d(tau) (:class:`~soft_arm_control.trajectories.Trajectory`,
period T [s], omega = 2 pi / T, tau from the goal's start). Whatever the arm repeats every period,
the model's static error along the path (the plant stiffer or softer than the model) and the part
of the path's dynamics the dynamic reference gets wrong (above the held arm's lowest mode), comes
back every period, where the online CLIK's error term (``control.clik.task_gain``, 0.5/s) is far
too slow to correct it. The learner corrects the path instead: the CLIK tracks the reference
x_r = x_d + c, with

    c(tau) = Re sum_k C_k exp(i k omega tau)        (k = 0 .. harmonics; C_k complex m-vectors)

and after every whole period the harmonics of the measured task coordinates X_k, of the reference
R_k and of the path D_k (sums over the period's CLIK steps) give, per coordinate, the period's
complex gain from reference to arm G_k = X_k / R_k (the whole closed loop: inner loop, CLIK, arm
and mocap latency, as the arm answered; the mean, k = 0, has gain 1: the CLIK's error term
integrates it), and the update

    C_k <- C_k + gain (D_k - X_k) / G_k.

With the gain below 1 it converges while the estimated G_k is within 90 degrees of the arm's
response (it is the arm's own measured answer; one gain per coordinate leaves out their coupling).
The new coefficients are blended in over the next period (a smoothstep, with its derivatives in the
reference's velocity and acceleration), so the reference has no step. Learned are the mean and, per
coordinate, the harmonics 1..``harmonics`` the path holds (|D_k| at least a tenth of the largest):
the circle and the line hold the first, the figure eight the first two. A period in which the CLIK
could not follow (a step constrained by the tension limits, or held: :meth:`add` is told) is not
learned from, and the correction learned so far is halved (blended in the same way): a path the
tendons cannot follow is not wound up against the limits. A period in which the dynamic reference
was clipped to the tension limits (``clipped``) is not learned from either (the arm's answer is not
the linear one the update assumes): the correction is kept, its error judged as below. The periods
that start within ``settle`` seconds of the goal (the arm's transient from rest, whose growing error
is no lesson) are watched, not learned from. A period whose error is more than :data:`WORSE` times
the best period's (the estimated G_k wrong: a path far above the arm's lowest mode, tensions
clipped) sends the learner back to the best period's correction with half the gain (the period it
takes to get there is not learned from; the next measures that correction's error again, as the new
best: the arm's answer to a correction takes periods to settle, so a best period can be a lucky
one). A wrong step costs the periods that try it and undo it; the gain halves with each. When the
best correction, measured again, does no better than no correction did (the first period learned
from), the learner gives up (``stopped``) and the path is tracked unlearned: it never keeps a
correction that does worse than none.

Units: task coordinates [m], times [s].
"""
from __future__ import annotations

import numpy as np

PRESENT = 0.1          # a harmonic of a coordinate is learned when |D_k| is this share of the largest
MIN_GAIN = 0.05        # nor when the arm's response to it, |G_k|, is below this (it did not follow)
BACK_OFF = 0.5         # the share of the correction kept after a period the CLIK could not follow
WORSE = 1.5            # a period's error this many times the best period's: back to the best


class HarmonicLearner:
    """The learned correction of one track goal's path: ``period`` [s], ``m`` task coordinates,
    the mean and the first ``harmonics`` harmonics, learning ``gain`` (0 < gain <= 1); the periods
    that start within ``settle`` [s] of the goal's start (the arm's transient from rest) are
    watched, not learned from."""

    def __init__(self, period: float, m: int, harmonics: int = 3, gain: float = 0.5, settle: float = 0.0):
        if not period > 0 or harmonics < 1 or not 0 < gain <= 1 or not settle >= 0:
            raise ValueError(f"a harmonic learner needs a period > 0 s, at least one harmonic, a gain "
                             f"in (0, 1] and a settling time >= 0 s, got {period}, {harmonics}, {gain}, "
                             f"{settle}")
        self.period, self.gain, self.settle = float(period), float(gain), float(settle)
        self.omega = 2 * np.pi / self.period
        self.k = np.arange(0, int(harmonics) + 1)
        self.previous = np.zeros((self.k.size, m), dtype=complex)    # C before the last change
        self.current = np.zeros((self.k.size, m), dtype=complex)     # C after it
        self.blend_from = 0.0          # tau [s] the current coefficients start blending in
        self.updates = 0               # periods learned from
        self.backed_off = 0            # periods after which the learner backed off
        self.frozen = 0                # periods not learned from: the dynamic reference was clipped
        self.gains: np.ndarray | None = None    # the last period's G_k (k, m)
        self.errors: list = []         # the error norm |D - X| of the learned harmonics, per period [m]
        self._best = (np.inf, self.current)     # the smallest period error [m] and its coefficients
        self._index = 0                # the period being summed
        self._sums = np.zeros((3, self.k.size, m), dtype=complex)    # X, R, D
        self._count = 0
        self._blocked = False          # the CLIK could not follow in the period being summed
        self._clipped = False          # the dynamic reference was clipped in it
        self._returning = False
        self._unlearned: float | None = None    # the error of the first period learned from (no correction)
        self.stopped = False           # given up: the path is tracked unlearned from then on

    def _harmonics(self, C: np.ndarray, tau: float) -> np.ndarray:
        """(value, first and second derivative) of Re sum_k C_k exp(i k omega tau): (3, m)."""
        w = self.k * self.omega
        e = np.exp(1j * w * tau)[:, None] * C
        return np.real(np.stack([e.sum(0), (1j * w[:, None] * e).sum(0), (-(w ** 2)[:, None] * e).sum(0)]))

    def correction(self, tau: float) -> np.ndarray:
        """c, its velocity and acceleration at tau [s] from the goal's start: (3, m) [m, m/s, m/s^2];
        the last change blended in over the period after it."""
        new = self._harmonics(self.current, tau)
        u = (tau - self.blend_from) / self.period
        if u >= 1.0:
            return new
        old = self._harmonics(self.previous, tau)
        u = max(u, 0.0)
        s = (3 - 2 * u) * u * u
        ds, dds = 6 * u * (1 - u) / self.period, (6 - 12 * u) / self.period ** 2
        d = new - old
        return np.stack([old[0] + s * d[0], old[1] + s * d[1] + ds * d[0],
                         old[2] + s * d[2] + 2 * ds * d[1] + dds * d[0]])

    def add(self, tau: float, desired, reference, measured, followed: bool = True,
            clipped: bool = False) -> bool:
        """A mocap frame at tau [s] from the goal's start: the path's ``desired`` coordinates, the
        ``reference`` the CLIK tracked, the ``measured`` ones [m]; ``followed``: False when the CLIK
        could not follow at this frame. The first frame of a new period closes the last one and
        learns from it; returns True when the correction changed."""
        index = int(tau // self.period)
        changed = False
        if index != self._index:
            if index == self._index + 1:
                changed = self._learn(tau)
            self._index, self._count, self._blocked, self._clipped = index, 0, False, False
            self._sums[:] = 0.0
        basis = np.exp(-1j * self.k * self.omega * tau)[:, None]
        for row, x in enumerate((measured, reference, desired)):
            self._sums[row] += basis * np.asarray(x, dtype=float)
        self._count += 1
        self._blocked |= not followed
        self._clipped |= clipped
        return changed

    def _learn(self, tau: float) -> bool:
        """The change at tau [s], the first frame of a period, from the sums of the last one."""
        if self.stopped or self._count < 4 * self.k[-1] or self._index * self.period < self.settle - 1e-9:
            return False                          # given up, frames missing, or the start's transient
        if self._blocked:
            self.backed_off += 1
            self._blend(tau, BACK_OFF * self.current)
            return True
        X, R, D = self._sums / self._count
        X[1:], R[1:], D[1:] = 2 * X[1:], 2 * R[1:], 2 * D[1:]       # amplitudes; k = 0: the mean
        learned = np.abs(D) >= PRESENT * np.abs(D[1:]).max()
        learned[0] = True
        gains = np.ones_like(self.current)
        with np.errstate(divide="ignore", invalid="ignore"):      # a reference harmonic cancelled
            gains[1:][learned[1:]] = X[1:][learned[1:]] / R[1:][learned[1:]]
        learned &= np.isfinite(gains) & (np.abs(gains) >= MIN_GAIN)
        self.gains = gains
        error = float(np.linalg.norm((D - X)[learned]))
        self.errors.append(error)
        if self._unlearned is None:
            self._unlearned = error
        if self._returning:                       # the period went back to the best: no lesson
            self._returning = False
            return False
        if np.isinf(self._best[0]) and self.updates and error > self._unlearned:
            self.stopped = True                   # the best, measured again, is no better than none
            self.backed_off += 1
            self._blend(tau, np.zeros_like(self.current))
            return True
        if error > WORSE * self._best[0]:         # worse than the best: back to it, learn slower
            self.backed_off += 1
            self.gain *= 0.5
            self._blend(tau, self._best[1])
            self._best = (np.inf, self._best[1])  # measured again once it is back
            self._returning = True
            return True
        if error < self._best[0]:
            self._best = (error, self.current)
        if self._clipped:
            self.frozen += 1
            return False
        step = np.zeros_like(self.current)
        step[learned] = self.gain * (D[learned] - X[learned]) / gains[learned]
        self.updates += 1
        self._blend(tau, self.current + step)
        return True

    def _blend(self, tau: float, coefficients: np.ndarray):
        """Blend ``coefficients`` in over the period that starts at the boundary before tau [s] (the
        last blend ended there)."""
        self.previous, self.current = self.current, coefficients
        self.blend_from = self.period * (tau // self.period)
