"""The immutable arm model and its scratch workspace (Pinocchio style: ``ArmModel`` + ``ArmData``).

``build_model(config)`` discretises the arm once: divisions, Legendre strain basis, Gauss points and
Magnus intervals, cross-section properties, tendon routing, friction quadrature, K and D. Algorithms
are free functions of ``(model, data, q, ...)`` in :mod:`soft_arm_model.dynamics`,
:mod:`~soft_arm_model.statics` and :mod:`~soft_arm_model.integrators`.

Generalised coordinates ``q`` (length ``model.n``) are ordered by division, then strain mode
(``config.STRAIN_MODES`` order), then Legendre order. Angular basis rows are divided by the division
length, so an angular coordinate is an angle [rad] and an axial/shear coordinate a strain [-].
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.polynomial import legendre as npleg

from soft_arm_model import kernels

from .config import STRAIN_MODES, ArmConfig, Discretisation, load_arm_config
from .routing import routing_arrays, routing_of, tendon_ends

# arm_base <- section frame at the clamp: the section's x axis (the arm axis) points along -z,
# its y axis along +y and its z axis along +x.
R_BASE = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
XI_STAR = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
_ZANNA_OFFSETS = (0.5 - np.sqrt(3.0) / 6.0, 0.5 + np.sqrt(3.0) / 6.0)


def _frozen(a):
    a = np.ascontiguousarray(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class ArmModel:
    """Discretised arm. Arrays are read-only; ``P`` points, ``n`` coordinates, ``n_tendons`` tendons.

    Attributes (units SI, vectors in the section frame unless noted)::

      X, w: point abscissae [m] and quadrature weights [m] (zero at division ends).
      B, Bd: strain basis and its X-derivative at the points, (P, 6, n).
      h, B1, B2: Magnus interval lengths [m] and bases at the two Zanna points, (P-1,), (P-1, 6, n).
      mass_diag: rho [Jp, I, I, A, A, A]; stiff_diag: [G Jp, E I, E I, E A, G A, G A];
      visc_diag: eta [Jp, 3I, 3I, 3A, A, A] per point, (P, 6).
      lumped_mass: the inertia each point carries in the sums over points, (P, 6) [kg m^2, kg]:
        w mass_diag, plus the tip point mass (``tip_mass``, no rotary inertia) at the last point.
      K, D: stiffness at the reference and damping matrices, (n, n).
      tendon_d, tendon_dp, tendon_dpp: tendon offset and its first two X-derivatives, (n_t, P, 3) [m].
      tendon_active: 1 where the tendon runs through a point; friction_mu: mubar per tendon.
      friction_Q: cumulative quadrature, wrap(X_p) = sum_j Q[p, j] phi(X_j), (P, P).
      gravity: in arm_base [m/s^2]; marker_*: one Magnus sub-step from a point to each marker.
      rest_tendon_lengths, rest_theta: L_c and the friction-aware tendon integral theta of the
        straight arm (q = 0) [m], the origin of the actuation coordinates.
    """
    config: ArmConfig
    n: int
    X: np.ndarray
    w: np.ndarray
    B: np.ndarray
    Bd: np.ndarray
    h: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    mass_diag: np.ndarray
    lumped_mass: np.ndarray
    stiff_diag: np.ndarray
    visc_diag: np.ndarray
    K: np.ndarray
    D: np.ndarray
    tendon_d: np.ndarray
    tendon_dp: np.ndarray
    tendon_dpp: np.ndarray
    tendon_active: np.ndarray
    friction_mu: np.ndarray
    friction_Q: np.ndarray
    gravity: np.ndarray
    marker_X: np.ndarray
    marker_point: np.ndarray
    marker_h: np.ndarray
    marker_B1: np.ndarray
    marker_B2: np.ndarray
    coordinate_labels: tuple
    kernel_args: tuple = field(repr=False)
    rest_tendon_lengths: np.ndarray | None = None
    rest_theta: np.ndarray | None = None

    @property
    def n_tendons(self) -> int:
        return self.tendon_d.shape[0]

    @property
    def tendon_names(self) -> tuple:
        return tuple(t.name for t in self.config.tendons)

    @property
    def length(self) -> float:
        return self.config.geometry.length


class ArmData:
    """Scratch workspace for one model: every kernel output lives here (see kernels.evaluate)."""

    def __init__(self, model: ArmModel):
        P, n, nt, nm = model.X.size, model.n, model.n_tendons, model.marker_X.size
        self.xi = np.zeros((P, 6))
        self.R = np.zeros((P, 3, 3))
        self.p = np.zeros((P, 3))
        self.J = np.zeros((P, 6, n))
        self.eta = np.zeros((P, 6))
        self.psi = np.zeros((P, 6))
        self.Jd = np.zeros((P, 6, n))
        self.marker_R = np.zeros((nm, 3, 3))
        self.marker_p = np.zeros((nm, 3))
        self.marker_J = np.zeros((nm, 6, n))
        self.M = np.zeros((n, n))
        self.C = np.zeros((n, n))
        self.Cqd = np.zeros(n)
        self.Fg = np.zeros(n)
        self.Fel = np.zeros(n)
        self.Kt = np.zeros((n, n))
        self.A = np.zeros((n, nt))
        self.A0 = np.zeros((n, nt))
        self.Lc = np.zeros(nt)
        self.theta = np.zeros(nt)
        self.wrap = np.zeros((nt, P))
        self.phi = np.zeros((nt, P))
        self.energies = np.zeros(3)  # kinetic, elastic, gravitational [J]
        # per Magnus step: its exponent Omega, Z = dOmega/dq and S = T(Omega) Z, kept for the
        # analytic derivatives (kernels.static_tangent); and the kernels' scratch
        self.Om = np.zeros((P - 1, 6))
        self.Z = np.zeros((P - 1, 6, n))
        self.S = np.zeros((P - 1, 6, n))
        self.work = kernels.new_work(P, n)
        self.kernel_args = (self.xi, self.R, self.p, self.J, self.eta, self.psi, self.Jd,
                            self.marker_R, self.marker_p, self.marker_J, self.M, self.C, self.Cqd,
                            self.Fg, self.Fel, self.Kt,
                            self.A, self.A0, self.Lc, self.theta, self.wrap, self.phi, self.energies,
                            self.Om, self.Z, self.S, self.work)


# ---------------------------------------------------------------------------------------------------

def _division_bounds(disc: Discretisation):
    ends = disc.division_ends
    starts = (0.0,) + tuple(ends[:-1])
    return list(zip(starts, ends))


def _division_of(disc: Discretisation, X: float) -> int:
    for i, (a, b) in enumerate(_division_bounds(disc)):
        if X < b or i == len(disc.division_ends) - 1:
            return i
    raise AssertionError("unreachable")


def _coordinate_layout(disc: Discretisation):
    """(division, mode row, Legendre order) per coordinate, and the column offset per division."""
    labels, offsets = [], []
    modes = [r for r, on in enumerate(disc.modes) if on]
    for d, order in enumerate(disc.legendre_order):
        offsets.append(len(labels))
        for r in modes:
            for j in range(order + 1):
                labels.append((d, r, j))
    return labels, offsets


def _legendre(s: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Legendre polynomials P_0..P_order at ``s`` in [-1, 1] and their derivatives d/ds, by
    Bonnet's recurrence (one pass for every order, where evaluating each series apart costs a
    polynomial derivative per order and point)."""
    P = np.empty(order + 1)
    dP = np.empty(order + 1)
    P[0], dP[0] = 1.0, 0.0
    if order >= 1:
        P[1], dP[1] = s, 1.0
    for j in range(1, order):
        P[j + 1] = ((2 * j + 1) * s * P[j] - j * P[j - 1]) / (j + 1)
        dP[j + 1] = dP[j - 1] + (2 * j + 1) * P[j]
    return P, dP


