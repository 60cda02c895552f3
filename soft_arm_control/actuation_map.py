"""The paper's approximation of the friction-aware actuation coordinates by measured tendon lengths.

With friction, theta_a (the friction-weighted tendon integral) depends on the whole configuration q,
which cannot be measured. The paper observes that it depends mainly on the tendon lengths and uses
``thetabar_a(L_c)``. Here thetabar_a is a polynomial in the measured tendon shortenings
s = L_c(0) - L_c [m], fitted by least squares to static equilibria of the model over a grid of
tensions and checked on random equilibria that the fit did not see.

The inner loop regulates the shortenings themselves unless asked for this map
(``control.inner_loop.coordinates``): thetabar_a is not monotone in s. Its slope dthetabar_a/ds has a
symmetric part with a negative eigenvalue (:attr:`ActuationMap.slope_margin`), so tensions
proportional to thetabar_a(s_d) - thetabar_a(s) are no gradient of a potential in the shortenings:
they can put energy into a cycle of the arm, and the loop can settle where thetabar_a(s) =
thetabar_a(s_d) with s != s_d (docs/decisions/0021).
"""
from __future__ import annotations

import hashlib
import itertools
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from soft_arm_model import ArmData, ArmModel, EquilibriumError, evaluate, solve_equilibrium
from soft_arm_model.dynamics import STATICS

SCALE = 0.01  # m: shortenings are fitted in centimetres, which keeps the normal equations well scaled


def _monomials(n_vars: int, degree: int) -> np.ndarray:
    """Exponent rows of every monomial of total degree <= ``degree`` in ``n_vars`` variables."""
    rows = [e for e in itertools.product(range(degree + 1), repeat=n_vars) if sum(e) <= degree]
    return np.array(sorted(rows, key=lambda e: (sum(e), tuple(-x for x in e))), dtype=np.int64)


@dataclass(frozen=True, eq=False)
class ActuationMap:
    """thetabar_a(s): actuation coordinates [m] of every tendon from the shortenings s [m] of all tendons.

    ``exponents`` (F, n_t) and ``coef`` (n_t, F) define the polynomial in s / SCALE. ``rms_error`` and
    ``max_error`` [m] are the validation errors against the model's exact theta_a; ``samples`` counts
    the fitted equilibria; ``slope_margin`` is the smallest eigenvalue of the symmetric part of
    dthetabar_a/ds over the validation equilibria (> 0: monotone there; the identity's is 1). An
    identity map (the shortenings themselves) has ``coef`` None.
    """
    exponents: np.ndarray | None
    coef: np.ndarray | None
    rms_error: float
    max_error: float
    samples: int
    slope_margin: float = 1.0

    @classmethod
    def identity(cls) -> "ActuationMap":
        """theta_a = s: the shortenings, the exact actuation coordinates without friction."""
        return cls(None, None, 0.0, 0.0, 0)

    def report(self) -> dict:
        """What an inner loop on these coordinates regulates, for reports: the shortenings, or the
        fitted thetabar_a with its validation errors [m] and slope margin."""
        if self.coef is None:
            return {"coordinates": "shortenings"}
        return {"coordinates": "actuation_map", "rms_error": self.rms_error, "max_error": self.max_error,
                "slope_margin": self.slope_margin}

    def describe(self) -> str:
        """:meth:`report` in one line."""
        if self.coef is None:
            return "the tendon shortenings"
        return (f"thetabar_a(L_c): validation RMS {self.rms_error * 1e3:.2f} mm, max "
                f"{self.max_error * 1e3:.2f} mm, slope margin {self.slope_margin:.2f}")

    def __call__(self, s) -> np.ndarray:
        s = np.asarray(s, dtype=float)
        if self.coef is None:
            return s.copy()
        out = np.empty(self.exponents.shape[0])
        _features(s / SCALE, self.exponents, out)
        return self.coef @ out

    def batch(self, S) -> np.ndarray:
        """thetabar_a of every row of S (N, n_t) [m]."""
        S = np.asarray(S, dtype=float)
        if self.coef is None:
            return S.copy()
        X = np.empty((S.shape[0], self.exponents.shape[0]))
        for row, x in zip(X, S / SCALE):
            _features(x, self.exponents, row)
        return X @ self.coef.T

    def jacobian(self, s) -> np.ndarray:
        """d thetabar_a / ds (n_t, n_t) at s."""
        s = np.asarray(s, dtype=float)
        if self.coef is None:
            return np.eye(s.size)
        out = np.empty((self.exponents.shape[0], s.size))
        _feature_jacobian(s / SCALE, self.exponents, out)
        return (self.coef @ out) / SCALE


@njit(cache=True, nogil=True)
def _features(x, exps, out):
    """Monomials prod_j x_j^e_fj, one per row f of ``exps``."""
    for f in range(exps.shape[0]):
        acc = 1.0
        for j in range(x.shape[0]):
            for _ in range(exps[f, j]):
                acc *= x[j]
        out[f] = acc


@njit(cache=True, nogil=True)
def _feature_jacobian(x, exps, out):
    """d monomial_f / d x_j into out[f, j]."""
    for f in range(exps.shape[0]):
        for j in range(x.shape[0]):
            e = exps[f, j]
            if e == 0:
                out[f, j] = 0.0
                continue
            acc = float(e)
            for i in range(x.shape[0]):
                for _ in range(exps[f, i] - (1 if i == j else 0)):
                    acc *= x[i]
            out[f, j] = acc


