"""Percentiles for the motor driver's reports, computed in its cycle thread.

Not ``np.percentile``: its first call in a process imports ``numpy.ma`` (``np.unique`` asks
whether the array is masked), and an import in the cycle thread holds the interpreter until it is
done: 7 ms on an idle machine, longer on a loaded one, out of a 2-4 ms cycle.
"""
from __future__ import annotations

import numpy as np


def percentile(ascending: np.ndarray, q: float) -> float:
    """The ``q``-th percentile (0-100) of the non-empty ``ascending`` values, linear between the
    closest ranks (``np.percentile``'s default method)."""
    position = q / 100.0 * (ascending.size - 1)
    low = int(position)
    high = min(low + 1, ascending.size - 1)
    return float(ascending[low] + (position - low) * (ascending[high] - ascending[low]))
