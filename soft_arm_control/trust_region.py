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

from dataclasses import dataclass

import numpy as np


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
        recent = offsets[times >= t - c.window - 1e-9]
        mean = recent.mean(axis=0)
        if np.linalg.norm(mean) > c.radius:
            return (f"the estimate puts the task {np.linalg.norm(mean) * 1e3:.1f} mm from where the model "
                    f"puts the reference (trust radius {c.radius * 1e3:.1f} mm): it has left the arm, "
                    "or the arm the model")
        if self.period is not None:
            times, offsets = period_means(times, offsets, self.period)
        if not times.size or times[0] > t - 3.0 * c.window + 1e-9:
            return None                      # not yet three windows of offsets: no drift to judge
        # the offset in quarter-window means (the frames' noise averaged out), oldest first: the two
        # windows before this one (a period of the arm's slowest swing, 0.8 s), then this one
        edges = t - 3.0 * c.window + 0.25 * c.window * np.arange(13)
        edges[-1] += 1e-9
        index = np.digitize(times, edges) - 1
        inside = (index >= 0) & (index < 12)
        counts = np.bincount(index[inside], minlength=12)
        if np.any(counts == 0):
            return None                      # a gap in the frames: nothing to compare
        self.judged += 1
        means = np.stack([np.bincount(index[inside], offsets[inside, j], minlength=12)
                          for j in range(offsets.shape[1])], axis=1) / counts[:, None]
        # the second before as a straight line (the offset's slow trend) and the swing about it
        # (its peak-to-peak: a walk of the offset is no swing, or a steady walk would excuse itself)
        k = np.arange(8.0) - 3.5
        slope = k @ means[:8] / (k @ k)                   # per quarter window
        before = means[:8] - means[:8].mean(axis=0) - np.outer(k, slope)
        # half its peak-to-peak: how far a swing takes the offset off its line
        swing = 0.5 * float(np.sqrt(np.max(np.sum((before[:, None] - before[None]) ** 2, axis=2))))
        # the latest quarter window against that line carried on to it: a walk that starts
        moved = float(np.linalg.norm(means[11] - means[:8].mean(axis=0) - 7.5 * slope))
        if moved > c.drift + swing:
            return (f"the estimate moved {moved * 1e3:.1f} mm away from what the reference explains "
                    f"(allowed {c.drift * 1e3:.1f} mm + the arm's swing {swing * 1e3:.1f} mm): a bias, "
                    "or a loop the estimate does not follow")
        # a steady walk: the line itself moving more than the drift over a window
        walked = float(np.linalg.norm(4.0 * slope))
        if walked > c.drift + swing:
            return (f"the estimate walks {walked / c.window * 1e3:.1f} mm/s away from what the reference "
                    f"explains (allowed {c.drift * 1e3:.1f} mm + the arm's swing {swing * 1e3:.1f} mm "
                    f"over {c.window:.2f} s): a bias, or a loop the estimate does not follow")
        return None


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


def period_means(times, offsets, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The offsets (k, d) [m] at ``times`` (k,) [s], ascending, averaged over the ``period`` [s]
    before each (that frame included), for the frames with a whole period of frames before them:
    (their times, the means)."""
    kept = times >= times[0] + period - 1e-9
    sums = np.vstack([np.zeros(offsets.shape[1]), np.cumsum(offsets, axis=0)])
    end = np.arange(1, times.size + 1)[kept]
    begin = np.searchsorted(times, times[kept] - period + 1e-9)
    return times[kept], (sums[end] - sums[begin]) / (end - begin)[:, None]