def _basis_at(disc: Discretisation, n: int, X: float, division: int | None = None):
    """Strain basis B (6, n) and its derivative along the arm Bd at arc length X [m]: coordinate
    (division, strain row r, order j) is the Legendre polynomial P_j in row r only, so a column has
    one non-zero row at most (the kernels take that row alone)."""
    labels, _ = _coordinate_layout(disc)
    d = _division_of(disc, X) if division is None else division
    a, b = _division_bounds(disc)[d]
    L = b - a
    P, dP = _legendre(2.0 * (X - a) / L - 1.0, disc.legendre_order[d])
    B = np.zeros((6, n))
    Bd = np.zeros((6, n))
    for col, (dd, r, j) in enumerate(labels):
        if dd != d:
            continue
        scale = 1.0 / L if r < 3 else 1.0
        B[r, col] = scale * P[j]
        Bd[r, col] = scale * dP[j] * 2.0 / L
    return B, Bd


def _substep(disc: Discretisation, n: int, X0: float, X1: float):
    """Magnus sub-step data (h, B1, B2) from X0 to X1 (both in one division); B1 and B2 read-only,
    as the model's (the kernels are compiled for those)."""
    h = X1 - X0
    d = _division_of(disc, 0.5 * (X0 + X1)) if h > 0 else _division_of(disc, X0)
    B1, _ = _basis_at(disc, n, X0 + _ZANNA_OFFSETS[0] * h, d)
    B2, _ = _basis_at(disc, n, X0 + _ZANNA_OFFSETS[1] * h, d)
    return h, _frozen(B1), _frozen(B2)


