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
or a degenerate tendon tangent); the outputs are then meaningless. It keeps each Magnus step's
exponent Omega, Z = dOmega/dq and S = T(Omega) Z in the workspace.

``static_tangent`` then takes the static balance's tangent dR/dq = K_t - dF_g/dq + d(A u)/dq
analytically from that workspace, in one backward pass over the steps (see ``_gravity_tangent``
and ``_tendon_tangent``), and dA/d mu in closed form.

The kernels compile with ``fastmath``: 7-10 % faster, and no less reproducible across processors
than the BLAS already makes them (docs/decisions/0015-the-kernels-keep-fastmath.md).
"""
import numpy as np

from .lie import (TANGENT_SCRATCH, ad_apply, ad_apply_columns, ad_matrix, allocating, expmap,
                  inverse_adjoint_apply, inverse_adjoint_apply_vector, matmul_into, nonallocating, tangent,
                  tangent_rate, tangent_rate_apply, tangent_weights)

ZANNA = np.sqrt(3.0) / 12.0  # coefficient of the commutator in the 4th-order Magnus step


@nonallocating
def _strain(xi_star, Bx, q, lo, hi, out):
    """out = xi_star + Bx[:, lo:hi] q[lo:hi]: the strain of a basis that is zero outside the columns
    [lo, hi) (a division's; unsigned: see :func:`_columns`)."""
    for r in range(6):
        acc = xi_star[r]
        for j in range(lo, hi):
            acc += Bx[r, j] * q[j]
        out[r] = acc


@nonallocating
def _matvec(Bx, v, out):
    for r in range(Bx.shape[0]):
        acc = 0.0
        for j in range(v.shape[0]):
            acc += Bx[r, j] * v[j]
        out[r] = acc


@allocating
def new_scratch(n):
    """Scratch for ``_magnus_step``: (vectors (10, 6), 6 x n matrices (6, 6, n), 6x6 (13, 6, 6),
    3x3 (1, 3, 3)). Allocated once per evaluation."""
    return (np.zeros((10, 6)), np.zeros((6, 6, n)), np.zeros((TANGENT_SCRATCH + 2, 6, 6)),
            np.zeros((1, 3, 3)))


@nonallocating
def _magnus_step(q, qd, xi_star, h, B1, B2, lo, hi, R_prev, p_prev, J_prev, R_out, p_out, J_out,
                 rates, eta_prev, psi_prev, Jd_prev, eta_out, psi_out, Jd_out, scratch, omega, Z, S):
    """One Zanna step of length h from the previous section frame.

    rates = 0: R, p, J; 1: also the twist eta and psi = Jdot qd; 2: also Jdot. The step's Magnus
    exponent Omega, its q-derivative Z and S = T(Omega) Z go to ``omega``, ``Z`` and ``S`` (the
    workspace keeps them for the analytic derivatives; scratch's own vec[3], mat[0], mat[1] do
    where nobody needs them).

    [lo, hi) are the columns of the step's division: B1 and B2 are zero outside them, so Z and S
    are written there only, and J_prev and Jd_prev are zero from hi on (the coordinates of the
    divisions beyond the step do not move its frames), so J_out and Jd_out are computed on [0, hi)
    and zeroed beyond. The whole arm as one division is lo = 0, hi = n.
    """
    vec, mat, sq, m3 = scratch
    ulo, uhi = np.uint64(lo), np.uint64(hi)     # unsigned column loops vectorise: see _columns
    c = ZANNA * h * h
    xi1, xi2, com, ps, omega_dot, V, xi1d, xi2d, tw = (
        vec[0], vec[1], vec[2], vec[4], vec[5], vec[6], vec[7], vec[8], vec[9])
    JS, Zd, G = mat[2], mat[3], mat[4]
    T, Tdot = sq[TANGENT_SCRATCH], sq[TANGENT_SCRATCH + 1]
    Rs = m3[0]
    _strain(xi_star, B1, q, ulo, uhi, xi1)      # B1, B2 are zero outside [lo, hi)
    _strain(xi_star, B2, q, ulo, uhi, xi2)
    ad_apply(xi1, xi2, com)
    for r in range(6):
        omega[r] = 0.5 * h * (xi1[r] + xi2[r]) + c * com[r]
    for r in range(6):
        for j in range(ulo, uhi):
            Z[r, j] = 0.5 * h * (B1[r, j] + B2[r, j])
    ad_apply_columns(xi1, B2, Z, c, True, lo, hi)
    ad_apply_columns(xi2, B1, Z, -c, True, lo, hi)
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
    # S = T Z with T = [[T_w, 0], [T_v, T_w]]: the angular rows take Z's angular rows only; the
    # inner loop runs along Z's rows (vectorised)
    for r in range(6):
        for j in range(ulo, uhi):
            S[r, j] = 0.0
        for k in range(3 if r < 3 else 6):
            t = T[r, k]
            for j in range(ulo, uhi):
                S[r, j] += t * Z[k, j]
        for j in range(lo):
            JS[r, j] = J_prev[r, j]
        for j in range(ulo, uhi):
            JS[r, j] = J_prev[r, j] + S[r, j]
    inverse_adjoint_apply(Rs, ps, JS, J_out, hi)
    _zero_columns(J_out, hi)
    if rates == 0:
        return
    # eta+ = Ad^-1 (eta + V), V = T Omegadot;
    # psi+ = Ad^-1 (psi + ad_eta V + Tdot Omegadot + T Zdot qd), Zdot qd = 2 c ad(xi1d) xi2d
    # Omegadot = Z qd = h/2 (xi1d + xi2d) + c (ad(xi1) xi2d - ad(xi2) xi1d), xi1d = B1 qd, xi2d = B2 qd:
    # Z's definition applied to qd, without the 6 x n product
    _matvec_columns(B1, qd, lo, hi, xi1d)
    _matvec_columns(B2, qd, lo, hi, xi2d)
    ad_apply(xi1, xi2d, omega_dot)
    ad_apply(xi2, xi1d, com)
    for r in range(6):
        omega_dot[r] = 0.5 * h * (xi1d[r] + xi2d[r]) + c * (omega_dot[r] - com[r])
    _matvec(T, omega_dot, V)
    for r in range(6):
        tw[r] = eta_prev[r] + V[r]
    inverse_adjoint_apply_vector(Rs, ps, tw, eta_out)
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
    inverse_adjoint_apply_vector(Rs, ps, tw, psi_out)
    if rates == 1:
        return
    tangent_rate(omega, omega_dot, Tdot, sq)
    ad_apply_columns(xi1d, B2, Zd, c, False, lo, hi)
    ad_apply_columns(xi2d, B1, Zd, -c, True, lo, hi)
    # G = Jdot_prev + Tdot Z + T Zdot - ad(V)(J_prev + S)
    for r in range(6):
        for j in range(hi):
            G[r, j] = Jd_prev[r, j]
        for k in range(6):
            td, t = Tdot[r, k], T[r, k]
            for j in range(ulo, uhi):
                G[r, j] += td * Z[k, j] + t * Zd[k, j]
    ad_apply_columns(V, JS, G, -1.0, True, 0, hi)
    inverse_adjoint_apply(Rs, ps, G, Jd_out, hi)
    _zero_columns(Jd_out, hi)


@nonallocating
def _zero_columns(X, lo):
    """X[:, lo:] = 0, element by element."""
    ulo, un = np.uint64(lo), np.uint64(X.shape[1])
    for r in range(X.shape[0]):
        for j in range(ulo, un):
            X[r, j] = 0.0


@nonallocating
def _matvec_columns(Bx, v, lo, hi, out):
    """out = Bx[:, lo:hi] v[lo:hi]."""
    ulo, uhi = np.uint64(lo), np.uint64(hi)
    for r in range(Bx.shape[0]):
        acc = 0.0
        for j in range(ulo, uhi):
            acc += Bx[r, j] * v[j]
        out[r] = acc


@nonallocating
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@nonallocating
def _column_rows(Bp, lo, hi, rows):
    """rows[a] = the strain row r where Bp[r, a] != 0 for the columns a in [lo, hi), -1 where the
    column is zero at this point. Each coordinate is one strain mode's polynomial
    (``model._basis_at``): a column of B has at most one non-zero row."""
    for a in range(np.uint64(lo), np.uint64(hi)):
        rows[a] = -1
        for r in range(6):
            if Bp[r, a] != 0.0:
                rows[a] = r


@nonallocating
def strain_rows(w, B, col_lo, col_hi, rows):
    """rows[pt] (:func:`_column_rows`) at every point with weight, within its division's columns: what
    :func:`_elastic` and :func:`_tendons` read (``rows``: :func:`new_force_work`'s fourth array)."""
    for pt in range(w.shape[0]):
        if w[pt] != 0.0:
            lo, hi = _columns(col_lo, col_hi, pt)
            _column_rows(B[pt], lo, hi, rows[pt])


@nonallocating
def _elastic(w, B, xi, stiff_diag, neo_axial, col_lo, col_hi, Fel, Kt, energies, work):
    """Elastic force F_el = sum w B^T sigma(xi - xi*), tangent K_t, energy; False if stretch <= 0.
    ``work``: :func:`new_force_work`, its strain rows filled (:func:`strain_rows`)."""
    n = Fel.shape[0]
    P = w.shape[0]
    Fel[:] = 0.0
    Kt[:, :] = 0.0
    energy = 0.0
    sig, dsig = work[0][0], work[0][1]
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
        lo, hi = _columns(col_lo, col_hi, pt)      # B is zero outside the point's division
        rows = work[3][pt]
        # one strain mode per coordinate: B^T diag(dsig) B couples only coordinates of one mode, and
        # row r of B is zero in the columns of the other modes, so that the row's axpy over all of
        # them adds exact zeros there (no test per pair: it vectorises)
        for a in range(lo, hi):
            r = rows[a]
            if r < 0:
                continue
            Fel[a] += w[pt] * (B[pt, r, a] * sig[r])
            f = B[pt, r, a] * dsig[r]
            Br = B[pt, r]
            for b in range(a, hi):              # unsigned bounds (_columns): it vectorises
                Kt[a, b] += w[pt] * (f * Br[b])
    for a in range(n):
        for b in range(a):
            Kt[a, b] = Kt[b, a]
    energies[1] = energy
    return True


@nonallocating
def _gravity(lumped, gravity, R, p, J, Fg, energies, work):
    """F_g = sum m J_lin^T R^T g over the points' lumped masses m (quadrature weight included, the
    tip point mass too); the gravity potential energy into energies[2]."""
    n = Fg.shape[0]
    Fg[:] = 0.0
    ug = 0.0
    a_body = work[0][2]
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


@nonallocating
def _tendons(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
             A, A0, Lc, theta, wrap, phi, work):
    """Tendon columns with and without friction, lengths and friction-aware integrals. ``work``:
    :func:`new_force_work`, its strain rows filled (:func:`strain_rows`)."""
    n_t = t_d.shape[0]
    P = w.shape[0]
    A[:, :] = 0.0
    A0[:, :] = 0.0
    vec, per_point, ntau, rows = work[0], work[1], work[2], work[3]
    tang = per_point[0]
    # per point, whatever the tendon: the strain's rate of change along the arm xi' = Bd q (only
    # the points with weight are read)
    xid_all = per_point[1]
    for pt in range(P):
        if w[pt] != 0.0:
            _matvec(Bd[pt], q, xid_all[pt])
    tau, taud, tmp, v, phi_w = vec[2][0:3], vec[3][0:3], vec[4][0:3], vec[5][0:3], vec[6]
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
            xid = xid_all[pt]
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
            lo, hi = _columns(col_lo, col_hi, pt)
            for a in range(lo, hi):
                r = rows[pt, a]
                acc = B[pt, r, a] * phi_w[r] if r >= 0 else 0.0
                A0[a, k] += wa * acc
                A[a, k] += wa * weight * acc
            Lc[k] += wa * ntau[pt]
            theta[k] += wa * weight * ntau[pt]
    return True


@nonallocating
def tendon_rate_bias(w, B, xi, qd, t_d, t_dp, t_active, out):
    """out[k] = (dA0_k/dt)^T qd = qd^T (d A0_k/dq) qd [m/s^2]: the part of tendon k's length
    acceleration that the rates alone give (its rate of change with qdd = 0), at the strains ``xi``
    of q. A tendon's length is the integral of ``norm(tau)``, ``tau = kappa x d + gamma + d'``, with
    its routing d(X), d'(X) fixed in the section, so along qd
    ``d2/dt2 norm(tau) = (norm(tau')^2 - (t . tau')^2) / norm(tau)``, with
    ``tau' = kappa' x d + gamma'`` and ``(kappa'; gamma') = B qd``: exact, and local like the tendon
    terms (no kinematics). Call it after a successful :func:`evaluate` at q (its strains, and
    ``norm(tau) > 0``, which that checks)."""
    n_t = t_d.shape[0]
    for k in range(n_t):
        out[k] = 0.0
    for pt in range(w.shape[0]):
        if w[pt] == 0.0:
            continue
        # (kappa'; gamma') = B qd at the point
        r0 = r1 = r2 = r3 = r4 = r5 = 0.0
        for j in range(qd.shape[0]):
            v = qd[j]
            r0 += B[pt, 0, j] * v
            r1 += B[pt, 1, j] * v
            r2 += B[pt, 2, j] * v
            r3 += B[pt, 3, j] * v
            r4 += B[pt, 4, j] * v
            r5 += B[pt, 5, j] * v
        k0, k1, k2 = xi[pt, 0], xi[pt, 1], xi[pt, 2]
        for k in range(n_t):
            wa = w[pt] * t_active[k, pt]
            if wa == 0.0:
                continue
            d0, d1, d2 = t_d[k, pt, 0], t_d[k, pt, 1], t_d[k, pt, 2]
            a0 = k1 * d2 - k2 * d1 + xi[pt, 3] + t_dp[k, pt, 0]
            a1 = k2 * d0 - k0 * d2 + xi[pt, 4] + t_dp[k, pt, 1]
            a2 = k0 * d1 - k1 * d0 + xi[pt, 5] + t_dp[k, pt, 2]
            b0 = r1 * d2 - r2 * d1 + r3
            b1 = r2 * d0 - r0 * d2 + r4
            b2 = r0 * d1 - r1 * d0 + r5
            nt = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            along = (a0 * b0 + a1 * b1 + a2 * b2) / nt
            out[k] += wa * (b0 * b0 + b1 * b1 + b2 * b2 - along * along) / nt


@nonallocating
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


@allocating
def _mass_bias(lumped, J, eta, psi, col_hi, M, Cqd, energies, work):
    """M = sum J^T Mc J; C qd = sum J^T [Mc psi - ad_eta^T Mc eta] over the points' lumped inertias
    Mc; kinetic energy. ``work``: :func:`new_force_work`."""
    n = M.shape[0]
    _bias(lumped, J, eta, psi, col_hi, Cqd, energies, work)
    # M = G^T (Mc G) with G the points' Jacobians stacked (6 P x n; a massless point's rows add
    # nothing): one matrix product, which the BLAS vectorises where sums per point and row did not
    G = J.reshape((J.shape[0] * 6, n))
    W = work[4]
    _weigh_rows(lumped, G, W)
    np.dot(G.T, W, M)
    for a in range(n):                # exactly symmetric: the product's rounding need not be
        for b in range(a):
            M[a, b] = M[b, a]


@nonallocating
def _weigh_rows(lumped, G, W):
    """W = diag(lumped, stacked by point) G."""
    P = lumped.shape[0]
    for pt in range(P):
        for r in range(6):
            m = lumped[pt, r]
            for j in range(G.shape[1]):
                W[6 * pt + r, j] = m * G[6 * pt + r, j]


@nonallocating
def _bias(lumped, J, eta, psi, col_hi, Cqd, energies, work):
    """C qd = sum J^T [Mc psi - ad_eta^T Mc eta] over the points' lumped inertias Mc, and the kinetic
    energy into energies[0]."""
    n = Cqd.shape[0]
    Cqd[:] = 0.0
    kin = 0.0
    y, f = work[0][0], work[0][1]
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
    energies[0] = kin


@allocating
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
        ad_apply_columns(et, Jp, adJ, 1.0, False, 0, n)
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


@nonallocating
def _kinematics(B, h, B1, B2, xi_star, R0, col_lo, col_hi, m_point, m_h, m_B1, m_B2, q, qd, rates, markers,
                xi, R, p, J, eta, psi, Jd, mR, mp, mJ, Om, Zs, Ss, scratch):
    """The strains at the points, the frames and Jacobians along the arm (with the twists and
    their rates as ``rates`` asks: see :func:`_magnus_step`), and the markers' if ``markers``."""
    P = xi.shape[0]
    for pt in range(P):
        lo, hi = _columns(col_lo, col_hi, pt)      # B is zero outside the point's division
        _strain(xi_star, B[pt], q, lo, hi, xi[pt])
    # element by element: a whole-array assignment may copy its source, which needs the runtime
    for a in range(3):
        p[0, a] = 0.0
        for b in range(3):
            R[0, a, b] = R0[a, b]
    J[0] = 0.0
    eta[0, :] = 0.0
    psi[0, :] = 0.0
    Jd[0] = 0.0
    n = q.shape[0]
    for i in range(P - 1):
        lo, hi = _step_columns(col_lo, col_hi, i)
        _magnus_step(q, qd, xi_star, h[i], B1[i], B2[i], lo, hi, R[i], p[i], J[i], R[i + 1], p[i + 1],
                     J[i + 1], rates, eta[i], psi[i], Jd[i], eta[i + 1], psi[i + 1], Jd[i + 1],
                     scratch, Om[i], Zs[i], Ss[i])
    if markers:
        for m in range(m_point.shape[0]):
            pt = m_point[m]
            if m_h[m] == 0.0:
                for a in range(3):
                    mp[m, a] = p[pt, a]
                    for b in range(3):
                        mR[m, a, b] = R[pt, a, b]
                for a in range(6):
                    for b in range(J.shape[2]):
                        mJ[m, a, b] = J[pt, a, b]
            else:
                _magnus_step(q, qd, xi_star, m_h[m], m_B1[m], m_B2[m], np.uint64(0), np.uint64(n), R[pt],
                             p[pt], J[pt], mR[m], mp[m], mJ[m], 0, eta[pt], psi[pt], Jd[pt], eta[pt],
                             psi[pt], Jd[pt], scratch, scratch[0][3], scratch[1][0], scratch[1][1])


@nonallocating
def evaluate(w, B, Bd, h, B1, B2, xi_star, lumped, stiff_diag, neo_axial, R0, gravity,
             t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
             m_point, m_h, m_B1, m_B2,
             q, qd, level, markers,
             xi, R, p, J, eta, psi, Jd, mR, mp, mJ,
             M, C, Cqd, Fg, Fel, Kt, A, A0, Lc, theta, wrap, phi, energies, Om, Zs, Ss, work):
    """Fill the workspace arrays for (q, qd) up to ``level`` (0 kinematics, 1 statics, 2 dynamics,
    3 Coriolis matrix), markers if ``markers``; returns False outside the model's domain.
    ``work``: the kernels' scratch (:func:`new_work`). Compiled without reference counting, as
    its callers that unpack the workspace into it are; the mass matrix's product (the BLAS) and
    the Coriolis matrix count their own."""
    rates = 0 if level < 2 else (1 if level == 2 else 2)
    _kinematics(B, h, B1, B2, xi_star, R0, col_lo, col_hi, m_point, m_h, m_B1, m_B2, q, qd, rates, markers,
                xi, R, p, J, eta, psi, Jd, mR, mp, mJ, Om, Zs, Ss, work[0])
    if level < 1:
        return True
    forces = work[2]
    strain_rows(w, B, col_lo, col_hi, forces[3])
    if not _elastic(w, B, xi, stiff_diag, neo_axial, col_lo, col_hi, Fel, Kt, energies, forces):
        return False
    _gravity(lumped, gravity, R, p, J, Fg, energies, forces)
    if not _tendons(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                    A, A0, Lc, theta, wrap, phi, forces):
        return False
    if level >= 2:
        _mass_bias(lumped, J, eta, psi, col_hi, M, Cqd, energies, forces)
    if level >= 3:
        _coriolis_matrix(lumped, J, eta, Jd, C)
    return True


# --------------------------------------------------------------------------------------------------
# Analytic tangent of the static balance R(q) = F_el(q) - F_g(q) + A(q) u.


@allocating
def new_work(P, n):
    """The kernels' scratch, allocated once with a workspace (``ArmData.work``): (the Magnus step's
    (:func:`new_scratch`), :func:`static_tangent`'s (:func:`new_tangent_work`), the forces'
    (:func:`new_force_work`)), for a model of ``P`` points and ``n`` coordinates."""
    return (new_scratch(n), new_tangent_work(P, n), new_force_work(P, n))


@allocating
def new_force_work(P, n):
    """Scratch for the forces (:func:`_elastic`, :func:`_gravity`, :func:`_tendons`,
    :func:`_mass_bias`): vectors (8, 6); per point (2, P, 6) (a tendon's unit tangent, the
    strains' rates along the arm); per point (P,) (a tendon's norm(tau)); the strain row of each
    column per point (P, n), int; the mass-weighted Jacobians (6 P, n)."""
    return (np.zeros((8, 6)), np.zeros((2, P, 6)), np.zeros(P), np.full((P, n), -1, dtype=np.int64),
            np.zeros((6 * P, n)))


@allocating
def new_tangent_work(P, n):
    """Scratch for :func:`static_tangent`: (6 x n matrices (6, 6, n), P x n matrices (2, P, n),
    6x6 (TANGENT_SCRATCH + 8, 6, 6), vectors (16, 6))."""
    return (np.zeros((6, 6, n)), np.zeros((2, P, n)), np.zeros((TANGENT_SCRATCH + 8, 6, 6)),
            np.zeros((16, 6)))


@nonallocating
def _pi_matrix(U, out):
    """``out[d, v] = U^T ad(e_d) e_v``: the bilinear form (delta, v) -> U^T ad(delta) v of the wrench
    U = [a; b], i.e. [[-a~, -b~], [-b~, 0]] (skew: U^T ad(x) y = -U^T ad(y) x)."""
    out[:, :] = 0.0
    a0, a1, a2, b0, b1, b2 = U[0], U[1], U[2], U[3], U[4], U[5]
    # -a~ in the top-left block, -b~ in the top-right and bottom-left blocks
    for (i, j, s) in ((0, 1, 1.0), (0, 2, -1.0), (1, 0, -1.0), (1, 2, 1.0), (2, 0, 1.0), (2, 1, -1.0)):
        k = 3 - i - j
        out[i, j] = s * (a0 if k == 0 else (a1 if k == 1 else a2))
        bv = s * (b0 if k == 0 else (b1 if k == 1 else b2))
        out[i, 3 + j] = bv
        out[3 + i, j] = bv


@nonallocating
def _step_columns(col_lo, col_hi, i):
    """Columns [lo, hi) of the division the Magnus step from point i to i + 1 lies in (unsigned,
    as :func:`_columns`)."""
    if col_hi[i] > col_lo[i]:
        return _columns(col_lo, col_hi, i)
    return _columns(col_lo, col_hi, i + 1)


@nonallocating
def _columns(col_lo, col_hi, pt):
    """Columns [lo, hi) of point pt's division, as unsigned integers: a loop from a signed start
    that the compiler cannot prove non-negative keeps numba's negative-index wraparound in its
    body, which stops it vectorising (three times slower on these short rows)."""
    return np.uint64(col_lo[pt]), np.uint64(col_hi[pt])


@nonallocating
def _gravity_tangent(h, B1, B2, lumped, gravity, col_lo, col_hi, R, p, J, Om, Zs, Ss, jac, work):
    """jac -= dF_g/dq, by one backward pass over the Magnus steps.

    With g_k the frame of point k, S_k = T(Omega_k) Z_k the step's contribution to the body
    Jacobians (J_{k+1} = Ad_{exp(-Omega_k)} (J_k + S_k)) and mu_k the gravity wrench of everything
    beyond point k, in frame k, F_g = sum_k S_k^T mu_k. Its derivative has three parts:
    the steps before k move frame k (-(ad_{S_a}^T mu_k) . J_k[:, b]), every step moves the masses
    beyond k (their first moment's derivative, through the moment of mu_k), and step k's own
    S_k depends on q through Omega_k (dT/dOmega) and Z_k (the Zanna commutator).
    """
    m6n, _, sq, vec = work
    n = jac.shape[0]
    P = R.shape[0]
    Cd, G, HZ, PB = m6n[0], m6n[1], m6n[3], m6n[4]
    ad1, Hm, Pi, tmp = sq[0], sq[1], sq[2], sq[3]
    f, g = sq[4, 0, 0:4], sq[4, 1, 0:4]
    mu, lam, U, nf, V, gu = vec[0], vec[1], vec[2:7], vec[7], vec[8:12], vec[12]
    Cd[0:3, :] = 0.0
    cx, cy, cz = 0.0, 0.0, 0.0     # first moment of the masses beyond the current point
    mass = 0.0
    gx, gy, gz = gravity[0], gravity[1], gravity[2]
    for k in range(P - 2, -1, -1):
        i = k + 1
        m = lumped[i, 3]
        if m != 0.0:
            mass += m
            cx += m * p[i, 0]
            cy += m * p[i, 1]
            cz += m * p[i, 2]
            for r in range(3):
                for b in range(n):
                    Cd[r, b] += m * (R[i, r, 0] * J[i, 3, b] + R[i, r, 1] * J[i, 4, b]
                                     + R[i, r, 2] * J[i, 5, b])
        if mass == 0.0:
            continue
        lo, hi = _step_columns(col_lo, col_hi, k)
        Rk = R[k]
        # wrench beyond k about p_k, in arm_base: moment (c - M p_k) x g, force M g; into frame k
        ox, oy, oz = cx - mass * p[k, 0], cy - mass * p[k, 1], cz - mass * p[k, 2]
        nf[0] = oy * gz - oz * gy
        nf[1] = oz * gx - ox * gz
        nf[2] = ox * gy - oy * gx
        nf[3], nf[4], nf[5] = mass * gx, mass * gy, mass * gz
        for r in range(3):
            mu[r] = Rk[0, r] * nf[0] + Rk[1, r] * nf[1] + Rk[2, r] * nf[2]
            mu[3 + r] = Rk[0, r] * nf[3] + Rk[1, r] * nf[4] + Rk[2, r] * nf[5]
        # (1) the steps before k move frame k: mu^T ad_{J_k b} S_a = -S_a^T Pi(mu) J_k[:, b];
        # (2) every step moves the masses beyond k: (R_k S_a^ang) . (dc/dq_b x g).
        # Together d(F_g)_a/dq_b += S_a^T G_b with G = -Pi(mu) J_k + [R_k^T (dc/dq x g); 0].
        Sk = Ss[k]
        Jk = J[k]
        _pi_matrix(mu, Pi)
        for r in range(6):
            for b in range(n):
                G[r, b] = 0.0
            if r < 3:
                for b in range(n):
                    e0 = Cd[1, b] * gz - Cd[2, b] * gy
                    e1 = Cd[2, b] * gx - Cd[0, b] * gz
                    e2 = Cd[0, b] * gy - Cd[1, b] * gx
                    G[r, b] = Rk[0, r] * e0 + Rk[1, r] * e1 + Rk[2, r] * e2
            for s_ in range(6):
                pv = Pi[r, s_]
                if pv != 0.0:
                    for b in range(hi):        # J_k is zero beyond the step's division
                        G[r, b] -= pv * Jk[s_, b]
        for a in range(lo, hi):
            s0, s1, s2, s3, s4, s5 = Sk[0, a], Sk[1, a], Sk[2, a], Sk[3, a], Sk[4, a], Sk[5, a]
            for b in range(n):
                jac[a, b] -= (s0 * G[0, b] + s1 * G[1, b] + s2 * G[2, b] + s3 * G[3, b]
                              + s4 * G[4, b] + s5 * G[5, b])
        # (3) step k's own S_k = T(Omega) Z: mu^T dT[Z_b] Z_a + mu^T T dZ_a/dq_b
        om = Om[k]
        tangent_weights(om[0] ** 2 + om[1] ** 2 + om[2] ** 2, f, g)
        ad_matrix(om, ad1)
        # U_j = (ad^T)^j mu (j = 0..4); lam = T^T mu = mu + sum_k f_{k-1} U_k
        for r in range(6):
            U[0, r] = mu[r]
        for j in range(1, 5):
            _ad_transpose_apply(om, U[j - 1], U[j])
        for r in range(6):
            lam[r] = mu[r] + f[0] * U[1, r] + f[1] * U[2, r] + f[2] * U[3, r] + f[3] * U[4, r]
        # Hm[d, y] = d/dOmega_d (mu^T T e_y): the weights' part sum_k g_{k-1} Omega_ang,d U_k[y],
        # and sum_k f_{k-1} mu^T d(ad^k)[e_d] e_y = sum_j Pi(U_j) Phi_j (Phi_j = sum_m f_{j+m} ad^m)
        # = sum_m Pi(V_m) ad^m with V_m = sum_{j <= 3-m} f_{j+m} U_j, by Horner's rule in ad.
        for m in range(4):
            for r in range(6):
                acc = 0.0
                for j in range(4 - m):
                    acc += f[j + m] * U[j, r]
                V[m, r] = acc
        _pi_matrix(V[3], Hm)
        for m in range(2, -1, -1):
            matmul_into(Hm, ad1, tmp)
            _pi_matrix(V[m], Hm)
            for r in range(6):
                for s_ in range(6):
                    Hm[r, s_] += tmp[r, s_]
        for r in range(6):
            gu[r] = g[0] * U[1, r] + g[1] * U[2, r] + g[2] * U[3, r] + g[3] * U[4, r]
        for d in range(3):
            od = om[d]
            for y in range(6):
                Hm[d, y] += od * gu[y]
        Zk = Zs[k]
        # HZ = Hm Z (6 x cols); local[a, b] += Z_b^T Hm Z_a
        for r in range(6):
            for a in range(lo, hi):
                HZ[r, a] = 0.0
            for s_ in range(6):
                hv = Hm[r, s_]
                for a in range(lo, hi):
                    HZ[r, a] += hv * Zk[s_, a]
        # W = B1^T Pi(lam) B2, local += c (W + W^T)
        _pi_matrix(lam, Pi)
        c = ZANNA * h[k] * h[k]
        b1 = B1[k]
        b2 = B2[k]
        for a in range(lo, hi):
            for r in range(6):
                PB[r, a] = 0.0
            for s_ in range(6):
                bv = b2[s_, a]
                if bv != 0.0:
                    bv *= c
                    for r in range(6):
                        PB[r, a] += Pi[r, s_] * bv
        for a in range(lo, hi):
            for b in range(lo, hi):
                jac[a, b] -= (Zk[0, b] * HZ[0, a] + Zk[1, b] * HZ[1, a] + Zk[2, b] * HZ[2, a]
                              + Zk[3, b] * HZ[3, a] + Zk[4, b] * HZ[4, a] + Zk[5, b] * HZ[5, a])
        # B1 has one non-zero row per column (its strain mode): B1^T PB and its transpose
        for r in range(6):
            for a in range(lo, hi):
                ba = b1[r, a]
                if ba != 0.0:
                    for b in range(lo, hi):
                        jac[a, b] -= ba * PB[r, b]
                        jac[b, a] -= ba * PB[r, b]


@nonallocating
def _turning_rate_gradient(k, w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, smoothing, col_lo, col_hi,
                           Gphi, sq, vec):
    """Gphi[j, :] = d phi_k(X_j)/dq: the gradient of tendon k's smoothed turning rate
    phi = sqrt(|v|^2 + s^2) - s, v = kappa x t + (I - t t^T) tau' / |tau|, at every point, through
    the strains xi = xi* + B q and their derivatives xi' = Bd q."""
    P = w.shape[0]
    tau, taud, t, v, e, s3, rt, tmp, col = vec[8], vec[9], vec[10], vec[11], vec[12], vec[13], \
        vec[14], vec[15], vec[7]
    gphi = sq[TANGENT_SCRATCH + 6]    # rows 0, 1: d phi / d xi, d phi / d xi'
    Gphi[:, :] = 0.0
    for j in range(P):
        if w[j] == 0.0 or t_active[k, j] == 0.0:
            continue
        d = t_d[k, j]
        dp = t_dp[k, j]
        kap = xi[j, 0:3]
        _cross(kap, d, tau)
        for r in range(3):
            tau[r] += xi[j, 3 + r] + dp[r]
        nt = np.sqrt(tau[0] ** 2 + tau[1] ** 2 + tau[2] ** 2)
        for r in range(3):
            t[r] = tau[r] / nt
        _matvec(Bd[j], q, col)          # xi' = Bd q
        _cross(col[0:3], d, taud)
        _cross(kap, dp, tmp)
        for r in range(3):
            taud[r] += tmp[r] + col[3 + r] + t_dpp[k, j, r]
        tdt = t[0] * taud[0] + t[1] * taud[1] + t[2] * taud[2]
        _cross(kap, t, v)
        for r in range(3):
            v[r] += (taud[r] - t[r] * tdt) / nt
        rho = np.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2 + smoothing * smoothing)
        for r in range(3):
            e[r] = v[r] / rho
        te = t[0] * e[0] + t[1] * e[1] + t[2] * e[2]
        for r in range(3):
            s3[r] = (e[r] - t[r] * te) / nt          # P_t e / |tau|
        # rt = M_tau^T e = P_t (-kap x e) / n - P_t ((t.tau') e + (t.e) tau') / n^2 - t (tau'.P_t e) / n^2
        _cross(kap, e, tmp)
        for r in range(3):
            tmp[r] = -tmp[r] / nt - (tdt * e[r] + te * taud[r]) / (nt * nt)
        ttmp = t[0] * tmp[0] + t[1] * tmp[1] + t[2] * tmp[2]
        tps = (taud[0] * s3[0] + taud[1] * s3[1] + taud[2] * s3[2]) / nt
        for r in range(3):
            rt[r] = tmp[r] - t[r] * ttmp - t[r] * tps
        # d phi/d xi = [t x e + d x rt + d' x s3; rt], d phi/d xi' = [d x s3; s3]
        _cross(t, e, tmp)
        for r in range(3):
            gphi[0, r] = tmp[r]
        _cross(d, rt, tmp)
        for r in range(3):
            gphi[0, r] += tmp[r]
        _cross(dp, s3, tmp)
        for r in range(3):
            gphi[0, r] += tmp[r]
            gphi[0, 3 + r] = rt[r]
        _cross(d, s3, tmp)
        for r in range(3):
            gphi[1, r] = tmp[r]
            gphi[1, 3 + r] = s3[r]
        lo, hi = _columns(col_lo, col_hi, j)
        for b in range(lo, hi):
            acc = 0.0
            for r in range(6):
                acc += gphi[0, r] * B[j, r, b] + gphi[1, r] * Bd[j, r, b]
            Gphi[j, b] = acc


