"""Task coordinates: a list of (marker, axis) pairs read from the model's marker kinematics.

A task coordinate is one Cartesian component [m] in ``arm_base`` of one tracked marker; markers are
the arm's ``markers.positions`` in order from the base (index 0) to the tip (last index).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

from soft_arm_model import ArmData, ArmModel, evaluate
from soft_arm_model.dynamics import KINEMATICS

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class TaskSpace:
    """Controlled coordinates: ``markers`` (0-based marker indices) and ``axes`` (0, 1, 2 = x, y, z)."""
    markers: tuple
    axes: tuple

    def __post_init__(self):
        if len(self.markers) != len(self.axes) or not self.markers:
            raise ValueError("a task needs one axis per marker and at least one coordinate")
        if any(a not in (0, 1, 2) for a in self.axes):
            raise ValueError(f"axes must be 0, 1 or 2 (x, y, z), got {self.axes}")
        if len(set(zip(self.markers, self.axes))) != len(self.axes):
            raise ValueError("task coordinates must be distinct")

    @property
    def m(self) -> int:
        return len(self.axes)

    @cached_property
    def _index(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.markers, dtype=np.int64), np.array(self.axes, dtype=np.int64)

    def labels(self) -> list:
        """Human-readable names, e.g. ``marker4.x`` (markers numbered from 1 at the base)."""
        return [f"marker{k + 1}.{AXES[a]}" for k, a in zip(self.markers, self.axes)]

    def check(self, model: ArmModel):
        """Raise ValueError if a marker index is outside the model's markers."""
        n_markers = model.marker_X.size
        if any(not 0 <= k < n_markers for k in self.markers):
            raise ValueError(f"task markers {[k + 1 for k in self.markers]} outside 1..{n_markers}")

    def from_markers(self, markers) -> np.ndarray:
        """Task coordinates from marker positions (n_markers, 3) [m], e.g. a mocap frame."""
        markers = np.asarray(markers, dtype=float)
        return markers[list(self.markers), list(self.axes)].copy()

    def tip_sigma(self, tip_covariance) -> np.ndarray:
        """(m,) [m]: each coordinate's standard deviation read from the tip's position covariance
        (3, 3) [m^2] along its axis, for the markers nearer the base too (on an arm hanging from
        its base the tip is the least certain marker: the tip's bounds theirs). A covariance that is
        no number gives NaN."""
        variance = np.diagonal(np.asarray(tip_covariance, dtype=float))[list(self.axes)]
        return np.sqrt(np.where(variance >= 0.0, variance, np.nan))

    def evaluate(self, model: ArmModel, q, data: ArmData | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Task coordinates x(q) [m] and their Jacobian dx/dq (m, n) from the model."""
        return self.read(model, evaluate(model, data or ArmData(model), q, level=KINEMATICS, markers=True))

    def read(self, model: ArmModel, data: ArmData) -> tuple[np.ndarray, np.ndarray]:
        """Task coordinates [m] and their Jacobian (m, n) at the q ``data`` was evaluated at with
        its markers."""
        x, J = np.empty(self.m), np.empty((self.m, model.n))
        _read(data.marker_p, data.marker_R, data.marker_J, *self._index, x, J)
        return x, J


@njit(cache=True, nogil=True)
def _read(marker_p, marker_R, marker_J, markers, axes, x, J):
    """x[row] = component ``axes[row]`` of marker ``markers[row]``'s position [m], J[row] its
    row of R J[3:6] (the position's Jacobian in arm_base)."""
    for row in range(markers.shape[0]):
        k, a = markers[row], axes[row]
        x[row] = marker_p[k, a]
        for j in range(J.shape[1]):
            J[row, j] = (marker_R[k, a, 0] * marker_J[k, 3, j] + marker_R[k, a, 1] * marker_J[k, 4, j]
                         + marker_R[k, a, 2] * marker_J[k, 5, j])