def _points(disc: Discretisation):
    """Point abscissae, weights, owning division (-1 at division ends)."""
    X, w, div = [0.0], [0.0], [-1]
    for d, ((a, b), m) in enumerate(zip(_division_bounds(disc), disc.gauss_points)):
        s, ws = npleg.leggauss(m)
        X += list(a + 0.5 * (s + 1.0) * (b - a))
        w += list(0.5 * ws * (b - a))
        div += [d] * m
        X.append(b)
        w.append(0.0)
        div.append(-1)
    return np.array(X), np.array(w), np.array(div)


def _friction_quadrature(disc: Discretisation, X, div):
    """Q with wrap(X_p) = int_0^{X_p} phi = sum_j Q[p, j] phi(X_j), exact for phi polynomial of degree
    < gauss points in each division (Lagrange interpolation on the Gauss nodes)."""
    P = X.size
    Q = np.zeros((P, P))
    carry = np.zeros(P)  # full-division weights of the divisions already passed
    for d, ((a, b), m) in enumerate(zip(_division_bounds(disc), disc.gauss_points)):
        idx = np.flatnonzero(div == d)
        s, ws = npleg.leggauss(m)
        V = npleg.legvander(s, m - 1)             # V[j, i] = P_i(s_j)
        Cinv = np.linalg.inv(V)                   # Lagrange basis coefficients, column k -> l_k
        integ = np.zeros((m, m))                  # integ[j, i] = int_{-1}^{s_j} P_i
        for i in range(m):
            c = np.zeros(i + 1)
            c[i] = 1.0
            integ[:, i] = npleg.legval(s, npleg.legint(c, lbnd=-1.0))
        local = 0.5 * (b - a) * integ @ Cinv     # local[j, k] = int_a^{X_j} l_k
        for jj, pj in enumerate(idx):
            Q[pj] = carry
            Q[pj, idx] = local[jj]
        end_point = idx[-1] + 1
        carry = carry.copy()
        carry[idx] = 0.5 * ws * (b - a)
        Q[end_point] = carry
    return Q


