"""SE(3) helpers for the Variable-Strain kernels (numba, scalar loops, no allocation in loops).

Twists are ordered angular first, ``[omega; v]``, as in SoRoSim. All functions write into
caller-provided arrays so that the kernels in :mod:`soft_arm_model.kernels` stay allocation-light.

Conventions:

- ``ad(x) = [[w~, 0], [v~, w~]]`` for ``x = [w; v]``.
- ``Ad_g = [[R, 0], [p~ R, R]]`` for ``g = (R, p)``.
- ``T(Omega) = sum_k ad(Omega)^k / (k+1)!`` is the tangent operator of the exponential, so that the
  body twist after one Magnus step is ``Ad_{exp(-Omega)} (eta + T(Omega) dOmega/dt)``.
"""
import numpy as np
from numba import njit

# The decorator of every kernel that allocates nothing and keeps no reference to its arrays (the
# functions here, and most of :mod:`soft_arm_model.kernels`): compiled without numba's reference
# counting, the views they take of their arguments and pass on cost nothing, where each view's
# atomic increment and decrement took a fifth of an evaluation of the model
# (``bench/bench_model.py``). Its arrays live in the caller, which holds them for the call.
nonallocating = njit(cache=True, nogil=True, fastmath=True, error_model="numpy", _nrt=False)
# The same with strict IEEE arithmetic: the solvers and the time steppers that call the kernels
# (the statics' Newton step and LU, the IMEX and ROS2 steps, the estimator's update), whose results
# must not owe their rounding to the processor's vector width. Without reference counting, the
# tuples of workspace arrays they unpack into each evaluation cost nothing: counted, they took a
# third of a compiled IMEX step.
nonallocating_strict = njit(cache=True, nogil=True, _nrt=False)
# The kernels that allocate (their results, or the mass matrix's product through the BLAS) say that
# they count references, explicitly: a kernel that leaves it unsaid inherits its first caller's
# setting in numba, so that one compiled first under a nonallocating caller would fail to compile.
allocating = njit(cache=True, nogil=True, fastmath=True, error_model="numpy", _nrt=True)

# Below these angles the closed forms lose digits to cancellation; even power series are used instead.
_EXP_SERIES_BELOW = 0.1
_TANGENT_SERIES_BELOW = 0.5

# Even-power Taylor coefficients (theta^0, theta^2, ...) of the tangent-operator weights f1..f4 and of
# g_i = f_i'(theta) / theta (derived symbolically from the series of the SE(3) exponential).
_F_SERIES = np.array([
    [1 / 2, 0.0, -1 / 720, 1 / 20160, -1 / 1209600, 1 / 119750400],
    [1 / 6, 0.0, -1 / 5040, 1 / 181440, -1 / 13305600, 1 / 1556755200],
    [1 / 24, -1 / 360, 1 / 13440, -1 / 907200, 1 / 95800320, -1 / 14529715200],
    [1 / 120, -1 / 2520, 1 / 120960, -1 / 9979200, 1 / 1245404160, -1 / 217945728000],
])
_G_SERIES = np.array([
    [0.0, -1 / 180, 1 / 3360, -1 / 151200, 1 / 11975040],
    [0.0, -1 / 1260, 1 / 30240, -1 / 1663200, 1 / 155675520],
    [-1 / 180, 1 / 3360, -1 / 151200, 1 / 11975040, -1 / 1452971520],
    [-1 / 1260, 1 / 30240, -1 / 1663200, 1 / 155675520, -1 / 21794572800],
])


@nonallocating
def _even_series(coeffs, theta2):
    acc = 0.0
    for k in range(coeffs.shape[0] - 1, -1, -1):
        acc = acc * theta2 + coeffs[k]
    return acc


@nonallocating
def ad_matrix(x, out):
    """Write the 6x6 adjoint ``ad(x)`` of twist ``x = [w; v]`` into ``out``."""
    out[:, :] = 0.0
    w0, w1, w2, v0, v1, v2 = x[0], x[1], x[2], x[3], x[4], x[5]
    for blk in range(2):
        o = 3 * blk
        out[o + 0, o + 1] = -w2
        out[o + 0, o + 2] = w1
        out[o + 1, o + 0] = w2
        out[o + 1, o + 2] = -w0
        out[o + 2, o + 0] = -w1
        out[o + 2, o + 1] = w0
    out[3, 1] = -v2
    out[3, 2] = v1
    out[4, 0] = v2
    out[4, 2] = -v0
    out[5, 0] = -v1
    out[5, 1] = v0


