"""Workspace sampling (the paper's Fig. 2D): equilibria over combined tendon tensions."""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .dynamics import KINEMATICS, evaluate
from .model import ArmData, ArmModel
from .statics import EquilibriumError, solve_equilibrium


@dataclass(frozen=True)
class Workspace:
    """Sampled equilibria: tensions (N, n_t) [N], coordinates q (N, n), tip positions (N, 3) and
    marker positions (N, n_markers, 3) [m] in arm_base, tip rotations (N, 3, 3), and ``converged``
    (N,) — unconverged samples hold NaN."""
    tensions: np.ndarray
    q: np.ndarray
    tip: np.ndarray
    tip_rotation: np.ndarray
    markers: np.ndarray
    converged: np.ndarray


def sample_workspace(model: ArmModel, levels, tendons=None, friction: bool = True) -> Workspace:
    """Equilibria on the grid ``levels`` [N] per tendon (all tendons, or the indices ``tendons``).

    Samples are visited in lexicographic order and each continues from its neighbour one grid step
    back in the last tendon that changed, so every solve is a short load continuation.
    """
    levels = np.asarray(levels, dtype=float)
    if levels.ndim != 1 or levels.size < 1 or np.any(levels < 0):
        raise ValueError(f"levels must be a 1-D list of tensions >= 0 N, got {levels}")
    active = list(range(model.n_tendons)) if tendons is None else list(tendons)
    if not active or any(not 0 <= k < model.n_tendons for k in active):
        raise ValueError(f"tendons must be indices in [0, {model.n_tendons}), got {tendons}")
    grid = list(itertools.product(range(levels.size), repeat=len(active)))
    N = len(grid)
    tensions = np.zeros((N, model.n_tendons))
    q = np.full((N, model.n), np.nan)
    tip = np.full((N, 3), np.nan)
    rot = np.full((N, 3, 3), np.nan)
    markers = np.full((N, model.marker_X.size, 3), np.nan)
    ok = np.zeros(N, dtype=bool)
    index = {g: i for i, g in enumerate(grid)}
    data = ArmData(model)
    for i, g in enumerate(grid):
        tensions[i, active] = levels[list(g)]
        start_q, start_u = None, None
        for pos in range(len(g) - 1, -1, -1):  # nearest solved neighbour
            if g[pos] > 0:
                prev = index[g[:pos] + (g[pos] - 1,) + g[pos + 1:]]
                if ok[prev]:
                    start_q, start_u = q[prev], tensions[prev]
                break
        try:
            eq = solve_equilibrium(model, tensions[i], q_start=start_q, u_start=start_u,
                                   friction=friction, data=data)
        except EquilibriumError:
            continue
        d = evaluate(model, data, eq.q, level=KINEMATICS, markers=True)
        q[i], tip[i], rot[i], markers[i], ok[i] = eq.q, d.p[-1], d.R[-1], d.marker_p, True
    return Workspace(tensions, q, tip, rot, markers, ok)
