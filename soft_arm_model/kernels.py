"""Numba kernels of the Variable-Strain model: one pass over the quadrature points.

The kernel follows the geometric variable-strain formulation (SoRoSim):
between consecutive points one 4th-order Magnus (Zanna) step, with exact recursions for the body
Jacobian J, the body twist eta and the Jacobian rate Jdot; generalised terms by Gauss quadrature.
Everything is in the body frame of each cross-section (axis = local x) except positions and
rotations, which are expressed in ``arm_base``.

``evaluate`` computes, by ``level``:

- 0: kinematics: rotations R, positions p, body Jacobians J at the points and at the markers;
- 1: + static terms: gravity force F_g, elastic force F_el and its tangent K_t, tendon matrices A
  (with friction) and A0 (without), tendon lengths L_c, friction-aware tendon integrals theta,
  wrap angles, elastic and gravitational energies;
- 2: + dynamic terms: body twists eta, Jdot, mass matrix M, Coriolis matrix C (Mdot = C + C^T),
  kinetic energy.

It returns False when the configuration is outside the model's domain (non-positive axial stretch
or a degenerate tendon tangent); the outputs are then meaningless.

The kernels compile with ``fastmath``: 7-10 % faster, and no less reproducible across processors
than the BLAS already makes them (docs/decisions/0015-the-kernels-keep-fastmath.md).
"""
import numpy as np
from numba import njit

from .lie import (TANGENT_SCRATCH, ad_apply, ad_apply_columns, expmap, inverse_adjoint_apply, tangent,
                  tangent_rate, tangent_rate_apply)

