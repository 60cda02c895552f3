"""The tendons' routing through the cross-sections, and how the tendon terms change with it.

Tendon k runs at d_k(X) = rho_k(X) (0, sin th_k(X), cos th_k(X)) in the section frame (see
``model.R_BASE``), with rho_k = f_k r(X) (f_k its offset as a fraction of the cone's local radius
r) and th_k turning linearly from its start angle at the base to its end angle at its end. A cast
arm's tendons sit a few hundredths of a radius and a few degrees away from the drawing's; the
routing parameters (f, th_start, th_end) per tendon are what the dynamic shape estimate
(:mod:`soft_arm_control.dynamic_estimation`) carries as states, and this module gives the arrays of
a routing and the derivatives of the tendon matrices A, A0 and lengths L_c with respect to it.

The derivatives are forward differences of the tendon kernel (local: no kinematics), one tendon at
a time (a tendon's routing moves only its own column), at a step of :data:`ROUTING_STEP` (1e-7 of
a radius or a radian: the differences agree with central ones of the whole model to 1e-6
relative, ``test/model/test_routing.py``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from . import kernels

ROUTING_STEP = 1e-7


def routing_of(config) -> np.ndarray:
    """(3, n_tendons): the offset fractions, start angles and end angles [rad] of ``config``'s
    tendons."""
    return np.array([[t.offset_fraction for t in config.tendons], [t.start_angle for t in config.tendons],
                     [t.end_angle for t in config.tendons]], dtype=float)


def tendon_ends(config) -> np.ndarray:
    """(n_tendons,) [m]: where each tendon of ``config`` ends along the arm."""
    return np.array([t.end for t in config.tendons], dtype=float)


@njit(cache=True, nogil=True)
def routing_arrays(X, active, base_radius, taper, routing, ends, d, dp, dpp):
    """The offsets d (n_t, P, 3) [m] and their first two X-derivatives dp, dpp of the routing
    (3, n_t) (:func:`routing_of`'s layout), where ``active`` (n_t, P) is 1, zero elsewhere;
    ``taper`` = dr/dX of the cone's radius."""
    for k in range(routing.shape[1]):
        _tendon_routing(X, active[k], base_radius, taper, routing[0, k], routing[1, k], routing[2, k],
                        ends[k], d[k], dp[k], dpp[k])


@njit(cache=True, nogil=True)
def _tendon_routing(X, active, base_radius, taper, fraction, start, end_angle, end, d, dp, dpp):
    th_p = (end_angle - start) / end
    rho_p = fraction * taper
    for pt in range(X.shape[0]):
        if active[pt] == 0.0:
            for r in range(3):
                d[pt, r] = 0.0
                dp[pt, r] = 0.0
                dpp[pt, r] = 0.0
            continue
        x = X[pt]
        rho = fraction * (base_radius + taper * x)
        th = start + th_p * x
        s, c = np.sin(th), np.cos(th)
        d[pt, 0] = 0.0
        d[pt, 1] = rho * s
        d[pt, 2] = rho * c
        dp[pt, 0] = 0.0
        dp[pt, 1] = rho_p * s + rho * th_p * c
        dp[pt, 2] = rho_p * c - rho * th_p * s
        dpp[pt, 0] = 0.0
        dpp[pt, 1] = 2.0 * rho_p * th_p * c - rho * th_p * th_p * s
        dpp[pt, 2] = -2.0 * rho_p * th_p * s - rho * th_p * th_p * c


def new_routing_work(model) -> tuple:
    """Scratch of :func:`routing_derivatives` for ``model``: one tendon's arrays, and the tendon
    kernel's own scratch."""
    P, n = model.X.size, model.n
    return (np.zeros((1, P, 3)), np.zeros((1, P, 3)), np.zeros((1, P, 3)), np.zeros((1, P)), np.zeros(1),
            np.zeros((n, 1)), np.zeros((n, 1)), np.zeros(1), np.zeros(1), np.zeros((1, P)),
            np.zeros((1, P)), kernels.new_force_work(P, n))


@njit(cache=True, nogil=True)
def _one_tendon(w, B, Bd, xi, q, d, dp, dpp, active, mu, Q, smoothing, col_lo, col_hi, work):
    """Tendon terms of the one tendon in work's arrays (d, dp, dpp given) at strains xi: A, A0 and
    L_c land in work[5], work[6], work[7]; False at a degenerate tendon tangent."""
    kernels.strain_rows(w, B, col_lo, col_hi, work[11][3])
    return kernels._tendons(w, B, Bd, xi, q, d, dp, dpp, active, mu, Q, smoothing, col_lo, col_hi,
                            work[5], work[6], work[7], work[8], work[9], work[10], work[11])


@njit(cache=True, nogil=True)
def routing_derivatives(w, B, Bd, Q, smoothing, col_lo, col_hi, X, active, base_radius, taper, ends, mu,
                        routing, xi, q, xi_rest, q_rest, with_rest, L0, dA, dA0, dLc, dL0, work) -> bool:
    """The derivatives of tendon k's columns A_k, A0_k (n,) and lengths L_c,k at strains ``xi`` (of
    q) and at the straight arm's ``xi_rest`` (of ``q_rest``, zeros) with respect to its routing
    parameter j (:func:`routing_of`'s rows: offset fraction, start and end angles [rad]), at
    ``routing``: dA[j, :, k], dA0[j, :, k], dLc[j, k], and with ``with_rest`` dL0[j, k] and the
    straight arm's lengths L0[k] [m] at ``routing`` (left as they are without). Forward differences
    at :data:`ROUTING_STEP`; False at a degenerate tendon tangent."""
    d, dp, dpp, act, mu_k = work[0], work[1], work[2], work[3], work[4]
    n = dA.shape[1]
    base_A = np.empty(n)
    base_A0 = np.empty(n)
    for k in range(routing.shape[1]):
        for pt in range(X.shape[0]):
            act[0, pt] = active[k, pt]
        mu_k[0] = mu[k]
        for j in range(4):                       # j = 0: the routing itself; then each parameter
            f, s, e = routing[0, k], routing[1, k], routing[2, k]
            if j == 1:
                f += ROUTING_STEP
            elif j == 2:
                s += ROUTING_STEP
            elif j == 3:
                e += ROUTING_STEP
            _tendon_routing(X, act[0], base_radius, taper, f, s, e, ends[k], d[0], dp[0], dpp[0])
            rest = 0.0
            if with_rest:
                if not _one_tendon(w, B, Bd, xi_rest, q_rest, d, dp, dpp, act, mu_k, Q, smoothing, col_lo,
                                   col_hi, work):
                    return False
                rest = work[7][0]
            if not _one_tendon(w, B, Bd, xi, q, d, dp, dpp, act, mu_k, Q, smoothing, col_lo, col_hi,
                               work):
                return False
            if j == 0:
                base_rest, base_L = rest, work[7][0]
                if with_rest:
                    L0[k] = rest
                for a in range(n):
                    base_A[a] = work[5][a, 0]
                    base_A0[a] = work[6][a, 0]
                continue
            for a in range(n):
                dA[j - 1, a, k] = (work[5][a, 0] - base_A[a]) / ROUTING_STEP
                dA0[j - 1, a, k] = (work[6][a, 0] - base_A0[a]) / ROUTING_STEP
            dLc[j - 1, k] = (work[7][0] - base_L) / ROUTING_STEP
            if with_rest:
                dL0[j - 1, k] = (rest - base_rest) / ROUTING_STEP
    return True