@nonallocating
def _tendon_tangent(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                    wrap, u, friction, jac, dA_dmu, work):
    """jac += d(A u)/dq (A with the friction weight if ``friction``, else A0), and the derivative
    of A with respect to the friction coefficients into dA_dmu (n, n_t: column k is dA_k/dmu_k, the
    only one of A's columns mu_k moves; zero without friction). Local in the strains but for the
    friction weight's wrap angle, an integral of the tendon's turning rate phi from the base: its
    gradient enters through Q."""
    m6n, mPn, sq, vec = work
    n_t = t_d.shape[0]
    P = w.shape[0]
    DB = m6n[5]
    Gphi, dwrap = mPn[0], mPn[1]
    Dt = sq[TANGENT_SCRATCH + 5]
    tau, t, v, tmp = vec[8], vec[10], vec[11], vec[15]
    dA_dmu[:, :] = 0.0
    for pt in range(P):
        if w[pt] == 0.0:
            continue
        lo, hi = _columns(col_lo, col_hi, pt)
        Dt[:, :] = 0.0
        any_t = False
        for k in range(n_t):
            if t_active[k, pt] == 0.0 or u[k] == 0.0:
                continue
            any_t = True
            d = t_d[k, pt]
            _cross(xi[pt, 0:3], d, tau)
            for r in range(3):
                tau[r] += xi[pt, 3 + r] + t_dp[k, pt, r]
            nt = np.sqrt(tau[0] ** 2 + tau[1] ** 2 + tau[2] ** 2)
            for r in range(3):
                t[r] = tau[r] / nt
            weight = np.exp(-t_mu[k] * wrap[k, pt]) if friction else 1.0
            s = u[k] * w[pt] * t_active[k, pt] * weight / nt
            # d Phi_w / d xi = (1/|tau|) [d~; I] (I - t t^T) [-d~, I], column by column
            for c in range(6):
                tmp[:] = 0.0
                if c < 3:
                    tmp[c] = 1.0
                    _cross(tmp, d, v)             # -d~ e_c = e_c x d
                else:
                    v[:] = 0.0
                    v[c - 3] = 1.0
                tx = t[0] * v[0] + t[1] * v[1] + t[2] * v[2]
                for r in range(3):
                    v[r] -= t[r] * tx
                _cross(d, v, tmp)
                for r in range(3):
                    Dt[r, c] += s * tmp[r]
                    Dt[3 + r, c] += s * v[r]
        if not any_t:
            continue
        for b in range(lo, hi):                # B has one non-zero row per column
            for r in range(6):
                DB[r, b] = 0.0
            for c in range(6):
                bv = B[pt, c, b]
                if bv != 0.0:
                    for r in range(6):
                        DB[r, b] += Dt[r, c] * bv
        for r in range(6):
            for a in range(lo, hi):
                ba = B[pt, r, a]
                if ba != 0.0:                  # one strain row per basis column
                    for b in range(lo, hi):
                        jac[a, b] += ba * DB[r, b]
    if not friction:
        return
    # friction weight: A_k u_k = u_k sum_pt wa exp(-mu wrap(pt)) B^T Phi_w, wrap = Q phi
    for k in range(n_t):
        stiff = u[k] != 0.0 and t_mu[k] != 0.0     # the weight's q-derivative enters jac
        if not stiff:
            Gphi[:, :] = 0.0
            dwrap[:, :] = 0.0
        else:
            _turning_rate_gradient(k, w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, smoothing, col_lo,
                                   col_hi, Gphi, sq, vec)
        # dwrap = Q Gphi, then jac[a, b] += sum_pt c_pt[a] dwrap[pt, b]
        for pt in range(P):
            if w[pt] == 0.0 or t_active[k, pt] == 0.0:
                continue
            lo, hi = _columns(col_lo, col_hi, pt)
            if stiff:
                for b in range(hi):
                    dwrap[pt, b] = 0.0
                for j in range(P):
                    qv = Q[pt, j]
                    if qv != 0.0:
                        for b in range(hi):
                            dwrap[pt, b] += qv * Gphi[j, b]
            d = t_d[k, pt]
            kap = xi[pt, 0:3]
            _cross(kap, d, tau)
            for r in range(3):
                tau[r] += xi[pt, 3 + r] + t_dp[k, pt, r]
            nt = np.sqrt(tau[0] ** 2 + tau[1] ** 2 + tau[2] ** 2)
            for r in range(3):
                t[r] = tau[r] / nt
            _cross(d, t, tmp)
            weight = np.exp(-t_mu[k] * wrap[k, pt])
            wa = w[pt] * t_active[k, pt] * weight
            for a in range(lo, hi):
                acc = 0.0
                for r in range(3):
                    acc += B[pt, r, a] * tmp[r] + B[pt, 3 + r, a] * t[r]
                ba = wa * acc                       # this point's share of A[a, k]
                dA_dmu[a, k] -= ba * wrap[k, pt]
                if stiff:
                    f = -t_mu[k] * u[k] * ba
                    for b in range(hi):
                        jac[a, b] += f * dwrap[pt, b]


