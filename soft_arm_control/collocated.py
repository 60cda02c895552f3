"""Collocated coordinates of the arm (paper, "Low-level collocated control").

The equation of motion is written with the paper's input matrix B = -A (README, Conventions: tension u >= 0
pulls, ``M qdd + C qd + D qd + G(q) = B(q) u`` with ``G = F_el - F_g``). Tendons that the task does not
use are held at a constant tension (their pretension); their force is part of G.

Coordinates theta = [theta_a; theta_u] = h(q) with ``d theta_a/dt = B^T qd`` (tendon shortening
rates; exact without friction, quasi-static with it) and ``theta_u = S_u q`` for a constant selector
S_u. Then ``J_h = [B^T; S_u]`` and ``J_h^-T B = [I; 0]``: every actuated equation sees exactly one
tension. The transformed forces are ``K_theta = J_h^-T F_el``, ``F_theta = J_h^-T (G - F_el)`` and
``G_theta = K_theta + F_theta``; at an equilibrium ``G_theta = [u; 0]``, so ``G_theta_u = 0`` defines
the equilibrium set and ``G_theta_a`` is the feedforward tension. Both are independent of S_u.

Units: theta_a and shortenings [m]; theta_u are the selected coordinates of q [rad or -];
G_theta_a [N]; G_theta_u in the generalised-force units of the selected coordinates.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg
from numba import njit

from soft_arm_model import ArmData, ArmModel, actuation_matrix, evaluate, residual_jacobian, tangent_at
from soft_arm_model.dynamics import STATICS, mass_matrix


@dataclass(frozen=True, eq=False)
class CollocatedModel:
    """The collocated transformation for one set of actuated tendons.

    active: indices (0-based) of the actuated tendons, in task order; held: tension [N] of every
    tendon that is not actuated (zero on the actuated ones); selector: S_u, (n - n_a, n), constant;
    friction: use the paper's friction model in B and theta_a.
    """
    model: ArmModel
    active: tuple
    held: np.ndarray
    selector: np.ndarray
    friction: bool

    @property
    def n(self) -> int:
        return self.model.n

    @cached_property
    def active_index(self) -> np.ndarray:
        """``active`` as an integer array (the compiled terms' index)."""
        return np.array(self.active, dtype=np.int64)

    @property
    def n_a(self) -> int:
        return len(self.active)


def coordinate_selector(model: ArmModel, active, q_ref=None, friction: bool = True) -> np.ndarray:
    """S_u selecting the n - n_a coordinates of q that B(q_ref)^T depends on least.

    QR with column pivoting of B(q_ref)^T ranks the coordinates by how independently the tendons
    move them; the first n_a pivots are left to theta_a, the others become theta_u. This keeps
    J_h = [B^T; S_u] well conditioned near q_ref (default: the straight arm).
    """
    q_ref = np.zeros(model.n) if q_ref is None else np.asarray(q_ref, dtype=float)
    data = evaluate(model, ArmData(model), q_ref, level=STATICS)
    B = -(data.A if friction else data.A0)[:, list(active)]
    _, _, pivots = scipy.linalg.qr(B.T, pivoting=True, mode="economic")
    rest = np.sort(pivots[len(active):])
    S = np.zeros((model.n - len(active), model.n))
    S[np.arange(rest.size), rest] = 1.0
    return S


def build_collocated(model: ArmModel, active, held_tension: float = 0.0, friction: bool = True,
                     selector=None) -> CollocatedModel:
    """Collocated model for tendons ``active`` (0-based indices); the others hold ``held_tension`` [N].

    ``selector`` is S_u ((n - n_a, n)); by default :func:`coordinate_selector` at the straight arm.
    """
    active = tuple(int(k) for k in active)
    n_t = model.n_tendons
    if not active or len(set(active)) != len(active) or not all(0 <= k < n_t for k in active):
        raise ValueError(f"active tendons must be distinct indices in [0, {n_t - 1}], got {active}")
    if not np.isfinite(held_tension) or held_tension < 0:
        raise ValueError(f"held_tension must be >= 0 N, got {held_tension}")
    held = np.full(n_t, float(held_tension))
    held[list(active)] = 0.0
    S = coordinate_selector(model, active, friction=friction) if selector is None else \
        np.array(selector, dtype=float, order="C")
    if S.shape != (model.n - len(active), model.n):
        raise ValueError(f"selector must have shape ({model.n - len(active)}, {model.n}), got {S.shape}")
    S.setflags(write=False)
    held.setflags(write=False)
    return CollocatedModel(model, active, held, S, friction)


class CollocatedData:
    """Workspace of :func:`evaluate_collocated`; arrays are overwritten on every call.

    After a call: q; B (n, n_a); J_h (n, n); G (n); K_theta, F_theta, G_theta (n); u_eq = G_theta_a
    [N] (n_a); G_theta_u (n - n_a); shortening (n_t) = L_c(0) - L_c(q) [m]; theta_a (n_t), the
    friction-aware actuation coordinates [m] (equal to ``shortening`` without friction).
    """

    def __init__(self, cm: CollocatedModel):
        n, n_a = cm.n, cm.n_a
        self.arm = ArmData(cm.model)
        self.q = np.zeros(n)
        self.B = np.zeros((n, n_a))
        self.J_h = np.zeros((n, n))
        self.G = np.zeros(n)
        self.K_theta = np.zeros(n)
        self.F_theta = np.zeros(n)
        self.G_theta = np.zeros(n)
        self.shortening = np.zeros(cm.model.n_tendons)
        self.theta_a = np.zeros(cm.model.n_tendons)
        self.J_h_inv = np.zeros((n, n))

    @property
    def u_eq(self) -> np.ndarray:
        return self.G_theta[:self.B.shape[1]]

    @property
    def G_theta_u(self) -> np.ndarray:
        return self.G_theta[self.B.shape[1]:]

    def solve_transposed(self, rhs) -> np.ndarray:
        """J_h^-T rhs at the last evaluated q (rhs a vector or an (n, k) matrix)."""
        return self.J_h_inv.T @ rhs


def evaluate_collocated(cm: CollocatedModel, cd: CollocatedData, q, markers: bool = False) -> CollocatedData:
    """Fill ``cd`` at q (see :class:`CollocatedData`; ``cd.arm`` with the markers if ``markers``).
    Raises OutOfDomainError outside the domain, and ValueError when J_h is singular (the selector
    does not complement B^T at q)."""
    q = np.ascontiguousarray(q, dtype=float)
    cd.q[:] = np.nan            # until cd.arm holds q: a failed evaluation leaves no q to trust
    arm = evaluate(cm.model, cd.arm, q, level=STATICS, markers=markers)
    model = cm.model
    cd.q[:] = q
    try:
        regular = _collocated_terms(arm.A if cm.friction else arm.A0, cm.active_index, cm.selector, cm.held,
                                    arm.Fel, arm.Fg, model.rest_tendon_lengths, arm.Lc, model.rest_theta,
                                    arm.theta, cm.friction, cd.B, cd.J_h, cd.J_h_inv, cd.G, cd.K_theta,
                                    cd.F_theta, cd.G_theta, cd.shortening, cd.theta_a)
    except np.linalg.LinAlgError:
        regular = False
    if not regular:
        raise ValueError("J_h = [B^T; S_u] is singular at this configuration")
    return cd


@njit(cache=True, nogil=True)
def _collocated_terms(A, active, selector, held, Fel, Fg, rest_lengths, Lc, rest_theta, theta, friction,
                      B, J_h, J_h_inv, G, K_theta, F_theta, G_theta, shortening, theta_a) -> bool:
    """:func:`evaluate_collocated`'s terms from the workspace's statics (A: with friction or
    without, as ``friction``); False where J_h is singular (its inverse's scale beyond 1e12)."""
    n, n_a = A.shape[0], active.shape[0]
    for i in range(n):
        for a in range(n_a):
            B[i, a] = -A[i, active[a]]
            J_h[a, i] = B[i, a]
    for r in range(n - n_a):
        for i in range(n):
            J_h[n_a + r, i] = selector[r, i]
    J_h_inv[:, :] = np.linalg.inv(J_h)
    if np.abs(J_h_inv).max() * np.abs(J_h).max() > 1e12:
        return False
    for i in range(n):
        acc = Fel[i] - Fg[i]
        for k in range(A.shape[1]):
            acc += A[i, k] * held[k]
        G[i] = acc
    for i in range(n):                                   # J_h^-T F_el and J_h^-T (G - F_el)
        k_acc = 0.0
        f_acc = 0.0
        for j in range(n):
            k_acc += J_h_inv[j, i] * Fel[j]
            f_acc += J_h_inv[j, i] * (G[j] - Fel[j])
        K_theta[i] = k_acc
        F_theta[i] = f_acc
        G_theta[i] = k_acc + f_acc
    for k in range(Lc.shape[0]):
        shortening[k] = rest_lengths[k] - Lc[k]
        theta_a[k] = rest_theta[k] - theta[k] if friction else shortening[k]
    return True


def full_tensions(cm: CollocatedModel, u_active) -> np.ndarray:
    """Tensions of all tendons [N]: ``u_active`` on the actuated ones, the held tension elsewhere."""
    u = cm.held.copy()
    u[list(cm.active)] = u_active
    return u


def effective_stiffness(cm: CollocatedModel, cd: CollocatedData) -> np.ndarray:
    """H_eff = dG/dq - sum_i u_eq,i dB_i/dq at the last evaluated q (n, n).

    It is the tangent of the static residual at the tensions u_eq = G_theta_a(q), so that
    ``dG_theta/dq = J_h^-T H_eff``; the tendon part is the tension-induced geometric stiffness.
    It reads ``cd.arm`` as the last successful :func:`evaluate_collocated` left it at ``cd.q``
    (NaN after a failed one).
    """
    return tangent_at(cm.model, cd.arm, cd.q, full_tensions(cm, cd.u_eq), friction=cm.friction)


def held_stiffness(cm: CollocatedModel, q, u_active, proportional) -> np.ndarray:
    """The static stiffness of the arm at q under the inner loop, ``dR/dq + A K_p A0^T`` (n, n):
    the tangent of the static residual at the tensions ``u_active`` [N] of the actuated tendons plus
    the proportional gains ``proportional`` [N/m] (one per actuated tendon) on their shortenings
    (A with the friction model when ``cm.friction``, A0 the frictionless shortening Jacobian)."""
    cols = list(cm.active)
    _, jac = residual_jacobian(cm.model, q, full_tensions(cm, u_active), friction=cm.friction)
    a = actuation_matrix(cm.model, q, cm.friction)[:, cols]
    a0 = actuation_matrix(cm.model, q, False)[:, cols] if cm.friction else a
    return jac + a @ np.diag(np.asarray(proportional, dtype=float)) @ a0.T


def lowest_held_frequency(cm: CollocatedModel, q, u_active, proportional) -> float:
    """The lowest natural frequency [Hz] of the arm at q held by the inner loop (as
    :func:`held_stiffness`), from the smallest real part lambda of the eigenvalues of
    ``M^-1 (dR/dq + A K_p A0^T)`` (lambda = omega^2): ``sign(lambda) sqrt(|lambda|) / 2 pi``, so
    0 at a fold of the equilibria and negative (the divergence rate) where they are unstable. M is
    the arm's mass matrix (the rotors not included)."""
    stiffness = held_stiffness(cm, q, u_active, proportional)
    lam = float(np.linalg.eigvals(np.linalg.solve(mass_matrix(cm.model, q), stiffness)).real.min())
    return float(np.sign(lam) * np.sqrt(abs(lam)) / (2 * np.pi))


def collocated_jacobian(cm: CollocatedModel, cd: CollocatedData) -> np.ndarray:
    """dG_theta/dq = J_h^-T H_eff at the last evaluated q, (n, n): the first n_a rows are the rates
    of the feedforward tensions u_eq [N per unit of q], the others dG_theta_u/dq."""
    return cd.solve_transposed(effective_stiffness(cm, cd))


def equilibrium_jacobian(cm: CollocatedModel, cd: CollocatedData) -> np.ndarray:
    """dG_theta_u/dq = S J_h^-T H_eff at the last evaluated q, (n - n_a, n)."""
    return collocated_jacobian(cm, cd)[cm.n_a:]
