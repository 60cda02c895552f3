"""Independent reference solutions for validating the Variable-Strain model.

Nothing here uses the model's kernels: each reference is built from the continuum equations with
scipy, so the test suite and the benchmarks can compare the discretised model against it.

- :func:`euler_bernoulli_tip_deflection`: small-deflection tip sag of a tapered cantilever under its
  own weight (double quadrature of M(x) / EI(x)).
- :func:`kirchhoff_cantilever_tip`: large deflection of the same cantilever, planar inextensible
  Kirchhoff rod, solved as a boundary-value problem.
- :func:`tendon_load_tip`: the exact solution for tendon loads without gravity: at every section the
  body carries the tendon stress, ``Sigma (xi - xi*) + sum_k u_k Phi_k(xi, X) = 0`` (solved pointwise),
  and the strain is integrated to the tip.

Geometry, material and tendon routing are read from an :class:`~soft_arm_model.config.ArmConfig`.
Cantilevers are clamped horizontally: results are (along the clamp axis, along gravity) [m], the
deflection negative.
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import quad, solve_bvp, solve_ivp
from scipy.optimize import fsolve

from .config import ArmConfig

XI_STAR = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])


def _radius(cfg: ArmConfig, X):
    g = cfg.geometry
    return g.base_radius + (g.tip_radius - g.base_radius) * X / g.length


def euler_bernoulli_tip_deflection(cfg: ArmConfig, gravity: float = 9.81) -> float:
    """Tip deflection [m] (positive, along gravity) of the cone as a horizontal cantilever."""
    L, rho, E = cfg.geometry.length, cfg.material.density, cfg.material.youngs_modulus

    def moment(x):  # bending moment of the distal weight about the section at x
        return quad(lambda s: rho * gravity * np.pi * _radius(cfg, s) ** 2 * (s - x), x, L,
                    epsabs=0, epsrel=1e-13)[0]

    return quad(lambda x: (L - x) * moment(x) / (E * np.pi * _radius(cfg, x) ** 4 / 4), 0, L,
                epsabs=0, epsrel=1e-12)[0]


def kirchhoff_cantilever_tip(cfg: ArmConfig, gravity: float = 9.81) -> np.ndarray:
    """Tip (along the clamp axis, along gravity) [m] of the planar inextensible Kirchhoff cone under
    its own weight: theta' = m / EI, m' = W(s) cos(theta), theta(0) = 0, m(L) = 0 (continuation in
    gravity); raises RuntimeError if solve_bvp fails."""
    g, mat = cfg.geometry, cfg.material
    L, E, rho = g.length, mat.youngs_modulus, mat.density
    slope = (g.tip_radius - g.base_radius) / L

    def rhs(s, y, scale):
        weight = rho * gravity * np.pi * (_radius(cfg, L) ** 3 - _radius(cfg, s) ** 3) / (3 * slope)
        return np.vstack([y[1] / (E * np.pi * _radius(cfg, s) ** 4 / 4),
                          scale * weight * np.cos(y[0]), np.cos(y[0]), np.sin(y[0])])

    s = np.linspace(0, L, 400)
    y = np.zeros((4, s.size))
    y[2] = s
    for scale in np.linspace(0.1, 1.0, 10):
        sol = solve_bvp(lambda s, y, c=scale: rhs(s, y, c),
                        lambda ya, yb: np.array([ya[0], yb[1], ya[2], ya[3]]), s, y, tol=1e-10,
                        max_nodes=200000)
        if not sol.success:
            raise RuntimeError(f"Kirchhoff reference: {sol.message}")
        s, y = sol.x, sol.y
    return np.array([y[2, -1], y[3, -1]])


def _tendon_offsets(cfg: ArmConfig, tendon, X):
    """Offset d and dd/dX in the section frame (README, Conventions: d = rho (0, sin th, cos th))."""
    g = cfg.geometry
    rp = (g.tip_radius - g.base_radius) / g.length
    th_p = (tendon.end_angle - tendon.start_angle) / tendon.end
    th = tendon.start_angle + th_p * X
    rho, rho_p = tendon.offset_fraction * _radius(cfg, X), tendon.offset_fraction * rp
    d = np.array([0.0, rho * np.sin(th), rho * np.cos(th)])
    dp = np.array([0.0, rho_p * np.sin(th) + rho * th_p * np.cos(th),
                   rho_p * np.cos(th) - rho * th_p * np.sin(th)])
    return d, dp


def _cross(a, b) -> np.ndarray:
    """a x b of two 3-vectors (np.cross costs ten times this on one pair: the reference's
    strain solve calls it half a million times)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def tendon_load_tip(cfg: ArmConfig, u, base_rotation: np.ndarray) -> np.ndarray:
    """Tip position [m] of the frictionless arm under tendon tensions u [N] without gravity.

    The section frame at the clamp is ``base_rotation`` (columns: section axes in the base frame).
    Only the enabled strain modes deform; the others are constraints.
    """
    mat = cfg.material
    L = cfg.geometry.length
    enabled = [i for i, on in enumerate(cfg.discretisation.modes) if on]
    E, G = mat.youngs_modulus, mat.youngs_modulus / (2 * (1 + mat.poisson_ratio))

    def stress(xi, X):
        r = _radius(cfg, X)
        area, inertia = np.pi * r ** 2, np.pi * r ** 4 / 4
        s = np.array([G * 2 * inertia, E * inertia, E * inertia, E * area, G * area, G * area]) \
            * (xi - XI_STAR)
        if mat.axial_law == "neo_hookean":
            s[3] = E * area / 3 * (xi[3] - xi[3] ** -2)
        for tendon, uk in zip(cfg.tendons, u):
            if X < tendon.end and uk != 0:
                d, dp = _tendon_offsets(cfg, tendon, X)
                tau = _cross(xi[:3], d) + xi[3:] + dp
                t = tau / np.sqrt(tau @ tau)
                s[:3] += uk * _cross(d, t)
                s[3:] += uk * t
        return s

    last = {"xi": XI_STAR.copy()}

    def strain(X):
        def f(z):
            xi = XI_STAR.copy()
            xi[enabled] = z
            return stress(xi, X)[enabled]
        z, info, _, msg = fsolve(f, last["xi"][enabled], xtol=1e-12, full_output=True)
        if np.abs(info["fvec"]).max() > 1e-11:
            raise RuntimeError(f"tendon-load reference at X = {X}: {msg}")
        last["xi"] = XI_STAR.copy()
        last["xi"][enabled] = z
        return last["xi"]

    def rhs(X, y):
        R = y[:9].reshape(3, 3)
        xi = strain(X)
        k = xi[:3]
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.concatenate([(R @ K).ravel(), R @ xi[3:]])

    y = np.concatenate([np.asarray(base_rotation, dtype=float).ravel(), np.zeros(3)])
    X0 = 0.0
    for X1 in sorted({t.end for t in cfg.tendons} | {L}):  # the strain jumps at tendon ends
        y = solve_ivp(rhs, (X0, X1), y, method="DOP853", rtol=1e-11, atol=1e-13).y[:, -1]
        X0 = X1
    return y[9:]
