"""Exact least squares in a box for the few variables of a bounded CLIK step.

``min |A u - b|`` subject to ``lo <= u <= hi`` has, among its minimisers, one where every variable is
either at a bound or free and the free ones solve the least squares with the others held (a vertex
of the set of minimisers: its free columns of A are independent, so that solve is unique there).
So the minimum is the cheapest of the 3^n candidates "each variable at lo, at hi or free", each
clipped into the box and costed at the point it then is: every candidate is a feasible point, so
none undercuts the minimum, and the vertex's candidate reaches it. With n the task's dimension (3-4)
that is 27-81 small solves, done as one batched solve of the free blocks' normal equations (each
pattern on its own by a least-squares solve where a free block is singular): no iteration count or
tolerance to tune, and the same answer on any arithmetic up to rounding when A has full column rank
(the minimiser is then unique). The normal equations square A's condition number: exact to
rounding for the CLIK's well-conditioned tension-rate maps, not for A near rank deficiency.
"""
from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np

_MAX_VARIABLES = 8          # 3^8 = 6561 candidates; beyond, an iterative solver is the right tool


@lru_cache(maxsize=None)
def _patterns(n: int) -> np.ndarray:
    """(3^n, n) int8: each variable 0 free, 1 at its lower bound, 2 at its upper."""
    return np.array(list(itertools.product((0, 1, 2), repeat=n)), dtype=np.int8)


def box_least_squares(A, b, lo, hi) -> np.ndarray:
    """The u [any unit] minimising ``|A u - b|`` with ``lo <= u <= hi`` (element-wise).

    A: (k, n) with n <= 8; b: (k,); all finite. Where A is rank deficient the minimiser is not
    unique and one of them is returned. Raises ValueError on bad shapes, values or bounds."""
    A, b = np.asarray(A, dtype=float), np.asarray(b, dtype=float)
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    if A.ndim != 2 or b.shape != A.shape[:1]:
        raise ValueError(f"A must be (k, n) and b (k,): got {A.shape} and {b.shape}")
    n = A.shape[1]
    if not 1 <= n <= _MAX_VARIABLES:
        raise ValueError(f"{n} variables: box_least_squares takes 1 to {_MAX_VARIABLES}")
    if lo.shape != (n,) or hi.shape != (n,):
        raise ValueError(f"lo and hi must be ({n},): got {lo.shape} and {hi.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise ValueError("A and b must be finite")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise ValueError(f"the box must be finite with lo <= hi: lo {lo}, hi {hi}")
    pattern = _patterns(n)
    free = pattern == 0
    held = np.where(pattern == 1, lo, np.where(pattern == 2, hi, 0.0))      # (p, n)
    residual = b - held @ A.T                                                # (p, k)
    # The free block's normal equations, a multiple of the identity on the held block (on H's
    # scale), so that each pattern is one (n, n) system of the batch.
    H = A.T @ A
    scale = float(np.max(np.diag(H))) or 1.0
    both_free = free[:, :, None] & free[:, None, :]
    normal = np.where(both_free, H, 0.0) + np.where(~free, scale, 0.0)[:, :, None] * np.eye(n)
    rhs = np.where(free, residual @ A, scale * held)
    try:
        u = np.linalg.solve(normal, rhs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:       # a free block without full rank (A wide or deficient)
        u = np.array([_held_least_squares(A, r, f, h) for r, f, h in zip(residual, free, held)])
    u = np.clip(np.where(free, u, held), lo, hi)     # held ones exactly at their bounds
    cost = np.sum((u @ A.T - b) ** 2, axis=1)
    return u[np.argmin(cost)].copy()


def _held_least_squares(A, residual, free, held) -> np.ndarray:
    """One pattern's candidate: the held variables at ``held``, the free ones the least squares
    (minimum norm) of A's free columns against ``residual`` = b - A held."""
    u = held.copy()
    if free.any():
        u[free] = np.linalg.lstsq(A[:, free], residual, rcond=None)[0]
    return u