ZANNA = np.sqrt(3.0) / 12.0  # coefficient of the commutator in the 4th-order Magnus step


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _strain(xi_star, Bx, q, out):
    for r in range(6):
        acc = xi_star[r]
        for j in range(q.shape[0]):
            acc += Bx[r, j] * q[j]
        out[r] = acc


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _matvec(Bx, v, out):
    for r in range(Bx.shape[0]):
        acc = 0.0
        for j in range(v.shape[0]):
            acc += Bx[r, j] * v[j]
        out[r] = acc


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def new_scratch(n):
    """Scratch for ``_magnus_step``: (vectors (10, 6), 6 x n matrices (6, 6, n), 6x6 (13, 6, 6),
    3x3 (1, 3, 3)). Allocated once per evaluation."""
    return (np.zeros((10, 6)), np.zeros((6, 6, n)), np.zeros((TANGENT_SCRATCH + 2, 6, 6)),
            np.zeros((1, 3, 3)))


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _magnus_step(q, qd, xi_star, h, B1, B2, R_prev, p_prev, J_prev, R_out, p_out, J_out,
                 rates, eta_prev, psi_prev, Jd_prev, eta_out, psi_out, Jd_out, scratch):
    """One Zanna step of length h from the previous section frame.

    rates = 0: R, p, J; 1: also the twist eta and psi = Jdot qd; 2: also Jdot.
    """
    vec, mat, sq, m3 = scratch
    n = q.shape[0]
    c = ZANNA * h * h
    xi1, xi2, com, omega, ps, omega_dot, V, xi1d, xi2d, tw = (
        vec[0], vec[1], vec[2], vec[3], vec[4], vec[5], vec[6], vec[7], vec[8], vec[9])
    Z, S, JS, Zd, G = mat[0], mat[1], mat[2], mat[3], mat[4]
    T, Tdot = sq[TANGENT_SCRATCH], sq[TANGENT_SCRATCH + 1]
    Rs = m3[0]
    _strain(xi_star, B1, q, xi1)
    _strain(xi_star, B2, q, xi2)
    ad_apply(xi1, xi2, com)
    for r in range(6):
        omega[r] = 0.5 * h * (xi1[r] + xi2[r]) + c * com[r]
    for r in range(6):
        for j in range(n):
            Z[r, j] = 0.5 * h * (B1[r, j] + B2[r, j])
    ad_apply_columns(xi1, B2, Z, c, True)
    ad_apply_columns(xi2, B1, Z, -c, True)
    expmap(omega, Rs, ps[0:3])
    for a in range(3):
        acc = p_prev[a]
        for b in range(3):
            acc += R_prev[a, b] * ps[b]
            s = 0.0
            for k in range(3):
                s += R_prev[a, k] * Rs[k, b]
            R_out[a, b] = s
        p_out[a] = acc
    tangent(omega, T, sq)
    for r in range(6):
        for j in range(n):
            acc = 0.0
            for k in range(6):
                acc += T[r, k] * Z[k, j]
            S[r, j] = acc
            JS[r, j] = J_prev[r, j] + acc
    inverse_adjoint_apply(Rs, ps, JS, J_out)
    if rates == 0:
        return
    # eta+ = Ad^-1 (eta + V), V = T Omegadot;
    # psi+ = Ad^-1 (psi + ad_eta V + Tdot Omegadot + T Zdot qd), Zdot qd = 2 c ad(xi1d) xi2d
    _matvec(Z, qd, omega_dot)
    _matvec(B1, qd, xi1d)
    _matvec(B2, qd, xi2d)
    _matvec(T, omega_dot, V)
    for r in range(6):
        tw[r] = eta_prev[r] + V[r]
    inverse_adjoint_apply(Rs, ps, tw.reshape((6, 1)), eta_out.reshape((6, 1)))
    tangent_rate_apply(omega, omega_dot, tw, sq)        # tw = Tdot Omegadot
    ad_apply(xi1d, xi2d, com)
    for r in range(6):
        acc = 0.0
        for k in range(6):
            acc += T[r, k] * com[k]
        tw[r] += 2.0 * c * acc + psi_prev[r]
    ad_apply(eta_prev, V, com)
    for r in range(6):
        tw[r] += com[r]
    inverse_adjoint_apply(Rs, ps, tw.reshape((6, 1)), psi_out.reshape((6, 1)))
    if rates == 1:
        return
    tangent_rate(omega, omega_dot, Tdot, sq)
    ad_apply_columns(xi1d, B2, Zd, c, False)
    ad_apply_columns(xi2d, B1, Zd, -c, True)
    # G = Jdot_prev + Tdot Z + T Zdot - ad(V)(J_prev + S)
    for r in range(6):
        for j in range(n):
            acc = Jd_prev[r, j]
            for k in range(6):
                acc += Tdot[r, k] * Z[k, j] + T[r, k] * Zd[k, j]
            G[r, j] = acc
    ad_apply_columns(V, JS, G, -1.0, True)
    inverse_adjoint_apply(Rs, ps, G, Jd_out)


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _elastic(w, B, xi, stiff_diag, neo_axial, col_lo, col_hi, Fel, Kt, energies):
    """Elastic force F_el = sum w B^T sigma(xi - xi*), tangent K_t, energy; False if stretch <= 0."""
    n = Fel.shape[0]
    P = w.shape[0]
    Fel[:] = 0.0
    Kt[:, :] = 0.0
    energy = 0.0
    sig = np.empty(6)
    dsig = np.empty(6)
    for pt in range(P):
        if w[pt] == 0.0:
            continue
        for r in range(6):
            e = xi[pt, r] - (1.0 if r == 3 else 0.0)
            sig[r] = stiff_diag[pt, r] * e
            dsig[r] = stiff_diag[pt, r]
            if r == 3 and neo_axial:
                lam = xi[pt, 3]
                if lam <= 0.0:
                    return False
                k3 = stiff_diag[pt, 3] / 3.0
                sig[r] = k3 * (lam - 1.0 / (lam * lam))
                dsig[r] = k3 * (1.0 + 2.0 / (lam * lam * lam))
                energy += w[pt] * k3 * (0.5 * lam * lam + 1.0 / lam - 1.5)
            else:
                energy += w[pt] * 0.5 * stiff_diag[pt, r] * e * e
        for a in range(col_lo[pt], col_hi[pt]):  # B is zero outside the point's division
            acc = 0.0
            for r in range(6):
                acc += B[pt, r, a] * sig[r]
            Fel[a] += w[pt] * acc
            for b in range(a, col_hi[pt]):
                acc = 0.0
                for r in range(6):
                    acc += B[pt, r, a] * dsig[r] * B[pt, r, b]
                Kt[a, b] += w[pt] * acc
    for a in range(n):
        for b in range(a):
            Kt[a, b] = Kt[b, a]
    energies[1] = energy
    return True


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _gravity(lumped, gravity, R, p, J, Fg, energies):
    """F_g = sum m J_lin^T R^T g over the points' lumped masses m (quadrature weight included, the
    tip point mass too); the gravity potential energy into energies[2]."""
    n = Fg.shape[0]
    Fg[:] = 0.0
    ug = 0.0
    a_body = np.empty(3)
    for pt in range(lumped.shape[0]):
        m = lumped[pt, 3]
        if m == 0.0:
            continue
        for r in range(3):
            a_body[r] = R[pt, 0, r] * gravity[0] + R[pt, 1, r] * gravity[1] + R[pt, 2, r] * gravity[2]
        for a in range(n):
            Fg[a] += m * (J[pt, 3, a] * a_body[0] + J[pt, 4, a] * a_body[1] + J[pt, 5, a] * a_body[2])
        ug -= m * (gravity[0] * p[pt, 0] + gravity[1] * p[pt, 1] + gravity[2] * p[pt, 2])
    energies[2] = ug


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _tendons(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
             A, A0, Lc, theta, wrap, phi):
    """Tendon columns with and without friction, lengths and friction-aware integrals."""
    n_t = t_d.shape[0]
    P = w.shape[0]
    A[:, :] = 0.0
    A0[:, :] = 0.0
    tang = np.empty((P, 3))
    ntau = np.zeros(P)
    xid = np.empty(6)
    tau = np.empty(3)
    taud = np.empty(3)
    tmp = np.empty(3)
    v = np.empty(3)
    phi_w = np.empty(6)
    for k in range(n_t):
        Lc[k] = 0.0
        theta[k] = 0.0
        for pt in range(P):
            phi[k, pt] = 0.0
            if w[pt] == 0.0 or t_active[k, pt] == 0.0:
                continue
            kap = xi[pt, 0:3]
            d = t_d[k, pt]
            dp = t_dp[k, pt]
            _cross(kap, d, tau)
            for r in range(3):
                tau[r] += xi[pt, 3 + r] + dp[r]
            nt = np.sqrt(tau[0] ** 2 + tau[1] ** 2 + tau[2] ** 2)
            if nt <= 1e-12:
                return False
            ntau[pt] = nt
            for r in range(3):
                tang[pt, r] = tau[r] / nt
            # tau' = k' x d + k x d' + gamma' + d''
            _matvec(Bd[pt], q, xid)
            _cross(xid[0:3], d, taud)
            _cross(kap, dp, tmp)
            for r in range(3):
                taud[r] += tmp[r] + xid[3 + r] + t_dpp[k, pt, r]
            t = tang[pt]
            tdt = t[0] * taud[0] + t[1] * taud[1] + t[2] * taud[2]
            _cross(kap, t, v)
            for r in range(3):
                v[r] += (taud[r] - t[r] * tdt) / nt
            nv2 = v[0] ** 2 + v[1] ** 2 + v[2] ** 2
            phi[k, pt] = np.sqrt(nv2 + smoothing * smoothing) - smoothing
        for pt in range(P):
            s = 0.0
            for j in range(P):
                s += Q[pt, j] * phi[k, j]
            wrap[k, pt] = s
        for pt in range(P):
            if w[pt] == 0.0 or t_active[k, pt] == 0.0:
                continue
            weight = np.exp(-t_mu[k] * wrap[k, pt])
            t = tang[pt]
            _cross(t_d[k, pt], t, tmp)
            for r in range(3):
                phi_w[r] = tmp[r]
                phi_w[3 + r] = t[r]
            wa = w[pt] * t_active[k, pt]
            for a in range(col_lo[pt], col_hi[pt]):
                acc = 0.0
                for r in range(6):
                    acc += B[pt, r, a] * phi_w[r]
                A0[a, k] += wa * acc
                A[a, k] += wa * weight * acc
            Lc[k] += wa * ntau[pt]
            theta[k] += wa * weight * ntau[pt]
    return True


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _ad_transpose_apply(x, y, out):
    """``out = ad(x)^T y`` = [-(w x a) - (v x b); -(w x b)] for x = [w; v], y = [a; b]."""
    w0, w1, w2, v0, v1, v2 = x[0], x[1], x[2], x[3], x[4], x[5]
    a0, a1, a2, b0, b1, b2 = y[0], y[1], y[2], y[3], y[4], y[5]
    out[0] = -(w1 * a2 - w2 * a1) - (v1 * b2 - v2 * b1)
    out[1] = -(w2 * a0 - w0 * a2) - (v2 * b0 - v0 * b2)
    out[2] = -(w0 * a1 - w1 * a0) - (v0 * b1 - v1 * b0)
    out[3] = -(w1 * b2 - w2 * b1)
    out[4] = -(w2 * b0 - w0 * b2)
    out[5] = -(w0 * b1 - w1 * b0)


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _mass_bias(lumped, J, eta, psi, col_hi, M, Cqd, energies):
    """M = sum J^T Mc J; C qd = sum J^T [Mc psi - ad_eta^T Mc eta] over the points' lumped inertias
    Mc; kinetic energy."""
    n = M.shape[0]
    M[:, :] = 0.0
    Cqd[:] = 0.0
    kin = 0.0
    y = np.empty(6)
    f = np.empty(6)
    for pt in range(lumped.shape[0]):
        if lumped[pt, 3] == 0.0:
            continue
        mc = lumped[pt]
        et = eta[pt]
        Jp = J[pt]
        hi = col_hi[pt] or n          # J is zero beyond the point's division (the tip: all of it)
        for r in range(6):
            y[r] = mc[r] * et[r]
            kin += 0.5 * y[r] * et[r]
        _ad_transpose_apply(et, y, f)
        for r in range(6):
            f[r] = mc[r] * psi[pt, r] - f[r]
        for a in range(hi):
            acc = 0.0
            for r in range(6):
                acc += Jp[r, a] * f[r]
            Cqd[a] += acc
            for b in range(a, hi):
                accm = 0.0
                for r in range(6):
                    accm += Jp[r, a] * mc[r] * Jp[r, b]
                M[a, b] += accm
    for a in range(n):
        for b in range(a):
            M[a, b] = M[b, a]
    energies[0] = kin


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _coriolis_matrix(lumped, J, eta, Jd, C):
    """C = sum J^T [Mc Jdot + (Mc ad_eta - ad_eta^T Mc) J] over the points' lumped inertias Mc, so
    that Mdot = C + C^T."""
    n = C.shape[0]
    C[:, :] = 0.0
    Wm = np.empty((6, n))
    adJ = np.empty((6, n))
    y = np.empty(6)
    t = np.empty(6)
    for pt in range(lumped.shape[0]):
        if lumped[pt, 3] == 0.0:
            continue
        mc = lumped[pt]
        et = eta[pt]
        Jp = J[pt]
        ad_apply_columns(et, Jp, adJ, 1.0, False)
        for j in range(n):
            for r in range(6):
                y[r] = mc[r] * Jp[r, j]
            _ad_transpose_apply(et, y, t)
            for r in range(6):
                Wm[r, j] = mc[r] * (Jd[pt, r, j] + adJ[r, j]) - t[r]
        for a in range(n):
            for b in range(n):
                acc = 0.0
                for r in range(6):
                    acc += Jp[r, a] * Wm[r, b]
                C[a, b] += acc


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def evaluate(w, B, Bd, h, B1, B2, xi_star, lumped, stiff_diag, neo_axial, R0, gravity,
             t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
             m_point, m_h, m_B1, m_B2,
             q, qd, level, markers,
             xi, R, p, J, eta, psi, Jd, mR, mp, mJ,
             M, C, Cqd, Fg, Fel, Kt, A, A0, Lc, theta, wrap, phi, energies):
    """Fill the workspace arrays for (q, qd) up to ``level`` (0 kinematics, 1 statics, 2 dynamics,
    3 Coriolis matrix), markers if ``markers``; returns False outside the model's domain."""
    P = w.shape[0]
    rates = 0 if level < 2 else (1 if level == 2 else 2)
    for pt in range(P):
        _strain(xi_star, B[pt], q, xi[pt])
    R[0] = R0
    p[0, :] = 0.0
    J[0] = 0.0
    eta[0, :] = 0.0
    psi[0, :] = 0.0
    Jd[0] = 0.0
    scratch = new_scratch(q.shape[0])
    for i in range(P - 1):
        _magnus_step(q, qd, xi_star, h[i], B1[i], B2[i], R[i], p[i], J[i], R[i + 1], p[i + 1],
                     J[i + 1], rates, eta[i], psi[i], Jd[i], eta[i + 1], psi[i + 1], Jd[i + 1],
                     scratch)
    if markers:
        for m in range(m_point.shape[0]):
            pt = m_point[m]
            if m_h[m] == 0.0:
                mR[m] = R[pt]
                mp[m] = p[pt]
                mJ[m] = J[pt]
            else:
                _magnus_step(q, qd, xi_star, m_h[m], m_B1[m], m_B2[m], R[pt], p[pt], J[pt], mR[m],
                             mp[m], mJ[m], 0, eta[pt], psi[pt], Jd[pt], eta[pt], psi[pt], Jd[pt],
                             scratch)
    if level < 1:
        return True
    if not _elastic(w, B, xi, stiff_diag, neo_axial, col_lo, col_hi, Fel, Kt, energies):
        return False
    _gravity(lumped, gravity, R, p, J, Fg, energies)
    if not _tendons(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                    A, A0, Lc, theta, wrap, phi):
        return False
    if level >= 2:
        _mass_bias(lumped, J, eta, psi, col_hi, M, Cqd, energies)
    if level >= 3:
        _coriolis_matrix(lumped, J, eta, Jd, C)
    return True


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def tendon_matrices(w, B, Bd, h, B1, B2, xi_star, lumped, stiff_diag, neo_axial, R0, gravity,
                    t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                    m_point, m_h, m_B1, m_B2, q, xi, A, A0, Lc, theta, wrap, phi):
    """Only the tendon terms at q (A, A0, L_c, theta, wrap angles) into the given arrays: they
    depend on the local strains alone, so no kinematics is needed. False outside the domain."""
    for pt in range(w.shape[0]):
        _strain(xi_star, B[pt], q, xi[pt])
    return _tendons(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                    A, A0, Lc, theta, wrap, phi)
