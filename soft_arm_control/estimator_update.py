"""The shape estimator's updates in compiled calls (numba).

:class:`~soft_arm_control.shape_estimation.ShapeEstimator` calls :func:`tendon_update` once per
sample: the iterated EKF on the tendons' shortenings and the static balance, over the state
z = (q, stiffness scale k, friction offsets dmu) of size N = n + 1 + n_tendons, then the Joseph
form of the covariance; and :func:`marker_update` with the markers it took. Written out rather
than composed of numpy calls: the update runs at 250 Hz beside the loop, and the calls' overhead
and their temporary arrays cost more than their arithmetic at these sizes; nothing here
allocates. The innovation covariance is factored by Cholesky (it is symmetric positive definite:
the noise is), which also makes its rounding the same whatever kernels the machine's BLAS picks.
The measurement model (units and frames) is the estimator module's.
"""
from __future__ import annotations

import numpy as np

from soft_arm_model.lie import nonallocating_strict
from soft_arm_model.statics import residual_jacobian_kernel

# tendon_update's status
UPDATED, OUT_OF_DOMAIN, NOT_POSITIVE = 0, 1, 2
# the iterated update stops once a Gauss-Newton step moves no state by more than this part of its
# prior standard deviation: relinearising about a point that near changes the estimate by a part of
# that step (at rest, with a measurement much like the last, the first step is already that small)
CONVERGED = 1e-3


def new_work(n: int, n_tendons: int, n_markers: int) -> tuple:
    """The arrays the updates and the markers' moments and innovations work in, for a model with n
    coordinates, n_tendons and n_markers."""
    N, rows = n + 1 + n_tendons, max(n + n_tendons, 3 * n_markers)
    return (np.zeros(n), np.zeros(n), np.zeros((n, n)), np.zeros((n, n_tendons)),   # q, r, jac, dA
            np.zeros(rows), np.zeros((rows, N)), np.zeros((rows, rows)), np.zeros((rows, rows)),
            np.zeros(rows), np.zeros((N, N)), np.zeros((N, N)))   # y, HP, S, L, w, I - KH, (I - KH) P


@nonallocating_strict
def _cholesky(S, L, m) -> bool:
    """L L^T = S over the leading m x m block (L lower); False unless it is positive definite."""
    for j in range(m):
        acc = S[j, j]
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        if not acc > 0.0:
            return False
        d = np.sqrt(acc)
        L[j, j] = d
        for i in range(j + 1, m):
            acc = S[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / d
    return True


@nonallocating_strict
def _forward(L, b, x, m):
    """x[:m] = L[:m, :m]^-1 b[:m] (forward substitution)."""
    for i in range(m):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]


@nonallocating_strict
def _backward(L, b, x, m):
    """x[:m] = L[:m, :m]^-T b[:m] (back substitution)."""
    for i in range(m - 1, -1, -1):
        acc = b[i]
        for k in range(i + 1, m):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]


@nonallocating_strict
def _factor(H, P, noise, rows, HP, S, L) -> bool:
    """HP = H P and the Cholesky factor L of S = H P H^T + diag(noise) over the first ``rows``
    rows of H; False unless S is positive definite."""
    N = P.shape[0]
    for i in range(rows):                                    # HP = H P (P symmetric)
        for j in range(N):
            acc = 0.0
            for k in range(N):
                acc += H[i, k] * P[j, k]
            HP[i, j] = acc
    for i in range(rows):                                    # S = HP H^T + diag(noise)
        for j in range(i + 1):
            acc = 0.0
            for k in range(N):
                acc += HP[i, k] * H[j, k]
            S[i, j] = acc
            S[j, i] = acc
        S[i, i] += noise[i]
    return _cholesky(S, L, rows)


@nonallocating_strict
def _step(HP, L, innovation, rows, free, z_prior, z, x, w) -> float:
    """z = z_prior + K innovation with K = P H^T S^-1 (its rows from ``free`` on zero), as
    z_prior + HP^T S^-1 innovation without forming K; returns the innovation's normalised square
    (``w``: L^-1 innovation, ``x``: S^-1 innovation)."""
    _forward(L, innovation, w, rows)
    _backward(L, w, x, rows)
    for a in range(z.shape[0]):
        acc = z_prior[a]
        if a < free:
            for i in range(rows):
                acc += HP[i, a] * x[i]
        z[a] = acc
    nis = 0.0
    for i in range(rows):
        nis += w[i] * w[i]
    return nis


