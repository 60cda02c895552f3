"""Playing an experiment of ``tasks.yaml`` against a stream of mocap frames, ROS-free.

The schedule starts at the first frame; at each window start the runner issues the goal (target
coordinates and the phase's mode). It keeps the measured task coordinates and tip positions of
every frame and, at the end, computes the paper's metrics (the peak tip speed from differences of
the measured tip positions over at least 10 ms, as on the rig).
"""
from __future__ import annotations

import numpy as np

from soft_arm_control.config import TaskConfig

from .metrics import measured_speed, summarise, transition_metrics


class TaskRunner:
    """Runs one task; ``tip_marker``: index of the tip among the markers."""

    def __init__(self, task: TaskConfig, tip_marker: int):
        self.task = task
        self.windows = [(ph.name, ph.mode, k, ph.window) for ph in task.phases for k in ph.sequence]
        self.tip = tip_marker
        self.tip_axes = [a for k, a in zip(task.space.markers, task.space.axes) if k == tip_marker] \
            or [0, 1, 2]
        self.t0 = None
        self.index = -1
        self.starts = np.cumsum([0.0] + [w[3] for w in self.windows])
        self.samples = []          # (t, window, x, x_d, tip)

    @property
    def duration(self) -> float:
        return float(self.starts[-1])

    @property
    def done(self) -> bool:
        return self.t0 is not None and self.index >= len(self.windows)

    def frame(self, t: float, markers) -> tuple | None:
        """A mocap frame at time t [s] (markers (n, 3) [m]); returns (x_d, mode) when a new window
        starts with this frame, else None."""
        if self.t0 is None:
            self.t0 = t
        goal = None
        rel = t - self.t0
        while self.index < len(self.windows) and rel >= self.starts[self.index + 1] - 1e-9:
            self.index += 1
            if self.index < len(self.windows):
                _, mode, k, _ = self.windows[self.index]
                goal = (np.array(self.task.targets[k]), mode)
        if 0 <= self.index < len(self.windows):
            markers = np.asarray(markers, dtype=float)
            k = self.windows[self.index][2]
            self.samples.append((rel, self.index, self.task.space.from_markers(markers),
                                 np.array(self.task.targets[k]), markers[self.tip, self.tip_axes],
                                 markers[self.tip].copy()))
        return goal

    def metrics(self):
        """(per-transition metrics, summary) of the windows played so far."""
        rows = []
        for w, (phase, _, k, window) in enumerate(self.windows):
            s = [x for x in self.samples if x[1] == w]
            if len(s) < 3:
                continue
            t = np.array([x[0] for x in s])
            tip3 = np.array([x[5] for x in s])
            speed = measured_speed(t, tip3)
            rows.append(transition_metrics(phase, k + 1, t, np.array([x[3] - x[2] for x in s]),
                                           np.array([x[4] for x in s]), speed,
                                           self.task.steady_time, window))
        return rows, (summarise(rows) if rows else None)