def _tendon_arrays(config: ArmConfig, X, w):
    """The tendons' offsets d, dp, dpp (n_t, P, 3) [m] and where they run (n_t, P) (one
    implementation with the dynamic estimate's routing states: :mod:`.routing`)."""
    g = config.geometry
    P, nt = X.size, len(config.tendons)
    d, dp, dpp = np.zeros((nt, P, 3)), np.zeros((nt, P, 3)), np.zeros((nt, P, 3))
    ends = tendon_ends(config)
    active = _frozen((w[None, :] > 0) & (X[None, :] < ends[:, None]))
    routing_arrays(X, active, g.base_radius, (g.tip_radius - g.base_radius) / g.length, routing_of(config),
                   ends, d, dp, dpp)
    return d, dp, dpp, active


class _Grid(NamedTuple):
    """What a discretisation fixes of a model, whatever its material and tendons (read-only arrays,
    shared by the models built on it): coordinate labels and count, points (X, w, division), the
    basis and its derivative at the points, the Magnus sub-steps, the friction quadrature, each
    point's columns [col_lo, col_hi), and each marker's point and sub-step from it."""
    labels: tuple
    n: int
    X: np.ndarray
    w: np.ndarray
    div: np.ndarray
    B: np.ndarray
    Bd: np.ndarray
    h: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    Q: np.ndarray
    col_lo: np.ndarray
    col_hi: np.ndarray
    marker_point: np.ndarray
    marker_h: np.ndarray
    marker_B1: np.ndarray
    marker_B2: np.ndarray


@functools.lru_cache(maxsize=64)
def _grid(disc: Discretisation, length: float, marker_positions: tuple) -> _Grid:
    """The :class:`_Grid` of ``disc`` for an arm of ``length`` [m] with markers at
    ``marker_positions`` [m]; cached, as the fits and campaigns build many models on one
    discretisation and its Legendre and quadrature work is most of a model's construction."""
    labels, _ = _coordinate_layout(disc)
    n = len(labels)
    X, w, div = _points(disc)
    P = X.size
    B = np.zeros((P, 6, n))
    Bd = np.zeros((P, 6, n))
    for i in range(P):
        if div[i] >= 0:
            B[i], Bd[i] = _basis_at(disc, n, X[i], int(div[i]))
    h = np.diff(X)
    B1 = np.zeros((P - 1, 6, n))
    B2 = np.zeros((P - 1, 6, n))
    for i in range(P - 1):
        _, B1[i], B2[i] = _substep(disc, n, X[i], X[i + 1])
    Q = _friction_quadrature(disc, X, div)
    mX = np.array(marker_positions, dtype=float)
    m_point = np.array([int(np.flatnonzero(X <= x + 1e-15)[-1]) for x in mX], dtype=np.int64)
    m_h = np.zeros(mX.size)
    m_B1 = np.zeros((mX.size, 6, n))
    m_B2 = np.zeros((mX.size, 6, n))
    for m, (x, pt) in enumerate(zip(mX, m_point)):
        m_h[m], m_B1[m], m_B2[m] = _substep(disc, n, X[pt], min(x, length))
        if m_h[m] < 0:
            m_h[m] = 0.0
    # columns of each point's division (empty at division ends, whose weight is zero)
    col_lo = np.zeros(P, dtype=np.int64)
    col_hi = np.zeros(P, dtype=np.int64)
    for i in range(P):
        cols = [c for c, (d, _, _) in enumerate(labels) if d == div[i]]
        if cols:
            col_lo[i], col_hi[i] = cols[0], cols[-1] + 1
    for a in (div, col_lo, col_hi, m_point):
        a.setflags(write=False)
    return _Grid(tuple(labels), n, _frozen(X), _frozen(w), div, *(_frozen(a) for a in (B, Bd, h, B1, B2, Q)),
                 col_lo, col_hi, m_point, *(_frozen(a) for a in (m_h, m_B1, m_B2)))


