"""The dynamic shape estimator's prediction and update in compiled calls (numba).

:class:`~soft_arm_control.dynamic_estimation.DynamicShapeEstimator` evaluates the model's terms
(the workspace, the static tangent, the routing's derivatives: compiled kernels of their own) and
hands them here. :func:`predict_step` is the implicit step of the state, the step's Jacobian F and
the covariance F P F^T + G W G^T; :func:`tendon_rows` the tendons' measurement rows and their
normalised innovation; :func:`gain_update` the gain, the state's update and the Joseph form, for
any stack of rows (the tendons', and the markers' the estimator has gated). The expressions, units
and frames are the estimator module's. One call each: the same expressions in numpy are some
sixty calls a sample, whose overhead costs more than their arithmetic at these sizes
(N = 2n + 2 + 4 n_tendons: 58 at 20 coordinates). The gain is the static filter's
(:mod:`~soft_arm_control.estimator_update`: the innovation covariance's Cholesky factor, the gain
from it, its rows past the states a measurement may move zero); the products of N x N matrices go
to the BLAS (``np.dot``); the rest is written out. F is the identity but for its first 2n rows, and
the products use only those.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .estimator_update import _factor, _gain


def noise_parameters(config) -> np.ndarray:
    """(force, force_floor, tension, parameter_drift) of an
    :class:`~soft_arm_control.shape_estimation.EstimatorConfig`, as :func:`predict_step` takes them."""
    return np.array([config.force, config.force_floor, config.tension, config.parameter_drift])


@njit(cache=True, nogil=True)
def predict_step(M, D, Kt, A_model, A0, dA_dmu, jac, dA, dA0, Fg, Cqd, Fel, J_tip, R_tip, gravity,
                 rotor, adot, u, h, noise, parts, z, P, share, F):
    """One step of length ``h`` [s] under the tensions ``u`` [N] from the state ``z`` = (q, qd, k,
    dmu, routing, payload) with covariance ``P``; returns the new covariance (a new array) and
    updates ``z`` and the payload's ``share`` in place; F (N, N) receives the step's Jacobian.

    The model's terms at (q, qd): M, D, Kt, A_model (the tendons' A at the model's friction), A0,
    Fg, Cqd, Fel; ``dA_dmu`` (n, n_t) and ``jac`` (n, n), the static tangent's dA/dmu and dR/dq;
    ``dA``, ``dA0`` (3, n, n_t), the routing's derivatives; ``J_tip`` (6, n) and ``R_tip`` (3, 3),
    the tip marker's Jacobian and rotation, ``gravity`` (3,) in arm_base [m/s^2]; ``rotor`` (n_t,)
    the reflected masses [kg], ``adot`` (n_t,) Adot0^T qd; ``noise``: :func:`noise_parameters`;
    ``parts``: where the stiffness, friction, routing and payload start in z."""
    n, nt = A0.shape
    N = z.shape[0]
    k_at, mu_at, beta_at, load_at = parts[0], parts[1], parts[2], parts[3]
    force_rel, force_floor, tension, drift = noise[0], noise[1], noise[2], noise[3]
    k = z[k_at]
    payload = z[load_at]
    q = z[:n].copy()
    v = z[n:2 * n].copy()
    A = np.empty((n, nt))                    # A at the estimated friction
    for a in range(n):
        for j in range(nt):
            A[a, j] = A_model[a, j] + dA_dmu[a, j] * z[mu_at + j]
    g_body = np.zeros(3)                     # gravity in the tip's frame
    for i in range(3):
        for r in range(3):
            g_body[i] += R_tip[r, i] * gravity[r]
    weight = np.zeros(n)                     # the generalised weight of a unit mass at the tip
    for a in range(n):
        for i in range(3):
            weight[a] += J_tip[3 + i, a] * g_body[i]
    s_rate = np.zeros(nt)                    # A0^T qd
    for j in range(nt):
        for a in range(n):
            s_rate[j] += A0[a, j] * v[a]
    S = np.empty((n, n))
    rhs = np.empty(n)
    for a in range(n):
        Mv = 0.0
        for b in range(n):
            coupling = 0.0
            for j in range(nt):
                coupling += A[a, j] * rotor[j] * A0[b, j]
            S[a, b] = M[a, b] + h * D[a, b] + (h * h * k) * Kt[a, b] + coupling
            Mv += M[a, b] * v[b]
        rotor_force = 0.0
        tendon_force = 0.0
        for j in range(nt):
            rotor_force += A[a, j] * (rotor[j] * s_rate[j])
            tendon_force += A[a, j] * (u[j] + rotor[j] * adot[j])
        rhs[a] = Mv + rotor_force + h * (Fg[a] - Cqd[a] - k * Fel[a] - tendon_force + payload * weight[a])
    Sinv = np.linalg.inv(S)
    v_new = np.dot(Sinv, rhs)
    force = np.empty(nt)                     # the impulse per tendon over the step
    for j in range(nt):
        change = 0.0
        for a in range(n):
            change += A0[a, j] * (v_new[a] - v[a])
        force[j] = h * (u[j] + rotor[j] * adot[j]) + rotor[j] * change
    Kt_v = np.dot(Kt, v_new)
    # the rate's Jacobian, column by column: Sinv times what each state moves in the step's balance
    B = np.empty((n, N))
    for a in range(n):
        for b in range(n):
            B[a, b] = -h * (jac[a, b] + (k - 1.0) * Kt[a, b])
            B[a, n + b] = -h * (D[a, b] + (h * k) * Kt[a, b])
        B[a, k_at] = -h * (Fel[a] + h * Kt_v[a])
        for j in range(nt):
            B[a, mu_at + j] = -dA_dmu[a, j] * force[j]
        B[a, load_at] = h * weight[a]
    for r in range(3):                       # the routing moves A (the forces) and A0 (the rotors)
        for j in range(nt):
            rotor_rate = 0.0
            for a in range(n):
                rotor_rate += dA0[r, a, j] * (v_new[a] - v[a])
            rotor_rate *= rotor[j]
            for a in range(n):
                B[a, beta_at + r * nt + j] = -(dA[r, a, j] * force[j] + A[a, j] * rotor_rate)
    Fv = np.dot(Sinv, B)
    for a in range(n):
        Fv[a, n + a] += 1.0
    for i in range(N):
        for j in range(N):
            F[i, j] = 1.0 if i == j else 0.0
    for a in range(n):
        for j in range(N):
            F[n + a, j] = Fv[a, j]
            F[a, j] += h * Fv[a, j]
    # what the model does not explain: an impulse per coordinate and the tensions' noise through A
    scaled = np.empty((n, n))                # Sinv diag((h sigma_f)^2)
    Au = np.dot(A, u)
    Dv = np.dot(D, v)
    for b in range(n):
        sigma = h * (force_rel * (abs(k * Fel[b]) + abs(Au[b]) + abs(Dv[b])) + force_floor)
        for a in range(n):
            scaled[a, b] = Sinv[a, b] * sigma * sigma
    SA = np.dot(Sinv, A)
    SWS = np.dot(scaled, Sinv.T) + (h * h * tension * tension) * np.dot(SA, SA.T)
    # F P F^T, F's rows past 2n being the identity's
    m = 2 * n
    Fa = np.ascontiguousarray(F[:m])
    T = np.dot(Fa, P)
    top = np.dot(T, Fa.T)
    out = P.copy()
    for i in range(m):
        for j in range(m):
            out[i, j] = top[i, j]
        for j in range(m, N):
            out[i, j] = T[i, j]
            out[j, i] = T[i, j]
    for a in range(n):
        for b in range(n):
            out[a, b] += h * h * SWS[a, b]
            out[a, n + b] += h * SWS[a, b]
            out[n + a, b] += h * SWS[a, b]
            out[n + a, n + b] += SWS[a, b]
    for i in range(k_at, beta_at):           # the stiffness and friction drift; a cast arm's
        out[i, i] += drift * drift * h       # routing and its payload stay
    moved = np.dot(Fa, share)
    for i in range(m):
        share[i] = moved[i]
    for a in range(n):
        z[a] = q[a] + h * v_new[a]
        z[n + a] = v_new[a]
    return out


@njit(cache=True, nogil=True)
def tendon_rows(A0, v, dL0, dLc, dA0, L0, Lc, s, sd, noise, beta_at, P, H, y, r) -> float:
    """The shortenings' and their rates' rows (2 n_t of them) into H (2 n_t, N), their innovations
    into y and their noise variances into r, at the state (q, ``v``) whose A0 and tendon lengths
    ``Lc`` these are (``L0``: the straight arm's; ``dL0``, ``dLc``, ``dA0``: the routing's
    derivatives); ``noise``: (shortening [m], encoder rate [m/s]) standard deviations. Returns the
    shortenings' normalised innovation squared under ``P``."""
    n, nt = A0.shape
    N = P.shape[0]
    for i in range(2 * nt):
        for j in range(N):
            H[i, j] = 0.0
    for t in range(nt):
        rate = 0.0
        for a in range(n):
            H[t, a] = -A0[a, t]
            H[nt + t, n + a] = -A0[a, t]
            rate += A0[a, t] * v[a]
        for r_ in range(3):
            H[t, beta_at + r_ * nt + t] = dL0[r_, t] - dLc[r_, t]
            moved = 0.0
            for a in range(n):
                moved += v[a] * dA0[r_, a, t]
            H[nt + t, beta_at + r_ * nt + t] = -moved
        y[t] = s[t] - (L0[t] - Lc[t])
        y[nt + t] = sd[t] + rate
        r[t] = noise[0] * noise[0]
        r[nt + t] = noise[1] * noise[1]
    Hs = np.ascontiguousarray(H[:nt])
    Sy = np.dot(np.dot(Hs, P), Hs.T)
    for t in range(nt):
        Sy[t, t] += r[t]
    return float(np.dot(y[:nt], np.linalg.solve(Sy, y[:nt])))