@nonallocating_strict
def _gain(HP, L, rows, free, K, y, w):
    """The Kalman gain K (N, rows) = P H^T S^-1 from :func:`_factor`'s HP and L; its rows from
    ``free`` on are zero (states the measurement does not move)."""
    N = HP.shape[1]
    for j in range(N):                                       # K^T = S^-1 HP, column by column
        if j >= free:
            for i in range(rows):
                K[j, i] = 0.0
            continue
        for i in range(rows):
            y[i] = HP[i, j]
        _forward(L, y, w, rows)
        _backward(L, w, y, rows)
        for i in range(rows):
            K[j, i] = y[i]


@nonallocating_strict
def _joseph(P, K, H, noise, rows, IKH, tmp):
    """P <- (I - KH) P (I - KH)^T + K diag(noise) K^T over the first ``rows`` measurements,
    symmetric to the last bit (Joseph form: positive whatever the gain)."""
    N = P.shape[0]
    for i in range(N):
        for j in range(N):
            acc = 1.0 if i == j else 0.0
            for k in range(rows):
                acc -= K[i, k] * H[k, j]
            IKH[i, j] = acc
    for i in range(N):
        for j in range(N):
            acc = 0.0
            for k in range(N):
                acc += IKH[i, k] * P[j, k]
            tmp[i, j] = acc
    for i in range(N):                       # P's old values are in tmp now; its lower triangle,
        for j in range(i + 1):               # mirrored
            acc = 0.0
            for k in range(N):
                acc += tmp[i, k] * IKH[j, k]
            for k in range(rows):
                acc += K[i, k] * noise[k] * K[j, k]
            P[i, j] = acc
            P[j, i] = acc


@nonallocating_strict
def _converged(z, last, P) -> bool:
    """No state moved from ``last`` to ``z`` by more than :data:`CONVERGED` of its standard deviation
    in ``P``."""
    for a in range(z.shape[0]):
        step = z[a] - last[a]
        if step * step > CONVERGED * CONVERGED * P[a, a]:
            return False
    return True


@nonallocating_strict
def tendon_update(model_args, data_args, Fg, Fel, A, A0, Kt, Lc, rest_lengths, s, u, z_prior, P,
                  iterations, balance, balance_floor, inflation, shortening_var, moving,
                  z, K, H, noise, innovation, work):
    """The iterated tendon update from ``z_prior`` with covariance ``P`` (N, N), in place.

    Measurements: the shortenings ``s`` [m] (h = L_c(0) - L_c(q), noise variance ``shortening_var``
    [m^2]) and the static balance's residual R = R(q; k = 1, mu) + (k - 1) F_el + dA/dmu diag(u) dmu
    at the tensions ``u`` [N] (pseudo-measurement 0; standard deviation ``balance`` times
    ``|F_el| + |A u|`` per coordinate plus ``balance_floor``, times ``inflation``); at most
    ``iterations`` Gauss-Newton steps about the prior, fewer once one is below :data:`CONVERGED`.
    With ``moving`` the gain's rows of k and dmu are zero.

    Leaves in ``z`` the updated state, in ``K`` (N, rows) the last gain, in ``H`` (rows, N) the last
    measurement Jacobian (rows: the n_tendons shortenings, then the n balance coordinates), in
    ``noise`` and ``innovation`` their variances and the last innovation, in ``P`` the Joseph-form
    covariance, and the workspace (``data_args``) at the last linearisation's q. Returns (status,
    the innovation's normalised square, the shortenings' alone); on a status other than
    :data:`UPDATED` z and P are not to be used.
    """
    q, r, jac, dA, y, HP, S, L, w, IKH, tmp = work
    N = z_prior.shape[0]
    n = q.shape[0]
    m = s.shape[0]
    rows = n + m
    nis = 0.0
    for a in range(N):
        z[a] = z_prior[a]
    for _it in range(iterations):
        for a in range(n):
            q[a] = z[a]
        if not residual_jacobian_kernel(model_args, data_args, Fg, Fel, A, q, u, True, r, jac, dA):
            return OUT_OF_DOMAIN, 0.0, 0.0
        k1 = z[n] - 1.0
        for i in range(m):                                   # the shortenings: -A0^T, zero on k, dmu
            for j in range(n):
                H[i, j] = -A0[j, i]
            for j in range(n, N):
                H[i, j] = 0.0
            y[i] = s[i] - (rest_lengths[i] - Lc[i])
            noise[i] = shortening_var
        for a in range(n):                                   # the balance
            row = m + a
            for j in range(n):
                H[row, j] = jac[a, j] + k1 * Kt[a, j]
            H[row, n] = Fel[a]
            res = r[a] + k1 * Fel[a]
            actuation = 0.0
            for t in range(m):
                force = dA[a, t] * u[t]
                H[row, n + 1 + t] = force
                res += force * z[n + 1 + t]
                actuation += A[a, t] * u[t]
            y[row] = -res
            sigma = (balance * (abs(Fel[a]) + abs(actuation)) + balance_floor) * inflation
            noise[row] = sigma * sigma
        for i in range(rows):                                # about the prior: y - H (z_prior - z)
            acc = y[i]
            for j in range(N):
                acc -= H[i, j] * (z_prior[j] - z[j])
            innovation[i] = acc
        if not _factor(H, P, noise, rows, HP, S, L):
            return NOT_POSITIVE, 0.0, 0.0
        last = tmp[0]                   # the iterate before this step (tmp is free until the Joseph form)
        for a in range(N):
            last[a] = z[a]
        nis = _step(HP, L, innovation, rows, n if moving else N, z_prior, z, y, w)  # the parameters
        if _converged(z, last, P):
            break
    _gain(HP, L, rows, n if moving else N, K, y, w)                                 # learn at rest only
    _forward(L, innovation, w, m)                            # S's leading block: L's leading block
    shortening_nis = 0.0
    for i in range(m):
        shortening_nis += w[i] * w[i]
    _joseph(P, K, H, noise, rows, IKH, tmp)
    return UPDATED, nis, shortening_nis