def build_model(config: ArmConfig | None = None) -> ArmModel:
    """Discretise the arm described by ``config`` (default: the package's ``arm.yaml``; for
    overrides use ``build_model(load_arm_config(overrides={...}))``)."""
    if config is None:
        config = load_arm_config()
    grid = _grid(config.discretisation, float(config.geometry.length),
                 tuple(float(x) for x in config.marker_positions))
    labels, n, X, w = grid.labels, grid.n, grid.X, grid.w

    g, mat = config.geometry, config.material
    r = g.base_radius + (g.tip_radius - g.base_radius) * X / g.length
    area, inertia = np.pi * r ** 2, np.pi * r ** 4 / 4.0
    polar = 2.0 * inertia
    E = mat.youngs_modulus
    G = E / (2.0 * (1.0 + mat.poisson_ratio))
    mass_diag = mat.density * np.stack([polar, inertia, inertia, area, area, area], axis=1)
    lumped_mass = w[:, None] * mass_diag
    lumped_mass[-1, 3:] += config.tip_mass      # X[-1] is the tip (a division end)
    stiff_diag = np.stack([G * polar, E * inertia, E * inertia, E * area, G * area, G * area], axis=1)
    visc_diag = mat.viscosity * np.stack([polar, 3 * inertia, 3 * inertia, 3 * area, area, area], axis=1)
    K = np.einsum("p,pra,pr,prb->ab", w, grid.B, stiff_diag, grid.B)
    D = np.einsum("p,pra,pr,prb->ab", w, grid.B, visc_diag, grid.B)

    t_d, t_dp, t_dpp, active = _tendon_arrays(config, X, w)
    mu = np.array([t.friction for t in config.tendons])
    mX = np.array(config.marker_positions, dtype=float)
    arrays = dict(X=X, w=w, B=grid.B, Bd=grid.Bd, h=grid.h, B1=grid.B1, B2=grid.B2, mass_diag=mass_diag,
                  lumped_mass=lumped_mass, stiff_diag=stiff_diag, visc_diag=visc_diag, K=K, D=D, tendon_d=t_d,
                  tendon_dp=t_dp, tendon_dpp=t_dpp, tendon_active=active, friction_mu=mu,
                  friction_Q=grid.Q, gravity=np.array(config.gravity, dtype=float), marker_X=mX,
                  marker_h=grid.marker_h, marker_B1=grid.marker_B1, marker_B2=grid.marker_B2)
    arrays = {k: _frozen(v) for k, v in arrays.items()}
    m_point, col_lo, col_hi = grid.marker_point, grid.col_lo, grid.col_hi
    neo = config.material.axial_law == "neo_hookean"
    a = arrays
    kernel_args = (a["w"], a["B"], a["Bd"], a["h"], a["B1"], a["B2"], _frozen(XI_STAR),
                   a["lumped_mass"], a["stiff_diag"], neo, _frozen(R_BASE), a["gravity"], a["tendon_d"],
                   a["tendon_dp"], a["tendon_dpp"], a["tendon_active"], a["friction_mu"],
                   a["friction_Q"], float(config.friction_smoothing), col_lo, col_hi, m_point, a["marker_h"],
                   a["marker_B1"], a["marker_B2"])
    mode_names = STRAIN_MODES
    coordinate_labels = tuple(f"div{d + 1}.{mode_names[r]}.P{j}" for d, r, j in labels)
    model = ArmModel(config=config, n=n, marker_point=m_point, coordinate_labels=coordinate_labels,
                     kernel_args=kernel_args, **arrays)
    rest = ArmData(model)
    zero = np.zeros(n)
    if not kernels.evaluate(*kernel_args, zero, zero, 1, False, *rest.kernel_args):
        raise ValueError("the straight arm is outside the model's domain (degenerate tendon routing)")
    return replace(model, rest_tendon_lengths=_frozen(rest.Lc), rest_theta=_frozen(rest.theta))