@njit(cache=True, nogil=True)
def gain_update(H, y, r, z, P, share, payload_var, blind, unsettled, k_at, beta_at):
    """The update with the rows H (m, N), innovations y and noise variances r: ``z`` and the
    payload's ``share`` in place; returns (True, the new covariance), or (False, P) and nothing
    changed where the innovation covariance is not positive definite. ``blind`` (no marker among
    the rows): the gain is the covariance's without the payload's share (``payload_var`` times its
    outer product) and leaves the routing and payload alone, and ``unsettled`` (in motion, or at a
    rest shorter than the model's settling time) the stiffness and friction too (the estimator
    module's docstring); the covariance is the Joseph form's for that gain."""
    m, N = H.shape
    gain_P = P
    free = N                                 # the gain's rows from here on are zero
    if blind:
        gain_P = P - payload_var * np.outer(share, share)
        free = k_at if unsettled else beta_at
    HP, S, L = np.empty((m, N)), np.empty((m, m)), np.zeros((m, m))
    if not _factor(H, gain_P, r, m, HP, S, L):      # S = H P H^T + diag(r) is not positive definite
        return False, P
    K = np.empty((N, m))
    _gain(HP, L, m, free, K, np.empty(m), np.empty(m))
    Ky = np.dot(K, y)
    for i in range(N):
        z[i] += Ky[i]
    IKH = -np.dot(K, H)
    for i in range(N):
        IKH[i, i] += 1.0
    Kr = K * r.reshape(1, m)
    out = np.dot(np.dot(IKH, P), IKH.T) + np.dot(Kr, K.T)
    moved = np.dot(IKH, share)
    for i in range(N):
        share[i] = moved[i]
    return True, 0.5 * (out + out.T)