@nonallocating
def static_tangent(w, B, Bd, h, B1, B2, xi_star, lumped, stiff_diag, neo_axial, R0, gravity,
                   t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                   m_point, m_h, m_B1, m_B2,
                   q, u, friction,
                   xi, R, p, J, eta, psi, Jd, mR, mp, mJ,
                   M, C, Cqd, Fg, Fel, Kt, A, A0, Lc, theta, wrap, phi, energies, Om, Zs, Ss,
                   work, jac, dA_dmu):
    """The analytic tangent of the static residual, dR/dq = K_t - dF_g/dq + d(A u)/dq, into jac
    (A with the friction weight if ``friction``, else A0), and dA/d mu into dA_dmu (n, n_t; column k
    is dA_k/dmu_k, so d(A u)/d mu = dA_dmu diag(u)),
    from the workspace as :func:`evaluate` (level >= 1) left it at q."""
    n = q.shape[0]
    for a in range(n):
        for b in range(n):
            jac[a, b] = Kt[a, b]
    _gravity_tangent(h, B1, B2, lumped, gravity, col_lo, col_hi, R, p, J, Om, Zs, Ss, jac, work[1])
    _tendon_tangent(w, B, Bd, xi, q, t_d, t_dp, t_dpp, t_active, t_mu, Q, smoothing, col_lo, col_hi,
                    wrap, u, friction, jac, dA_dmu, work[1])