def _sample(model: ArmModel, tensions) -> tuple[np.ndarray, np.ndarray]:
    """(shortenings, friction-aware theta_a) at the equilibria of ``tensions`` that converge."""
    data = ArmData(model)
    s, th = [], []
    for u in tensions:
        try:
            eq = solve_equilibrium(model, np.asarray(u, dtype=float), data=data)
        except EquilibriumError:
            continue
        evaluate(model, data, eq.q, level=STATICS)
        s.append(model.rest_tendon_lengths - data.Lc)
        th.append(model.rest_theta - data.theta)
    return np.array(s), np.array(th)


def fit_actuation_map(model: ArmModel, levels, degree: int = 2, validation_samples: int = 40,
                      seed: int = 0) -> ActuationMap:
    """Fit thetabar_a on the equilibria of every combination of tensions in ``levels`` [N].

    The validation set is ``validation_samples`` equilibria at uniformly random tensions in
    [min(levels), max(levels)] (seeded). Raises ValueError when too few equilibria converge.
    """
    levels = [float(v) for v in levels]
    n_t = model.n_tendons
    exps = _monomials(n_t, degree)
    s, th = _sample(model, itertools.product(levels, repeat=n_t))
    if len(s) < 2 * exps.shape[0]:
        raise ValueError(f"only {len(s)} equilibria converged; a degree-{degree} fit needs "
                         f"at least {2 * exps.shape[0]} (add tension levels or lower the degree)")
    X = np.empty((len(s), exps.shape[0]))
    for row, x in zip(X, s / SCALE):
        _features(x, exps, row)
    coef, *_ = np.linalg.lstsq(X, th, rcond=None)
    rng = np.random.default_rng(seed)
    s_v, th_v = _sample(model, rng.uniform(min(levels), max(levels), (validation_samples, n_t)))
    fit = ActuationMap(exps, coef.T, 0.0, 0.0, len(s))
    err = np.array([fit(x) - y for x, y in zip(s_v, th_v)])
    return ActuationMap(exps, coef.T, float(np.sqrt(np.mean(err ** 2))), float(np.abs(err).max()),
                        len(s), slope_margin(fit, s_v))


def slope_margin(fit: ActuationMap, shortenings) -> float:
    """The smallest eigenvalue of the symmetric part of dthetabar_a/ds over ``shortenings`` (N, n_t)
    [m]: positive where thetabar_a is monotone, the condition for tensions proportional to its error
    to be the gradient of a convex potential."""
    return float(min(np.linalg.eigvalsh(0.5 * (J + J.T)).min()
                     for J in (fit.jacobian(s) for s in shortenings)))


def actuation_map_for(model: ArmModel, control) -> ActuationMap:
    """The coordinates the controller configuration (``control.yaml``) has the inner loop regulate:
    the fitted thetabar_a when it asks for the actuation map with friction, the shortenings (the
    identity) otherwise. A fit takes one to two seconds and is the same for the same arm, settings
    and code, so it is kept (:func:`cached_fit`): every node and run of one arm fits it once."""
    if not (control.friction and control.inner_coordinates == "actuation_map"):
        return ActuationMap.identity()
    return cached_fit(model, tuple(control.map_levels), control.map_degree, control.map_validation_samples)


_FITTED: dict = {}       # digest -> ActuationMap, this process's


def cache_dir() -> Path:
    """Where fitted maps are kept across processes: ``$SOFT_ARM_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/soft_arm`` (``~/.cache/soft_arm``)."""
    base = os.environ.get("SOFT_ARM_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "soft_arm")
    return Path(base) / "actuation_maps"


def _digest(model: ArmModel, levels, degree: int, samples: int) -> str:
    """What a fit depends on: the arm's description, the fit's settings and the code that computes
    the equilibria and the features (a changed model or fit gives another digest, never a stale map)."""
    code = hashlib.sha256()
    modules = [m for name, m in sorted(sys.modules.items()) if name.startswith("soft_arm_model.")]
    for module in [sys.modules[__name__]] + modules:
        path = getattr(module, "__file__", None)
        if path and path.endswith(".py"):
            code.update(Path(path).read_bytes())
    key = repr((model.config, tuple(float(v) for v in levels), int(degree), int(samples), code.hexdigest()))
    return hashlib.sha256(key.encode()).hexdigest()[:32]


def cached_fit(model: ArmModel, levels, degree: int, samples: int) -> ActuationMap:
    """:func:`fit_actuation_map`, kept in this process and in :func:`cache_dir` (a file written whole
    or not at all; a cache that cannot be read or written is no cache, never an error)."""
    digest = _digest(model, levels, degree, samples)
    if digest in _FITTED:
        return _FITTED[digest]
    path = cache_dir() / f"{digest}.npz"
    try:
        with np.load(path) as f:
            fit = ActuationMap(f["exponents"], f["coef"], float(f["rms_error"]), float(f["max_error"]),
                               int(f["samples"]), float(f["slope_margin"]))
    except (OSError, KeyError, ValueError):
        fit = fit_actuation_map(model, levels, degree, samples)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_suffix(f".{os.getpid()}.partial.npz")
            np.savez(partial, exponents=fit.exponents, coef=fit.coef, rms_error=fit.rms_error,
                     max_error=fit.max_error, samples=fit.samples, slope_margin=fit.slope_margin)
            os.replace(partial, path)
        except OSError:
            pass
    _FITTED[digest] = fit
    return fit
