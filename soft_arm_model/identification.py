"""Static identification of the arm from quasi-static samples (ROS-free).

A sample is what a rig records once the arm has settled under constant tensions: the applied
tensions u [N], the encoder shortenings s [m] (their zero unknown: the encoders are zeroed wherever
the arm was at power-up) and the marker positions [m] in the motion-capture frame. The fit is a
weighted nonlinear least squares (``scipy.optimize.least_squares``) on the project's own model:

- arm parameters: Young's modulus and density (as logs of their ratio to the starting arm), the
  mass at the tip [kg] (a payload, a marker's clamp: its weight bends the arm unlike the body's), and
  per tendon the friction coefficient, the offset fraction and the start and end angles [rad];
- nuisance parameters: the encoder zero of each tendon [m] and the rigid transform from the mocap
  frame to ``arm_base`` (a rotation vector [rad] and a translation [m]).

Residuals: the markers predicted at the equilibrium of each sample against the registered
measurement, over ``marker_sigma``; the shortenings against the measured ones minus the encoder
zero, over ``shortening_sigma``; a prior on each tendon geometry parameter (its starting value, with
:data:`PRIOR_SIGMA`). Sensitivities of the equilibria come from the implicit function theorem:
``dq/dp = -(dR/dq)^-1 dR/dp``, with dR/dp by central differences of the static residual of models
built at p +- h (no equilibrium is re-solved per parameter).

A gauge: the arm is axisymmetric and gravity is along its axis, so turning every tendon by the same
angle about the axis is indistinguishable from turning the mocap frame. The fit holds the mean
start angle at its starting value (arm_base's x axis is where the drawing puts it, relative to the
tendons at the base) and gives the common turn to the mocap registration.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .config import ArmConfig
from .dynamics import STATICS, OutOfDomainError, evaluate
from .model import ArmData, build_model
from .statics import EquilibriumError, solve_equilibrium

TENDON_GROUPS = ("friction", "offset_fraction", "start_angle", "end_angle")
# prior standard deviations of the tendon geometry around the starting arm: casting tolerances
PRIOR_SIGMA = {"offset_fraction": 0.05, "start_angle": np.radians(3.0), "end_angle": np.radians(3.0)}
GAUGE_SIGMA = 1e-6          # rad: the mean start angle is held (see the module's docstring)
OFFSET_BOUNDS = (0.05, 0.95)  # the offset fractions the fit may take: inside the body
MIN_PULL = 0.5              # N above the smallest tension a tendon must see to be identifiable
_STEP = 1e-6                # central-difference step of dR/dp (log ratios, rad, fractions)


class IdentificationError(ValueError):
    """The data cannot determine the parameters (too few samples, a tendon never pulled, ...)."""


@dataclass(frozen=True)
class StaticSample:
    """The arm at rest: applied tensions (n_t,) [N], encoder shortenings (n_t,) [m] (unknown zero)
    and marker positions (n_m, 3) [m] in the mocap frame."""
    tension: np.ndarray
    shortening: np.ndarray
    markers: np.ndarray


@dataclass(frozen=True)
class Registration:
    """The rigid transform from the mocap frame to ``arm_base``: p_arm = rotation p_mocap + translation."""
    rotation: np.ndarray
    translation: np.ndarray

    def to_arm(self, points) -> np.ndarray:
        return np.asarray(points, dtype=float) @ self.rotation.T + self.translation

    @property
    def angle(self) -> float:
        """Its rotation angle [rad]."""
        return float(Rotation.from_matrix(self.rotation).magnitude())


@dataclass(frozen=True)
class Estimate:
    """One identified value with its standard error (from the Jacobian at the optimum: the noise's
    share), in ``unit``; ``basis_shift``: how far the same data fitted on another strain basis
    moves it (:func:`with_basis_shift`: the model's share, which the standard error does not see)."""
    value: float
    standard_error: float
    unit: str
    basis_shift: float = 0.0

    @property
    def uncertainty(self) -> float:
        """Both shares together, ``hypot(standard_error, basis_shift)``."""
        return float(np.hypot(self.standard_error, self.basis_shift))


@dataclass(frozen=True)
class StaticFit:
    """The identified arm, encoder zeros (n_t,) [m], mocap registration, every estimate by name,
    residual RMS per marker [m] and per tendon shortening [m], the number of samples and of
    least-squares evaluations, and the weighted sum of squared residuals at the optimum (priors
    included; fits of the same samples compare by it)."""
    arm: ArmConfig
    encoder_zero: np.ndarray
    registration: Registration
    estimates: dict
    marker_rms: np.ndarray
    shortening_rms: np.ndarray
    samples: int
    evaluations: int
    cost: float


_TENDONS = 3                # index of the first tendon parameter in the parameter vector


class _Layout:
    """The parameter vector: [log E ratio, log density ratio, tip mass [kg], per tendon (friction,
    offset, start angle, end angle) grouped by kind, encoder zeros (n_t), rotation vector (3),
    translation (3)]."""

    def __init__(self, arm: ArmConfig):
        self.arm0 = arm
        n_t = len(arm.tendons)
        self.n_t = n_t
        self.n_model = _TENDONS + 4 * n_t
        self.size = self.n_model + n_t + 6
        self.names = (["youngs_modulus", "density", "tip_mass"]
                      + [f"{g}[{t.name}]" for g in TENDON_GROUPS for t in arm.tendons]
                      + [f"encoder_zero[{t.name}]" for t in arm.tendons]
                      + [f"mocap_rotation[{a}]" for a in "xyz"] + [f"mocap_translation[{a}]" for a in "xyz"])

    def initial(self, registration: Registration | None) -> np.ndarray:
        a = self.arm0
        p = np.zeros(self.size)
        p[2] = a.tip_mass
        p[_TENDONS:self.n_model] = np.concatenate([[getattr(t, g) for t in a.tendons] for g in TENDON_GROUPS])
        if registration is not None:
            p[-6:-3] = Rotation.from_matrix(registration.rotation).as_rotvec()
            p[-3:] = registration.translation
        return p

    def arm(self, p) -> ArmConfig:
        a, n_t = self.arm0, self.n_t
        groups = p[_TENDONS:self.n_model].reshape(4, n_t)
        material = replace(a.material, youngs_modulus=a.material.youngs_modulus * np.exp(p[0]),
                           density=a.material.density * np.exp(p[1]))
        tendons = tuple(replace(t, **{g: float(groups[i, k]) for i, g in enumerate(TENDON_GROUPS)})
                        for k, t in enumerate(a.tendons))
        return replace(a, material=material, tendons=tendons, tip_mass=float(p[2]))

    def encoder_zero(self, p) -> np.ndarray:
        return p[self.n_model:self.n_model + self.n_t]

    def registration(self, p) -> Registration:
        return Registration(Rotation.from_rotvec(p[-6:-3]).as_matrix(), p[-3:].copy())


class _Predictor:
    """Equilibria of the samples for a parameter vector, warm-started from the last ones."""

    def __init__(self, samples):
        self.samples = samples
        self.q = [None] * len(samples)

    def equilibria(self, model) -> list:
        out, prev = [], None
        for k, smp in enumerate(self.samples):
            starts = []
            if self.q[k] is not None:
                starts.append((self.q[k], smp.tension))
            if prev is not None:
                starts.append((prev.q, prev.u))
            starts.append((None, None))
            for q0, u0 in starts:
                try:
                    eq = solve_equilibrium(model, smp.tension, q_start=q0, u_start=u0)
                    break
                except EquilibriumError:
                    eq = None
            if eq is None:
                raise IdentificationError(f"no equilibrium of the model under sample {k + 1}'s tensions "
                                          f"{np.round(smp.tension, 3).tolist()} N")
            self.q[k] = eq.q
            out.append(eq)
            prev = eq
        return out


def observe(model, data: ArmData, q):
    """What the rig's sensors see of the model at q (``data``: a workspace of ``model``): markers
    (n_m, 3) [m] in arm_base and tendon shortenings (n_t,) [m], with their Jacobians (n_m * 3, n)
    and (n_t, n)."""
    evaluate(model, data, q, level=STATICS, markers=True)
    Jp = np.concatenate([data.marker_R[k] @ data.marker_J[k][3:] for k in range(data.marker_p.shape[0])])
    return data.marker_p.copy(), model.rest_tendon_lengths - data.Lc, Jp, -data.A0.T.copy()


def _residual_and_shortening(model, data: ArmData, q, u):
    """The static residual F_el - F_g + A u (friction on) and the tendon shortenings [m] at (q, u),
    from one evaluation (``data``: a workspace of ``model``)."""
    evaluate(model, data, q, level=STATICS)
    return data.Fel - data.Fg + data.A @ u, model.rest_tendon_lengths - data.Lc


def check_excitation(samples, n_tendons: int, names=None, min_pull: float = MIN_PULL):
    """IdentificationError saying what is missing when ``samples`` cannot determine the fit: too few
    of them, or a tendon never pulled ``min_pull`` [N] above the smallest tension it sees."""
    names = names or [f"tendon {k + 1}" for k in range(n_tendons)]
    if len(samples) < 2 * n_tendons:
        raise IdentificationError(f"{len(samples)} quasi-static samples: at least {2 * n_tendons} are "
                                  "needed (each tendon loaded and unloaded)")
    u = np.array([s.tension for s in samples])
    for k in range(n_tendons):
        if u[:, k].max() - u[:, k].min() < min_pull:
            raise IdentificationError(
                f"{names[k]} is never pulled more than {min_pull} N above its smallest tension "
                f"(range {u[:, k].min():.3f}-{u[:, k].max():.3f} N): its friction, offset and angles "
                "cannot be identified")


class StaticProblem:
    """The weighted least-squares problem of :func:`identify_static`: ``residual(p)`` and its
    ``jacobian(p)`` (implicit function theorem) over the parameter vector ``p`` (``names``)."""

    def __init__(self, arm: ArmConfig, samples, marker_sigma: float, shortening_sigma: float,
                 registration: Registration | None = None):
        self.samples = samples = list(samples)
        self.n_t = n_t = len(arm.tendons)
        check_excitation(samples, n_t, [t.name for t in arm.tendons])
        self.layout = layout = _Layout(arm)
        self.names = layout.names
        self.marker_sigma, self.shortening_sigma = float(marker_sigma), float(shortening_sigma)
        self.p0 = layout.initial(registration)
        if registration is None:          # start the translation where the hanging markers say
            model0 = build_model(arm)
            eq0 = solve_equilibrium(model0, samples[0].tension)
            self.p0[-3:] = (observe(model0, ArmData(model0), eq0.q)[0] - samples[0].markers).mean(axis=0)
        self.predictor = _Predictor(samples)
        self.prior_index = [_TENDONS + i * n_t + k for i, g in enumerate(TENDON_GROUPS) if g in PRIOR_SIGMA
                            for k in range(n_t)]
        self.prior_sigma = np.array([PRIOR_SIGMA[TENDON_GROUPS[(j - _TENDONS) // n_t]]
                                     for j in self.prior_index])
        self.start_angles = slice(_TENDONS + 2 * n_t, _TENDONS + 3 * n_t)
        self.measured_p = np.array([s.markers for s in samples])
        self.measured_s = np.array([s.shortening for s in samples])
        self._cache = {}
        self._jacobian = None

    def evaluate(self, p):
        """(residual, model, equilibria, observations) at p, cached for the last p."""
        key = p.tobytes()
        if key in self._cache:
            return self._cache[key]
        layout, p0 = self.layout, self.p0
        model = build_model(layout.arm(p))
        data = ArmData(model)
        try:
            eqs = self.predictor.equilibria(model)
            obs = [observe(model, data, eq.q) for eq in eqs]
        except OutOfDomainError as exc:
            raise IdentificationError(f"the fit left the model's domain: {exc}") from exc
        reg = layout.registration(p)
        r_p = (np.array([o[0] for o in obs]) - reg.to_arm(self.measured_p)) / self.marker_sigma
        predicted_s = np.array([o[1] for o in obs])
        r_s = (predicted_s - (self.measured_s - layout.encoder_zero(p))) / self.shortening_sigma
        r_prior = (p[self.prior_index] - p0[self.prior_index]) / self.prior_sigma
        r_gauge = [np.mean(p[self.start_angles] - p0[self.start_angles]) / GAUGE_SIGMA]
        r = np.concatenate([r_p.ravel(), r_s.ravel(), r_prior, r_gauge])
        self._cache = {key: (r, model, eqs, obs)}
        return self._cache[key]

    def residual(self, p) -> np.ndarray:
        return self.evaluate(p)[0]

    def jacobian(self, p) -> np.ndarray:
        """d residual / d p: the equilibria's sensitivities by the implicit function theorem (the
        last one kept: the fit asks again at its solution)."""
        key = p.tobytes()
        if self._jacobian is None or self._jacobian[0] != key:
            self._jacobian = (key, self._jacobian_at(p))
        return self._jacobian[1].copy()

    def _jacobian_at(self, p) -> np.ndarray:
        r, model, eqs, obs = self.evaluate(p)
        layout, samples, n_t = self.layout, self.samples, self.n_t
        ms, ss = self.marker_sigma, self.shortening_sigma
        J = np.zeros((r.size, layout.size))
        n_p = self.measured_p[0].size
        rows_p = [slice(k * n_p, (k + 1) * n_p) for k in range(len(samples))]
        off = len(samples) * n_p
        rows_s = [slice(off + k * n_t, off + (k + 1) * n_t) for k in range(len(samples))]
        n_model, n_q = layout.n_model, model.n
        dR = np.zeros((len(samples), n_q, n_model))      # d residual / d p at each sample's q
        ds = np.zeros((len(samples), n_t, n_model))       # the direct dependence of the tendon
        for j in range(n_model):                          # lengths on the geometry
            plus, minus = p.copy(), p.copy()
            plus[j] += _STEP
            minus[j] -= _STEP
            m_plus, m_minus = build_model(layout.arm(plus)), build_model(layout.arm(minus))
            d_plus, d_minus = ArmData(m_plus), ArmData(m_minus)
            for k, (eq, smp) in enumerate(zip(eqs, samples)):
                r_plus, s_plus = _residual_and_shortening(m_plus, d_plus, eq.q, smp.tension)
                r_minus, s_minus = _residual_and_shortening(m_minus, d_minus, eq.q, smp.tension)
                dR[k, :, j] = (r_plus - r_minus) / (2 * _STEP)
                ds[k, :, j] = (s_plus - s_minus) / (2 * _STEP)
        for k, eq in enumerate(eqs):
            dq = -np.linalg.solve(eq.jacobian, dR[k])
            _, _, Jp, Js = obs[k]
            J[rows_p[k], :n_model] = (Jp @ dq) / ms
            J[rows_s[k], :n_model] = (Js @ dq + ds[k]) / ss
        for k in range(len(samples)):                                   # encoder zeros
            J[rows_s[k], layout.n_model:layout.n_model + n_t] = np.eye(n_t) / ss
        for j in range(layout.size - 6, layout.size):                   # the registration
            plus, minus = p.copy(), p.copy()
            plus[j] += _STEP
            minus[j] -= _STEP
            d = (layout.registration(plus).to_arm(self.measured_p)
                 - layout.registration(minus).to_arm(self.measured_p))
            for k in range(len(samples)):
                J[rows_p[k], j] = -d[k].ravel() / (2 * _STEP) / ms
        base = len(samples) * (n_p + n_t)
        for i, j in enumerate(self.prior_index):
            J[base + i, j] = 1.0 / self.prior_sigma[i]
        J[-1, self.start_angles] = 1.0 / (n_t * GAUGE_SIGMA)
        return J


def identify_static(arm: ArmConfig, samples, marker_sigma: float = 2e-4, shortening_sigma: float = 2e-5,
                    registration: Registration | None = None, max_evaluations: int = 60,
                    start: StaticFit | None = None) -> StaticFit:
    """Fit the static parameters of ``arm`` (the starting guess and everything not identified) to
    ``samples`` (:class:`StaticSample`); ``marker_sigma`` and ``shortening_sigma`` [m]: the noise of
    one sample's markers and shortenings; ``registration``: a starting mocap registration (default:
    identity); ``start``: a fit to start from instead (e.g. on another strain basis: the priors
    stay ``arm``'s). Raises IdentificationError when the data cannot determine the fit."""
    pb = StaticProblem(arm, samples, marker_sigma, shortening_sigma, registration)
    layout, n_t, n = pb.layout, pb.n_t, len(pb.samples)
    lower, upper = np.full(layout.size, -np.inf), np.full(layout.size, np.inf)
    lower[2] = 0.0                                                  # tip mass
    lower[_TENDONS:_TENDONS + n_t] = 0.0                            # friction coefficients
    lower[_TENDONS + n_t:_TENDONS + 2 * n_t], upper[_TENDONS + n_t:_TENDONS + 2 * n_t] = OFFSET_BOUNDS
    p0 = pb.p0 if start is None else parameter_vector(layout, start)
    p0 = np.clip(p0, lower + 1e-6, upper - 1e-6)
    r0 = pb.residual(p0)                     # the start must have every equilibrium
    rejected = np.full(r0.size, 1e3 * (1.0 + np.abs(r0).max()))

    def residual(p):
        """A trial step whose model has no equilibrium under some sample's tensions is refused
        (a residual far above the start's: the trust region shrinks), not the fit."""
        try:
            return pb.residual(p)
        except IdentificationError:
            return rejected

    sol = least_squares(residual, p0, jac=pb.jacobian, bounds=(lower, upper), method="trf",
                        x_scale="jac", xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=max_evaluations)
    p = sol.x
    r = pb.residual(p)
    J = pb.jacobian(p)
    scale = 2.0 * sol.cost / max(1, r.size - layout.size)        # the residuals' own variance
    se = np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J) * scale), 0.0, None))
    fitted = layout.arm(p)
    units = {"tip_mass": "kg", "friction": "-", "offset_fraction": "-", "start_angle": "rad",
             "end_angle": "rad", "encoder_zero": "m", "mocap_rotation": "rad", "mocap_translation": "m"}
    estimates = {}
    for j, name in enumerate(layout.names):
        if name == "youngs_modulus":
            E = fitted.material.youngs_modulus
            estimates[name] = Estimate(E, E * se[j], "Pa")
        elif name == "density":
            rho = fitted.material.density
            estimates[name] = Estimate(rho, rho * se[j], "kg/m^3")
        else:
            estimates[name] = Estimate(float(p[j]), float(se[j]), units[name.split("[")[0]])
    n_m = pb.measured_p.shape[1]
    r_p = r[:n * n_m * 3].reshape(n, n_m, 3) * pb.marker_sigma
    r_s = r[n * n_m * 3:n * (n_m * 3 + n_t)].reshape(n, n_t) * pb.shortening_sigma
    return StaticFit(fitted, layout.encoder_zero(p).copy(), layout.registration(p), estimates,
                     np.sqrt(np.mean(np.sum(r_p ** 2, axis=2), axis=0)), np.sqrt(np.mean(r_s ** 2, axis=0)),
                     n, int(sol.nfev), float(r @ r))


