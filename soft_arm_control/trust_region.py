"""The online CLIK's trust region on an estimated feedback (ROS-free).

Closing the CLIK on a shape estimate (``--feedback estimate|fused``) may improve on the precomputed
reference, never make it worse. The CLIK predicts where each reference puts the arm at rest: the
model's task coordinates at the reference, x_model(q_d). What the estimate then shows differs from
it by the model's error at that pose, the *offset* o = x_hat - x_model(q_d): a few millimetres on
an arm that is the model to 15 %, slowly varying with the pose, swinging while the arm swings.
An estimate that has left the arm (another branch of the crossed tendons' equilibria, a bias
walking away) shows itself in the offset:

- **radius**: the offset, averaged over ``window``, is larger than any model error the lab expects
  (``radius`` [m]): the estimate claims the arm is where the model cannot put it (or the arm is
  there: a plant far from its model can settle on a branch the model does not have; the tendons
  cannot tell the two apart, and the precomputed reference is the closest safe thing to hold);
- **drift**: the offset, in means over quarter windows, leaves the straight line of the two windows
  before (carried on to now) by more than ``drift`` [m] beyond what the arm's own swing explains
  (half the peak-to-peak of those means about their line), or that line itself moves by more than
  ``drift`` + the swing over a ``window``: a walking bias, or a loop whose steps move the estimate
  the other way than they move the model (a branch on which the CLIK runs away). Along a track
  goal's periodic path the offset swings with the path (the arm's lag behind its reference), so
  the drift is judged on the offset averaged over the path's period before each frame
  (:meth:`TrustRegion.new_goal`).

A steady bias inside the radius shows itself in nothing the tendons measure: on an arm whose tendons
run a few per cent off their modelled paths the tendon-only estimate is 20 mm off at rest, three
times the precomputed reference's own error there. What the estimate can defend is what its
uncertainty says. With sigma_i the standard deviation of task coordinate i and ``confidence`` the
bound gamma on each coordinate's bias (``abs(b_i) <= gamma sigma_i``), the true error is the
estimated error ``e = x_d - x_hat`` plus that bias, which adds at most
``B = gamma sum_i abs(e_i) sigma_i`` along e. A step that takes a fraction alpha of e ends no
further from the target than no step, whatever the bias, if ``alpha <= 2 (1 - B / norm(e)^2)``:
:meth:`TrustRegion.fraction` is that alpha, clipped to [0, 1].
The online CLIK steps on alpha e: not on an error the estimate's uncertainty explains (within about
gamma sigma: no correcting step, the goal is *uncertain*), on all of one beyond twice that.

:class:`TrustRegion` keeps the recent offsets and judges each frame; the outer loop returns to the
precomputed reference when it refuses, and steps again only after ``recover`` seconds of frames it
accepts. Times are the caller's [s], coordinates [m] in arm_base.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class TrustConfig:
    """``radius`` [m], ``drift`` [m], ``window`` [s], ``recover`` [s] and ``confidence`` (standard
    deviations): see the module docstring; ``enabled``: the outer loop judges an estimated feedback
    with them."""
    radius: float
    drift: float
    window: float
    recover: float
    confidence: float = 2.0
    enabled: bool = True

    @classmethod
    def of(cls, values: dict) -> "TrustConfig":
        """From validated ``control`` values (``clik.trust.*``)."""
        return cls(*(float(values[f"clik.trust.{k}"])
                     for k in ("radius", "drift", "window", "recover", "confidence")),
                   bool(values["clik.trust.enabled"]))


class TrustRegion:
    """Judges an estimated feedback frame by frame (:meth:`judge`); :meth:`new_goal` starts a goal,
    :meth:`reset` forgets the offsets (a reference that jumped). ``judged`` counts the frames whose
    drift was judged (the history long enough and gapless)."""

    def __init__(self, config: TrustConfig):
        self.config = config
        self.period: float | None = None    # s: the path period the drift averages over (None: none)
        # the offsets over the last three windows (and a period and a quarter window more while
        # averaging over a period)
        self._history = _OffsetHistory()
        self.judged = 0

    def reset(self):
        self._history.clear()

    def new_goal(self, period: float | None = None):
        """Forget the offsets and judge a new goal's: ``period`` [s] is a track goal's path period
        (None: a fixed target). Along a periodic path the arm lags its reference by a phase and an
        amplitude of its own, so the offset swings with the path (by 13 mm on the fast circle,
        1.5 cm at 0.2 m/s), far beyond the drift; the drift is then judged on the offset averaged
        over the period before each frame, in which that swing and its harmonics cancel, so that a
        walk under it is seen as one. A path slower than two windows is judged as a fixed target
        (its lag moves along the line the judge fits, and averaging over its period would leave the
        drift unjudged for that long: the tracking task's slow circles take 20 s).
        """
        slow = period is None or period > 2.0 * self.config.window
        self.period = None if slow else float(period)
        self.reset()

    def fraction(self, error, sigma) -> float:
        """The fraction alpha in [0, 1] of the estimated task ``error`` [m] (target less estimate)
        that a step may take, given the standard deviations ``sigma`` [m] of the estimate's task
        coordinates (module docstring; 0 without ``sigma`` or with one that is no number: nothing
        is defended)."""
        if sigma is None:
            return 0.0
        sigma = np.asarray(sigma, dtype=float)
        if not np.all(np.isfinite(sigma)):
            return 0.0
        return defensible_fraction(error, sigma, self.config.confidence)

    def judge(self, t: float, x_estimate, x_model) -> str | None:
        """Take the frame at t [s] (the estimate's task coordinates and the model's at the current
        reference [m]); None when it is within the trust region, otherwise why not."""
        c = self.config
        offset = np.asarray(x_estimate, dtype=float) - np.asarray(x_model, dtype=float)
        # three windows, and on a periodic path a period and a quarter window more to average over
        span = 3.0 * c.window + (0.0 if self.period is None else self.period + 0.25 * c.window)
        times, offsets = self._history.append(float(t), offset, t - span - 1e-9)
        mean, judged, moved, walked, swing = _judgement(
            times, offsets, float(t), float(c.window), np.nan if self.period is None else self.period)
        if mean > c.radius:
            return (f"the estimate puts the task {mean * 1e3:.1f} mm from where the model "
                    f"puts the reference (trust radius {c.radius * 1e3:.1f} mm): it has left the arm, "
                    "or the arm the model")
        if not judged:
            return None                  # not yet three windows of offsets, or a gap in the frames
        self.judged += 1
        if moved > c.drift + swing:
            return (f"the estimate moved {moved * 1e3:.1f} mm away from what the reference explains "
                    f"(allowed {c.drift * 1e3:.1f} mm + the arm's swing {swing * 1e3:.1f} mm): a bias, "
                    "or a loop the estimate does not follow")
        if walked > c.drift + swing:
            return (f"the estimate walks {walked / c.window * 1e3:.1f} mm/s away from what the reference "
                    f"explains (allowed {c.drift * 1e3:.1f} mm + the arm's swing {swing * 1e3:.1f} mm "
                    f"over {c.window:.2f} s): a bias, or a loop the estimate does not follow")
        return None


@njit(cache=True, nogil=True)
def _judgement(times, offsets, t, window, period):
    """The figures :meth:`TrustRegion.judge` compares, from the kept frames' ``times`` (k,) [s],
    ascending, and ``offsets`` (k, d) [m], the latest at ``t`` [s]: (the norm of the offset averaged
    over the last ``window`` [s], whether the drift was judged, then, if it was, how far the
    latest quarter window moved from the line of the two windows before, how far that line walks
    over a window, and the swing about it [m]). On a periodic path (``period`` [s]; NaN: none) the
    drift is judged on the offsets averaged over the period before each frame (:func:`_period_means`).
    Not judged: fewer than three windows of frames, or a quarter window without one."""
    k, d = offsets.shape
    mean = np.zeros(d)
    count = 0
    for i in range(k):
        if times[i] >= t - window - 1e-9:
            count += 1
            for j in range(d):
                mean[j] += offsets[i, j]
    norm = 0.0
    for j in range(d):
        norm += (mean[j] / count) ** 2
    mean_norm = math.sqrt(norm)
    if not np.isnan(period):
        times, offsets = _period_means(times, offsets, period)
    if times.shape[0] == 0 or times[0] > t - 3.0 * window + 1e-9:
        return mean_norm, False, 0.0, 0.0, 0.0
    # the offset in quarter-window means (the frames' noise averaged out), oldest first: the two
    # windows before this one (a period of the arm's slowest swing, 0.8 s), then this one
    edges = (t - 3.0 * window) + (0.25 * window) * np.arange(13)
    edges[-1] += 1e-9
    means = np.zeros((12, d))
    counts = np.zeros(12)
    for i in range(times.shape[0]):
        b = np.searchsorted(edges, times[i], side="right") - 1
        if 0 <= b < 12:
            counts[b] += 1.0
            for j in range(d):
                means[b, j] += offsets[i, j]
    for b in range(12):
        if counts[b] == 0.0:
            return mean_norm, False, 0.0, 0.0, 0.0          # a gap in the frames: nothing to compare
        for j in range(d):
            means[b, j] /= counts[b]
    # the two windows before as a straight line (the offset's slow trend) and the swing about it
    # (its peak-to-peak: a walk of the offset is no swing, or a steady walk would excuse itself)
    slope = np.zeros(d)                                  # per quarter window
    centre = np.zeros(d)
    for j in range(d):
        for b in range(8):
            slope[j] += (b - 3.5) * means[b, j]
            centre[j] += means[b, j]
        slope[j] /= 42.0                                 # sum of (b - 3.5)^2 over the eight
        centre[j] /= 8.0
    before = np.empty((8, d))
    for b in range(8):
        for j in range(d):
            before[b, j] = means[b, j] - centre[j] - (b - 3.5) * slope[j]
    widest = 0.0
    for a in range(8):
        for b in range(a + 1, 8):
            apart = 0.0
            for j in range(d):
                apart += (before[a, j] - before[b, j]) ** 2
            widest = max(widest, apart)
    swing = 0.5 * math.sqrt(widest)                      # how far a swing takes the offset off its line
    moved = 0.0                                          # the latest quarter window against that line
    walked = 0.0                                         # the line itself over a window
    for j in range(d):
        moved += (means[11, j] - centre[j] - 7.5 * slope[j]) ** 2
        walked += (4.0 * slope[j]) ** 2
    return mean_norm, True, math.sqrt(moved), math.sqrt(walked), swing


@njit(cache=True, nogil=True)
def _period_means(times, offsets, period):
    """The offsets (k, d) [m] at ``times`` (k,) [s], ascending, averaged over the ``period`` [s]
    before each (that frame included), for the frames with a whole period of frames before them:
    (their times, the means)."""
    k, d = offsets.shape
    sums = np.zeros((k + 1, d))
    for i in range(k):
        for j in range(d):
            sums[i + 1, j] = sums[i, j] + offsets[i, j]
    first = np.searchsorted(times, times[0] + period - 1e-9)      # the first with a whole period
    out_t = np.empty(k - first)
    out_x = np.empty((k - first, d))
    for i in range(first, k):
        begin = np.searchsorted(times, times[i] - period + 1e-9)
        out_t[i - first] = times[i]
        for j in range(d):
            out_x[i - first, j] = (sums[i + 1, j] - sums[begin, j]) / (i + 1 - begin)
    return out_t, out_x


class _OffsetHistory:
    """The judged frames' times [s] and offsets [m], oldest first, in arrays that a frame appends to
    in place: a frame's judgement reads the last three windows (some 700 frames at 240 Hz) as views,
    without building them again from a queue each frame."""

    def __init__(self, capacity: int = 1024):
        self._t = np.empty(capacity)
        self._x: np.ndarray | None = None           # (capacity, d), once the first offset tells d
        self._head = self._tail = 0

    def clear(self):
        self._head = self._tail = 0

    def append(self, t: float, offset: np.ndarray, oldest: float) -> tuple[np.ndarray, np.ndarray]:
        """Add the frame at ``t`` [s] with its ``offset`` (d,) [m], forget the frames before
        ``oldest`` [s] (from the oldest on, as they came); the frames kept: (times (k,), offsets
        (k, d)), views valid until the next append or clear."""
        if self._x is None:
            self._x = np.empty((self._t.size, offset.size))
        if self._tail == self._t.size:
            kept = self._tail - self._head
            if kept > self._t.size // 2:                 # more than half full: twice the room
                self._t = np.concatenate([self._t, np.empty(self._t.size)])
                self._x = np.concatenate([self._x, np.empty_like(self._x)])
            self._t[:kept] = self._t[self._head:self._tail]
            self._x[:kept] = self._x[self._head:self._tail]
            self._head, self._tail = 0, kept
        self._t[self._tail] = t
        self._x[self._tail] = offset
        self._tail += 1
        while self._t[self._head] < oldest:
            self._head += 1
        return self._t[self._head:self._tail], self._x[self._head:self._tail]


def defensible_fraction(error, sigma, confidence: float) -> float:
    """``alpha = 2 (1 - B / norm(e)^2)`` clipped to [0, 1], ``B = confidence sum_i abs(e_i) sigma_i``:
    the largest fraction of the estimated ``error`` e [m] a step may take and end no further from the
    target than without it, whatever bias within ``confidence`` standard deviations ``sigma`` [m]
    per coordinate the estimate carries (module docstring). 0 for a zero error."""
    o = np.asarray(error, dtype=float)
    square = float(o @ o)
    if square == 0.0:
        return 0.0
    bound = confidence * float(np.abs(o) @ np.asarray(sigma, dtype=float))
    return float(np.clip(2.0 * (1.0 - bound / square), 0.0, 1.0))
