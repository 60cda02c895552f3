"""Timing helper shared by the benchmark scripts."""
import time

import numpy as np


def best_of(fn, repeats: int = 7, inner: int = 500) -> float:
    """The best mean time [s] of one call of ``fn`` over ``repeats`` runs of ``inner`` calls."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, (time.perf_counter() - t0) / inner)
    return best