def with_basis_shift(fit: StaticFit, check: StaticFit) -> StaticFit:
    """``fit`` with the basis shift of each estimate: its distance from ``check``'s (the same
    samples fitted on another strain basis, e.g. started from ``fit``)."""
    return replace(fit, estimates={name: replace(e, basis_shift=abs(check.estimates[name].value - e.value))
                                   for name, e in fit.estimates.items()})


def parameter_vector(layout: _Layout, fit: StaticFit) -> np.ndarray:
    """The parameter vector of ``layout`` (its arm's priors) that gives ``fit``'s values."""
    p = np.array([fit.estimates[name].value for name in layout.names])
    a0 = layout.arm0.material
    p[0] = np.log(fit.arm.material.youngs_modulus / a0.youngs_modulus)
    p[1] = np.log(fit.arm.material.density / a0.density)
    return p


def predict_samples(arm: ArmConfig, samples) -> tuple[np.ndarray, np.ndarray]:
    """The model's markers (k, n_m, 3) [m] in arm_base and shortenings (k, n_t) [m] at the
    equilibria of ``samples``' tensions (e.g. of an identified arm, to compare with the data)."""
    model = build_model(arm)
    data = ArmData(model)
    obs = [observe(model, data, eq.q) for eq in _Predictor(list(samples)).equilibria(model)]
    return np.array([o[0] for o in obs]), np.array([o[1] for o in obs])


def staircase(n_tendons: int, low: float, high: float, steps: int = 3, pairs=None) -> np.ndarray:
    """Tensions (k, n_tendons) [N] of a quasi-static identification experiment: each tendon alone,
    then each pair of ``pairs`` (default: every pair), loaded from ``low`` to ``high`` in ``steps``
    and unloaded the same way (so that friction shows as the difference between the two), the
    others held at ``low``; starts and ends on the hanging arm at ``low``."""
    if not 0 <= low < high:
        raise ValueError(f"expected 0 <= low < high [N], got {low}, {high}")
    pairs = [(i, j) for i in range(n_tendons) for j in range(i + 1, n_tendons)] if pairs is None else pairs
    levels = np.linspace(low, high, steps + 1)[1:]
    ramp = np.concatenate([levels, levels[-2::-1], [low]])
    rows = [np.full(n_tendons, low)]
    for group in [(k,) for k in range(n_tendons)] + list(pairs):
        for v in ramp:
            u = np.full(n_tendons, low)
            u[list(group)] = v
            rows.append(u)
    return np.array(rows)