@nonallocating
def ad_apply(x, y, out):
    """``out = ad(x) y`` for twists x, y (out must not alias x or y)."""
    w0, w1, w2, v0, v1, v2 = x[0], x[1], x[2], x[3], x[4], x[5]
    out[0] = w1 * y[2] - w2 * y[1]
    out[1] = w2 * y[0] - w0 * y[2]
    out[2] = w0 * y[1] - w1 * y[0]
    out[3] = w1 * y[5] - w2 * y[4] + v1 * y[2] - v2 * y[1]
    out[4] = w2 * y[3] - w0 * y[5] + v2 * y[0] - v0 * y[2]
    out[5] = w0 * y[4] - w1 * y[3] + v0 * y[1] - v1 * y[0]


@nonallocating
def ad_apply_columns(x, Y, out, scale, accumulate, lo, hi):
    """``out (+)= scale * ad(x) Y`` on the columns [lo, hi) of a 6 x n matrix ``Y`` (row-wise loops,
    out must not alias Y); out's other columns are left as they are."""
    w0, w1, w2 = scale * x[0], scale * x[1], scale * x[2]
    v0, v1, v2 = scale * x[3], scale * x[4], scale * x[5]
    ulo, uhi = np.uint64(lo), np.uint64(hi)   # unsigned: no negative-index wraparound, so it vectorises
    if not accumulate:
        for r in range(6):
            for j in range(ulo, uhi):
                out[r, j] = 0.0
    for j in range(ulo, uhi):
        out[0, j] += w1 * Y[2, j] - w2 * Y[1, j]
    for j in range(ulo, uhi):
        out[1, j] += w2 * Y[0, j] - w0 * Y[2, j]
    for j in range(ulo, uhi):
        out[2, j] += w0 * Y[1, j] - w1 * Y[0, j]
    for j in range(ulo, uhi):
        out[3, j] += w1 * Y[5, j] - w2 * Y[4, j] + v1 * Y[2, j] - v2 * Y[1, j]
    for j in range(ulo, uhi):
        out[4, j] += w2 * Y[3, j] - w0 * Y[5, j] + v2 * Y[0, j] - v0 * Y[2, j]
    for j in range(ulo, uhi):
        out[5, j] += w0 * Y[4, j] - w1 * Y[3, j] + v0 * Y[1, j] - v1 * Y[0, j]


@nonallocating
def matmul_into(A, B, out):
    """``out = A @ B`` for small dense matrices (plain loops; out must not alias A or B)."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            acc = 0.0
            for k in range(A.shape[1]):
                acc += A[i, k] * B[k, j]
            out[i, j] = acc


@nonallocating
def expmap(omega, R, p):
    """Closed-form SE(3) exponential of the twist ``omega``: rotation ``R`` and translation ``p``."""
    wx, wy, wz = omega[0], omega[1], omega[2]
    theta2 = wx * wx + wy * wy + wz * wz
    if theta2 < _EXP_SERIES_BELOW * _EXP_SERIES_BELOW:
        a = 1.0 - theta2 / 6.0 * (1.0 - theta2 / 20.0 * (1.0 - theta2 / 42.0 * (1.0 - theta2 / 72.0)))
        b = 0.5 * (1.0 - theta2 / 12.0 * (
            1.0 - theta2 / 30.0 * (1.0 - theta2 / 56.0 * (1.0 - theta2 / 90.0))))
        c = (1.0 - theta2 / 20.0 * (
            1.0 - theta2 / 42.0 * (1.0 - theta2 / 72.0 * (1.0 - theta2 / 110.0)))) / 6.0
    else:
        theta = np.sqrt(theta2)
        s = np.sin(theta)
        co = np.cos(theta)
        a = s / theta
        b = (1.0 - co) / theta2
        c = (theta - s) / (theta2 * theta)
    # K = w~, K2 = w~ w~ = w w^T - theta2 I
    w = (wx, wy, wz)
    v = (omega[3], omega[4], omega[5])
    for i in range(3):
        acc = 0.0
        for j in range(3):
            # K = w~ (entries -eps_ijk w_k), K^2 = w w^T - theta2 I
            kij = 0.0
            if i != j:
                m = 3 - i - j
                kij = w[m] if (i - j) % 3 == 1 else -w[m]
            k2 = w[i] * w[j] - (theta2 if i == j else 0.0)
            eye = 1.0 if i == j else 0.0
            R[i, j] = eye + a * kij + b * k2
            acc += (eye + b * kij + c * k2) * v[j]
        p[i] = acc


@nonallocating
def tangent_weights(theta2, f, g):
    """Weights f1..f4 of ``T = I + f1 ad + f2 ad^2 + f3 ad^3 + f4 ad^4`` and g_i = f_i'/theta."""
    if theta2 < _TANGENT_SERIES_BELOW * _TANGENT_SERIES_BELOW:
        for i in range(4):
            f[i] = _even_series(_F_SERIES[i], theta2)
            g[i] = _even_series(_G_SERIES[i], theta2)
    else:
        t = np.sqrt(theta2)
        s = np.sin(t)
        c = np.cos(t)
        t3 = theta2 * t
        t4 = theta2 * theta2
        f[0] = (4.0 - 4.0 * c - t * s) / (2.0 * theta2)
        f[1] = (4.0 * t - 5.0 * s + t * c) / (2.0 * t3)
        f[2] = (2.0 - 2.0 * c - t * s) / (2.0 * t4)
        f[3] = (2.0 * t - 3.0 * s + t * c) / (2.0 * t4 * t)
        n1 = -8.0 + (8.0 - theta2) * c + 5.0 * t * s
        n2 = -8.0 * t + (15.0 - theta2) * s - 7.0 * t * c
        g[0] = n1 / (2.0 * t4)
        g[1] = n2 / (2.0 * t4 * t)
        g[2] = n1 / (2.0 * t4 * theta2)
        g[3] = n2 / (2.0 * t4 * t3)


