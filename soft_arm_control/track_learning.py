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

and after every whole period the mean and harmonics of the measured task coordinates X_k, of the
reference R_k and of the path D_k, fitted by least squares over the period's frames (frames may be
missing or uneven: a period whose frames do not cover it is not used), give, per coordinate, the
period's complex gain from reference to arm G_k = X_k / R_k (the whole closed loop: inner loop,
CLIK, arm and mocap latency, as the arm answered; the mean, k = 0, has gain 1: the CLIK's error
term integrates it), and the update, from the correction the period applied (R_k - D_k)::

    C_k <- (R_k - D_k) + gain (D_k - X_k) / G_k.

With the gain below 1 it converges while the estimated G_k is within 90 degrees of the arm's
response (it is the arm's own measured answer; one gain per coordinate leaves out their coupling).
The new coefficients are blended in over the next period (a quintic smootherstep, with its
derivatives in the reference's velocity and acceleration: the reference, its velocity and its
acceleration have no step). Learned are the mean and, per coordinate, the harmonics
1..``harmonics`` the path holds (``|D_k|`` at least a tenth of the largest): the circle and the line
hold the first, the figure eight the first two. A frame with a non-finite coordinate is dropped.

Guards, so that learning cannot make the tracking much worse than the CLIK alone:

- The periods that start within ``settle`` seconds of the goal (the arm's transient from rest,
  whose growing error is no lesson) are watched, not learned from.
- A period in which the CLIK could not follow (a step constrained by the tension limits, or held:
  :meth:`add` is told) is not learned from; the correction is halved and so is the gain: a path the
  tendons cannot follow is not wound up against the limits again and again.
- A period in which the dynamic reference was clipped to the tension limits (``clipped``) is not
  learned from either (the arm's answer is not the linear one the update assumes); the correction
  is kept, and its error judged as below.
- A period whose error is more than :data:`WORSE` times the best period's (the estimated G_k
  wrong: a path far above the arm's lowest mode) sends the learner back to the best correction with
  half the gain; the periods that take (the blend back, and ``settle`` for the arm's ringing) are
  not learned from, and the next one measures that correction's error again, as the new best (a
  best period can be a lucky one). If it does worse than the path did unlearned (the first period
  learned from), the correction is dropped: none is the best.
- Once the gain has halved :data:`HALVINGS` times, the learner stops (``stopped``) and keeps its
  best correction.

Units: task coordinates [m], times [s].
"""
from __future__ import annotations

import math

import numpy as np

PRESENT = 0.1          # a harmonic of a coordinate is learned when |D_k| is this share of the largest
MIN_GAIN = 0.05        # nor when the arm's response to it, |G_k|, is below this (it did not follow)
BACK_OFF = 0.5         # the share of the correction kept after a period the CLIK could not follow
WORSE = 1.5            # a period's error this many times the best period's: back to the best
HALVINGS = 4           # the learner stops when its gain has halved this many times
COVERAGE = 100.0       # a period whose least-squares fit is worse conditioned than this is not used


def smootherstep(u: float) -> tuple[float, float, float]:
    """The quintic 10 u^3 - 15 u^4 + 6 u^5 on [0, 1] and its first two derivatives in u (all three
    continuous: 0 at u = 0, and 1, 0, 0 at u = 1)."""
    return (u ** 3 * (10 - 15 * u + 6 * u * u), 30 * u * u * (1 - u) ** 2,
            60 * u * (1 - u) * (1 - 2 * u))


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
        self.stopped = False           # the gain has halved HALVINGS times: the best correction kept
        self.gains: np.ndarray | None = None    # the last period's G_k (k, m)
        self.errors: list = []         # the error norm |D - X| of the learned harmonics, per period [m]
        self._min_gain = self.gain * 0.5 ** HALVINGS
        self._best = (np.inf, self.current)     # the smallest period error [m] and its coefficients
        self._unlearned: float | None = None    # the error of the first period learned from
        self._wait = 0                 # periods still not to learn from after going back
        self._index = 0                # the period being fitted
        self._normal = np.zeros((2 * self.k.size - 1,) * 2)        # sum of phi phi^T over its frames
        self._moments = np.zeros((3, 2 * self.k.size - 1, m))     # sum of phi x^T: X, R, D
        self._blocked = False          # the CLIK could not follow in the period being fitted
        self._clipped = False          # the dynamic reference was clipped in it

    def _harmonics(self, C: np.ndarray, tau: float) -> np.ndarray:
        """(value, first and second derivative) of Re sum_k C_k exp(i k omega tau): (3, m)."""
        w = self.k * self.omega
        e = np.exp(1j * w * tau)
        return np.real(np.array([e, 1j * w * e, -w * w * e]) @ C)

    def correction(self, tau: float) -> np.ndarray:
        """c, its velocity and acceleration at tau [s] from the goal's start: (3, m) [m, m/s, m/s^2];
        the last change blended in over the period from its time."""
        new = self._harmonics(self.current, tau)
        T = self.period
        u = (tau - self.blend_from) / T
        if u >= 1.0:
            return new
        old = self._harmonics(self.previous, tau)
        s, ds, dds = smootherstep(max(u, 0.0))
        ds, dds = ds / T, dds / T ** 2
        d = new - old
        return np.stack([old[0] + s * d[0], old[1] + s * d[1] + ds * d[0],
                         old[2] + s * d[2] + 2 * ds * d[1] + dds * d[0]])

    def _basis(self, tau: float) -> np.ndarray:
        """phi(tau) = [1, cos(k omega tau), sin(k omega tau) for k >= 1]."""
        w = self.k[1:] * self.omega * tau
        return np.concatenate([[1.0], np.cos(w), np.sin(w)])

    def add(self, tau: float, desired, reference, measured, followed: bool = True,
            clipped: bool = False) -> bool:
        """A mocap frame at tau [s] from the goal's start: the path's ``desired`` coordinates, the
        ``reference`` the CLIK tracked, the ``measured`` ones [m]; ``followed``: False when the CLIK
        could not follow at this frame; ``clipped``: the dynamic reference was clipped. The first
        frame of a new period closes the last one and learns from it; returns True when the
        correction changed."""
        index = int(tau // self.period)
        changed = False
        if index != self._index:
            if index == self._index + 1:
                changed = self._learn(tau)
            self._index, self._blocked, self._clipped = index, False, False
            self._normal[:] = 0.0
            self._moments[:] = 0.0
        signals = np.array([measured, reference, desired], dtype=float)
        if not np.all(np.isfinite(signals)):
            return changed
        phi = self._basis(tau)
        self._normal += np.outer(phi, phi)
        self._moments += phi[None, :, None] * signals[:, None, :]
        self._blocked |= not followed
        self._clipped |= clipped
        return changed

    def _fit(self):
        """The period's (X, R, D): complex amplitudes (k, m), k = 0 the mean; None when its frames
        do not cover it (too few, or a gap that leaves the fit ill-conditioned)."""
        n = self._normal[0, 0]
        if n < 2 * self._normal.shape[0] or np.linalg.cond(self._normal / n) > COVERAGE:
            return None
        theta = np.linalg.solve(self._normal, self._moments.transpose(1, 0, 2).reshape(len(self._normal), -1))
        theta = theta.reshape(len(self._normal), 3, -1).transpose(1, 0, 2)          # (3, 1 + 2K, m)
        K = self.k.size - 1
        amplitudes = np.empty((3, self.k.size, theta.shape[2]), dtype=complex)
        amplitudes[:, 0] = theta[:, 0]
        amplitudes[:, 1:] = theta[:, 1:1 + K] - 1j * theta[:, 1 + K:]    # a cos + b sin = Re((a - ib) e^iwt)
        return amplitudes

    def _learn(self, tau: float) -> bool:
        """The change at tau [s], the first frame of a period, from the fit of the last one."""
        if self.stopped or self._index * self.period < self.settle - 1e-9:
            return False                          # stopped, or the start's transient
        fit = self._fit()
        if fit is None:                           # frames missing: nothing to learn from
            return False
        if self._blocked:
            self.backed_off += 1
            self._slow_down()
            self._best = (np.inf, BACK_OFF * self.current)
            self._blend(tau, BACK_OFF * self.current)
            return True
        X, R, D = fit
        learned = np.abs(D) >= PRESENT * np.abs(D[1:]).max()
        learned[0] = True
        gains = np.ones_like(self.current)
        with np.errstate(divide="ignore", invalid="ignore"):      # a reference harmonic cancelled
            gains[1:][learned[1:]] = X[1:][learned[1:]] / R[1:][learned[1:]]
        learned &= np.isfinite(gains) & (np.abs(gains) >= MIN_GAIN)
        self.gains = gains
        error = float(np.linalg.norm((D - X)[learned]))
        self.errors.append(error)
        applied = np.where(learned, R - D, self.current)     # the correction this period ran
        if self._unlearned is None:
            self._unlearned = error
        if self._wait:                            # going back to the best: no lesson yet
            self._wait -= 1
            return False
        if np.isinf(self._best[0]):               # the first period, or the best measured again
            if error > self._unlearned:           # it does worse than none did: drop it
                self.backed_off += 1
                self._best = (self._unlearned, np.zeros_like(self.current))
                self._go_back(tau)
                return True
            self._best = (error, applied)
        elif error > WORSE * self._best[0]:       # worse than the best: back to it, learn slower
            self.backed_off += 1
            self._slow_down()
            self._go_back(tau)
            self._best = (np.inf, self._best[1])  # measured again once it is back
            return True
        elif error < self._best[0]:
            self._best = (error, applied)
        if self._clipped:
            self.frozen += 1
            return False
        step = np.zeros_like(self.current)
        step[learned] = self.gain * (D[learned] - X[learned]) / gains[learned]
        self.updates += 1
        self._blend(tau, applied + step)
        return True

    def _go_back(self, tau: float):
        """Blend the best correction back in from tau [s]; not learned from until the blend and the
        arm's ringing (``settle``) are over."""
        self._wait = max(1, math.ceil(self.settle / self.period))
        self._blend(tau, self._best[1])

    def _slow_down(self):
        """Halve the gain; stop at :data:`HALVINGS` halvings."""
        self.gain *= 0.5
        self.stopped = self.gain < self._min_gain * 1.0001

    def _blend(self, tau: float, coefficients: np.ndarray):
        """Blend ``coefficients`` in over the period from tau [s]. A blend not over yet (a period's
        first frame late, the next early) is cut where it is: its coefficients at tau start the new
        one (the correction has no step, its velocity a small one)."""
        u = (tau - self.blend_from) / self.period
        start = self.current
        if u < 1.0:
            start = self.previous + smootherstep(max(u, 0.0))[0] * (self.current - self.previous)
        self.previous, self.current = start, coefficients
        self.blend_from = tau