@nonallocating_strict
def marker_moments(marker_R, marker_J, P, H, C, work):
    """Each marker's position Jacobian and covariance at the evaluated workspace: H[k] (3, n) =
    R_k J_k[3:6], d(marker k in arm_base)/dq [m], and C[k] (3, 3) = H_k P H_k^T [m^2] with P the
    leading (n, n) block of ``P`` (the configuration's)."""
    HP = work[5]
    n = H.shape[2]
    for k in range(H.shape[0]):
        for i in range(3):
            for j in range(n):
                acc = 0.0
                for a in range(3):
                    acc += marker_R[k, i, a] * marker_J[k, 3 + a, j]
                H[k, i, j] = acc
        for i in range(3):                                   # HP = H_k P (P symmetric)
            for j in range(n):
                acc = 0.0
                for m in range(n):
                    acc += H[k, i, m] * P[j, m]
                HP[i, j] = acc
        for i in range(3):
            for j in range(i + 1):
                acc = 0.0
                for m in range(n):
                    acc += HP[i, m] * H[k, j, m]
                C[k, i, j] = acc
                C[k, j, i] = acc


@nonallocating_strict
def marker_innovations(C, markers, predicted, noise_var, innovation, nis, work):
    """Each seen marker's innovation (measured - predicted) [m] and its normalised square
    nu^T (C_k + noise_var I)^-1 nu, by a 3 x 3 Cholesky factor; NaN for a marker not seen (a row of
    ``markers`` with a NaN) or whose innovation covariance is not positive definite."""
    S, L, w = work[6], work[7], work[8]
    for k in range(markers.shape[0]):
        seen = True
        for i in range(3):
            innovation[k, i] = markers[k, i] - predicted[k, i]
            if not np.isfinite(markers[k, i]):
                seen = False
        nis[k] = np.nan
        if not seen:
            continue
        for i in range(3):
            for j in range(3):
                S[i, j] = C[k, i, j]
            S[i, i] += noise_var
        if not _cholesky(S, L, 3):
            continue
        _forward(L, innovation[k], w, 3)
        nis[k] = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]


@nonallocating_strict
def marker_update(H, innovation, rows, noise_var, n, z, P, K, noise, work) -> bool:
    """The update with the markers taken: the first ``rows`` rows of ``H`` (rows, N) (their
    Jacobians d(marker position)/dq, zero on the parameters) and of ``innovation`` [m], each of
    noise variance ``noise_var`` [m^2]; moves q only (the gain's rows from ``n`` on are zero). z
    and P in place; False (nothing changed) unless the innovation covariance is positive definite."""
    _, _, _, _, y, HP, S, L, w, IKH, tmp = work
    for i in range(rows):
        noise[i] = noise_var
    if not _factor(H, P, noise, rows, HP, S, L):
        return False
    _step(HP, L, innovation, rows, n, z, z, y, w)
    _gain(HP, L, rows, n, K, y, w)
    _joseph(P, K, H, noise, rows, IKH, tmp)
    return True