TANGENT_SCRATCH = 11  # number of 6x6 scratch matrices the tangent functions share


@nonallocating
def tangent(omega, T, work):
    """Tangent operator ``T(omega)``. Leaves the weights f, g in work[10] for ``tangent_rate`` and
    ``tangent_rate_apply``; ``work`` has shape (TANGENT_SCRATCH, 6, 6).

    In closed form by 3 x 3 blocks rather than by powers of ad: with W = w~, V = v~, ad = [[W, 0],
    [V, W]], W^3 = -theta^2 W, and the block identities W V W = -(w.v) W, V W + W V = w v^T + v w^T
    - 2 (w.v) I, the series I + f1 ad + ... + f4 ad^4 is [[T_w, 0], [T_v, T_w]] with
    T_w = I + a W + b W^2 and T_v = a V + b (V W + W V) - 2 (w.v) (f3 W + f4 W^2), where
    a = f1 - theta^2 f3 and b = f2 - theta^2 f4.
    """
    w0, w1, w2, v0, v1, v2 = omega[0], omega[1], omega[2], omega[3], omega[4], omega[5]
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    f = work[10, 0, 0:4]
    tangent_weights(theta2, f, work[10, 1, 0:4])
    a = f[0] - theta2 * f[2]
    b = f[1] - theta2 * f[3]
    wv = w0 * v0 + w1 * v1 + w2 * v2
    w = (w0, w1, w2)
    v = (v0, v1, v2)
    for i in range(3):
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            Wij = 0.0   # (w~)_ij = -eps_ijk w_k
            Vij = 0.0
            if i != j:
                k = 3 - i - j
                sign = 1.0 if (i - j) % 3 == 1 else -1.0
                Wij = sign * w[k]
                Vij = sign * v[k]
            W2ij = w[i] * w[j] - theta2 * eye
            P1ij = w[i] * v[j] + v[i] * w[j] - 2.0 * wv * eye
            tw = eye + a * Wij + b * W2ij
            T[i, j] = tw
            T[i + 3, j + 3] = tw
            T[i, j + 3] = 0.0
            T[i + 3, j] = a * Vij + b * P1ij - 2.0 * wv * (f[2] * Wij + f[3] * W2ij)


@nonallocating
def _ad_powers(omega, work):
    """ad(omega)^1..4 into work[0:4]."""
    ad_matrix(omega, work[0])
    matmul_into(work[0], work[0], work[1])
    matmul_into(work[1], work[0], work[2])
    matmul_into(work[2], work[0], work[3])


@nonallocating
def tangent_rate(omega, omega_dot, Tdot, work):
    """Time derivative of ``T(omega)`` for ``d omega/dt = omega_dot`` (call ``tangent`` first)."""
    f = work[10, 0, 0:4]
    g = work[10, 1, 0:4]
    _ad_powers(omega, work)
    ad1, ad2, ad3, ad4 = work[0], work[1], work[2], work[3]
    theta_dtheta = omega[0] * omega_dot[0] + omega[1] * omega_dot[1] + omega[2] * omega_dot[2]
    E, d2, d3, d4, tmp, tmp2 = work[4], work[5], work[6], work[7], work[8], work[9]
    ad_matrix(omega_dot, E)
    # d(ad^k)/dt = sum_j ad^j E ad^(k-1-j)
    matmul_into(E, ad1, d2)
    matmul_into(ad1, E, tmp)
    d2 += tmp
    matmul_into(d2, ad1, d3)          # (E ad + ad E) ad
    matmul_into(ad2, E, tmp)          # + ad^2 E
    d3 += tmp
    matmul_into(d3, ad1, d4)          # (E ad^2 + ad E ad + ad^2 E) ad
    matmul_into(ad3, E, tmp2)         # + ad^3 E
    d4 += tmp2
    for i in range(6):
        for j in range(6):
            Tdot[i, j] = theta_dtheta * (g[0] * ad1[i, j] + g[1] * ad2[i, j] + g[2] * ad3[i, j]
                                         + g[3] * ad4[i, j]) \
                + f[0] * E[i, j] + f[1] * d2[i, j] + f[2] * d3[i, j] + f[3] * d4[i, j]


@nonallocating
def tangent_rate_apply(omega, omega_dot, out, work):
    """``out = (dT/dt) omega_dot`` without forming dT/dt (call ``tangent`` first).

    Uses ad(omega_dot) omega_dot = 0: with a_k = ad^k omega_dot and e_k = ad(omega_dot) a_k,
    d(ad^2) omega_dot = e_1, d(ad^3) omega_dot = e_2 + ad e_1, d(ad^4) omega_dot = e_3 + ad (e_2 + ad e_1).
    """
    f = work[10, 0, 0:4]
    g = work[10, 1, 0:4]
    v = work[4]  # rows: a1, a2, a3, a4, e1, e2
    a1, a2, a3, a4, e1, e2 = v[0], v[1], v[2], v[3], v[4], v[5]
    t = work[5]
    e3, d3, d4, tmp = t[0], t[1], t[2], t[3]
    ad_apply(omega, omega_dot, a1)
    ad_apply(omega, a1, a2)
    ad_apply(omega, a2, a3)
    ad_apply(omega, a3, a4)
    ad_apply(omega_dot, a1, e1)
    ad_apply(omega_dot, a2, e2)
    ad_apply(omega_dot, a3, e3)
    ad_apply(omega, e1, tmp)
    for r in range(6):
        d3[r] = e2[r] + tmp[r]
    ad_apply(omega, d3, tmp)
    for r in range(6):
        d4[r] = e3[r] + tmp[r]
    theta_dtheta = omega[0] * omega_dot[0] + omega[1] * omega_dot[1] + omega[2] * omega_dot[2]
    for r in range(6):
        out[r] = theta_dtheta * (g[0] * a1[r] + g[1] * a2[r] + g[2] * a3[r] + g[3] * a4[r]) \
            + f[1] * e1[r] + f[2] * d3[r] + f[3] * d4[r]


@nonallocating
def inverse_adjoint_apply(R, p, X, out, hi):
    """``out = Ad_{g^-1} X`` on the columns [0, hi) of a 6 x n matrix X, for g = (R, p) (out must
    not alias X); out's other columns are left as they are.

    ``Ad_{g^-1} = [[R^T, 0], [-R^T p~, R^T]]``, i.e. [R^T w; R^T (v - p x w)] per column.
    """
    p0, p1, p2 = p[0], p[1], p[2]
    for i in range(3):
        r0, r1, r2 = R[0, i], R[1, i], R[2, i]
        # -R[:, i] . (p x w) = (p x R[:, i]) . w
        c0 = p1 * r2 - p2 * r1
        c1 = p2 * r0 - p0 * r2
        c2 = p0 * r1 - p1 * r0
        for j in range(hi):
            out[i, j] = r0 * X[0, j] + r1 * X[1, j] + r2 * X[2, j]
        for j in range(hi):
            out[3 + i, j] = r0 * X[3, j] + r1 * X[4, j] + r2 * X[5, j] \
                + c0 * X[0, j] + c1 * X[1, j] + c2 * X[2, j]


@nonallocating
def inverse_adjoint_apply_vector(R, p, x, out):
    """``out = Ad_{g^-1} x`` for g = (R, p) and a twist x (out must not alias x): the one-column
    case of :func:`inverse_adjoint_apply`, without reshaping the vectors into matrices."""
    p0, p1, p2 = p[0], p[1], p[2]
    for i in range(3):
        r0, r1, r2 = R[0, i], R[1, i], R[2, i]
        out[i] = r0 * x[0] + r1 * x[1] + r2 * x[2]
        out[3 + i] = r0 * x[3] + r1 * x[4] + r2 * x[5] \
            + (p1 * r2 - p2 * r1) * x[0] + (p2 * r0 - p0 * r2) * x[1] + (p0 * r1 - p1 * r0) * x[2]
