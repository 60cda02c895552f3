"""Proprioceptive shape estimation: the arm's configuration from its tendons, fused with whatever
markers the mocap still sees. ROS-free; the ``shape_estimator`` node is its shell.

The estimate is an extended Kalman filter on the configuration q of the controller's model, with a
random walk between updates (intensity ``process`` per coordinate, scaled by the coordinate's
compliance so that soft modes may move more), and three kinds of measurement:

- **tendon shortenings** (the encoders): h(q) = L_c(0) - L_c(q), Jacobian -A0(q)^T, with
  ``shortening`` [m] of noise (encoder and model geometry). Four numbers, but exact ones: they fix
  how much the arm bends along each tendon's path;
- **static balance** (a pseudo-measurement): the residual R = k F_el(q) - F_g(q) + A(q, mu) u is
  zero at rest under the measured tensions u, A with the paper's friction weight at the tendons'
  friction coefficients mu. The model is not the plant: its stiffness scale k (1 for the model)
  and the friction coefficients' offsets from the model's are estimated with q (the state is (q, k,
  dmu); they drift by ``parameter_drift`` per sqrt(s); dA/dmu in closed form with the balance's
  tangent, :func:`~soft_arm_model.statics.static_tangents`), and what remains is uncertain in
  proportion to the forces in the balance: a standard deviation of ``balance`` times the magnitude
  of the elastic
  and tendon forces of each coordinate, inflated by ``moving`` per m/s of tendon speed (the arm's
  inertia and damping while it moves); the stiffness and friction are learnt only while every
  tendon is slower than ``rest_speed``. The balance fixes the shape's family, which the four
  lengths cannot;
- **markers** (mocap, when seen): the model's marker positions [m] in arm_base, noise ``marker``
  [m], growing with the tendons' speed as the balance's does (a frame arrives a few milliseconds
  after its exposure); they correct q, never the stiffness and friction. Each marker's innovation
  is gated (Mahalanobis distance squared above ``gate``, chi-square
  with 3 degrees of freedom, is rejected as an outlier); a marker whose innovations stay out of the
  gate for ``regate`` frames in a row is taken again, and kept until its innovation is back
  within the gate (the estimate had diverged from it: counted in ``diverged``).

The stiffness scale stays within :data:`STIFFNESS_BOUNDS` and the friction within
:data:`FRICTION_BOUNDS`. An estimate that is lost (:data:`RESTART_AFTER` updates in a row out of the
model's domain, or at rest with shortenings :data:`RESTART_NIS` normalised squares each away from
what it predicts, or a stiffness the tendons can only explain at or beyond its bounds, moving or
not) starts again from
the equilibrium of the measured tensions (``restarts``).

The estimator does not stand by an estimate (:attr:`ShapeEstimate.distrust`) whose stiffness the
tendons push beyond its bounds, whose shortenings disagree with it by :data:`RESTART_NIS` each, or
whose update left the model's domain; nor by a marker whose standard deviation exceeds
``max_sigma`` (:meth:`ShapeEstimate.defended`). Such markers go to the online CLIK as unseen.

The tendon and balance updates are iterated (at most ``iterations`` Gauss-Newton steps of the
iterated EKF, fewer once a step moves no state by a thousandth of its standard deviation,
the balance being strongly nonlinear in bending). Everything is in SI units and arm_base. Each
update returns the innovations' normalised squares for the diagnostics, and the estimate carries the
covariance of q and of every marker position, so that a consumer can tell what it knows.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from soft_arm_model import ArmData, ArmModel, evaluate, solve_equilibrium
from soft_arm_model.dynamics import KINEMATICS, STATICS, OutOfDomainError
from soft_arm_model.statics import EquilibriumError
from soft_arm_model.parameters import (ConfigError, check_value, default_config_dir, load_section,
                                       read_parameters)

from .estimator_update import (OUT_OF_DOMAIN, UPDATED, marker_innovations, marker_moments, marker_update,
                               new_work, tendon_update)

MAX_PREDICTION = 0.3          # the largest predicted step of a coordinate, in compliance units
STIFFNESS_BOUNDS = (0.5, 2.0)  # the arm's stiffness against the model's: what a cast arm can be
FRICTION_BOUNDS = (0.0, 0.5)   # a tendon's friction coefficient
RESTART_NIS = 25.0             # per shortening: the tendons disagree with the estimate by 5 sigma
RESTART_AFTER = 25             # updates in a row out of the domain, pinned, or at rest and disagreeing
PROCESS_MODELS = ("static", "dynamic")   # what carries the estimate between samples

ESTIMATOR_SCHEMA = {
    "rate": ("float", lambda v: 1 <= v <= 1000, "an update rate in [1, 1000] Hz"),
    "max_time_step": ("float", lambda v: 0 < v <= 10,
                      "a time in (0, 10] s: tendon/state stamps further apart, or going back, are a "
                      "clock step (counted; the estimate advances by the states' period)"),
    "noise.process": ("float", lambda v: 0 < v <= 100,
                      "a random-walk intensity in (0, 100] (generalised force units per sqrt(s))"),
    "noise.shortening": ("float", lambda v: 0 < v <= 0.01, "a standard deviation in (0, 0.01] m"),
    "noise.balance": ("float", lambda v: 0 < v <= 10, "a relative standard deviation in (0, 10]"),
    "noise.balance_floor": ("float", lambda v: 0 < v <= 1,
                            "a standard deviation in (0, 1] (generalised force units)"),
    "noise.moving": ("float", lambda v: 0 <= v <= 1000, "an inflation in [0, 1000] per m/s"),
    "noise.marker": ("float", lambda v: 0 < v <= 0.05, "a standard deviation in (0, 0.05] m"),
    "noise.tension_change": ("float", lambda v: 0 <= v <= 100,
                             "a random-walk step in [0, 100] per N of tension change (compliance units)"),
    "rest_speed": ("float", lambda v: 0 < v <= 1,
                   "a tendon speed in (0, 1] m/s below which the arm counts as at rest"),
    "noise.parameter_drift": ("float", lambda v: 0 <= v <= 1,
                              "a random-walk intensity in [0, 1] per sqrt(s) of the stiffness and "
                              "friction scales"),
    "prior.stiffness": ("float", lambda v: 0 < v <= 1, "a relative standard deviation in (0, 1]"),
    "prior.friction": ("float", lambda v: 0 < v <= 1,
                       "a standard deviation in (0, 1] of each tendon's friction coefficient"),
    "gate": ("float", lambda v: 1 <= v <= 1000, "a chi-square threshold in [1, 1000] (3 degrees of freedom)"),
    "regate": ("int", lambda v: v >= 1, "a number of frames >= 1"),
    "iterations": ("int", lambda v: 1 <= v <= 10, "a number of Gauss-Newton steps in [1, 10]"),
    "max_sigma": ("float", lambda v: 0 < v <= 1,
                  "a standard deviation in (0, 1] m: a marker estimated less surely is no position "
                  "(NaN on estimate/markers)"),
    "process_model": ("str", lambda v: v in PROCESS_MODELS, f"one of {list(PROCESS_MODELS)}"),
    "noise.force": ("float", lambda v: 0 <= v <= 10,
                    "a relative standard deviation in [0, 10] of the forces in the dynamics"),
    "noise.force_floor": ("float", lambda v: 0 < v <= 1,
                          "a standard deviation in (0, 1] (generalised force units)"),
    "noise.tension": ("float", lambda v: 0 <= v <= 10, "a standard deviation in [0, 10] N"),
    "noise.encoder_rate": ("float", lambda v: 0 < v <= 1, "a standard deviation in (0, 1] m/s"),
    "marker_age": ("float", lambda v: 0 <= v <= 0.1, "a time in [0, 0.1] s"),
    "max_frame_age": ("float", lambda v: 0 < v <= 1,
                      "a time in (0, 1] s: a mocap frame stamped further from the state it would be "
                      "weighed with is left out (counted)"),
    "max_substep": ("float", lambda v: 0 < v <= 0.1, "a time step in (0, 0.1] s"),
    "prior.tendon_offset": ("float", lambda v: 0 <= v <= 0.2,
                            "a standard deviation in [0, 0.2] of a tendon's offset (fraction of the radius)"),
    "prior.tendon_angle": ("float", lambda v: 0 <= v <= 0.2, "a standard deviation in [0, 0.2] rad"),
    "prior.payload": ("float", lambda v: 0 <= v <= 0.1, "a standard deviation in [0, 0.1] kg"),
}


@dataclass(frozen=True)
class EstimatorConfig:
    """The estimator's rate [Hz] and noise levels (see the module docstring for each; the values
    are ``config/estimator.yaml``'s, :func:`load_estimator_config`)."""
    rate: float
    max_time_step: float
    process: float
    shortening: float
    balance: float
    balance_floor: float
    moving: float
    marker: float
    gate: float
    regate: int
    iterations: int
    parameter_drift: float
    tension_change: float
    rest_speed: float
    prior_stiffness: float
    prior_friction: float
    max_sigma: float
    process_model: str
    force: float
    force_floor: float
    tension: float
    encoder_rate: float
    marker_age: float
    max_frame_age: float
    max_substep: float
    prior_tendon_offset: float
    prior_tendon_angle: float
    prior_payload: float

    @classmethod
    def of(cls, values: dict) -> "EstimatorConfig":
        """From validated ``estimator`` values (:data:`ESTIMATOR_SCHEMA`)."""
        return cls(**{key.replace("noise.", "").replace(".", "_"): value for key, value in values.items()})


def load_estimator_config(path: str | None = None, overrides=None) -> EstimatorConfig:
    """``estimator`` of ``config/estimator.yaml`` (default: the package's) with overrides."""
    path = path or os.path.join(default_config_dir(), "estimator.yaml")
    return EstimatorConfig.of(load_section(path, "estimator", ESTIMATOR_SCHEMA, overrides))


def prior_overrides(path: str) -> dict:
    """``estimator.prior.*`` of a parameter file (an arm file: soft-arm-identify writes the
    identified payload's uncertainty there) as overrides for :func:`load_estimator_config`, checked
    against the schema (ConfigError naming ``path``); empty if the file has none."""
    estimator = read_parameters(path).get("estimator")
    prior = estimator.get("prior") if isinstance(estimator, dict) else None
    if not isinstance(prior, dict):
        return {}
    try:
        return {f"prior.{key}": check_value(ESTIMATOR_SCHEMA, "estimator", f"prior.{key}", value)
                for key, value in prior.items()}
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def at_rest(rate, rest_speed: float) -> bool:
    """Whether every tendon's rate [m/s] is at most ``rest_speed``: the arm is at rest."""
    return not rate.size or float(np.max(np.abs(rate))) <= rest_speed


def fused_markers(mocap, estimate) -> np.ndarray:
    """(n_markers, 3) [m]: the mocap's markers where they were seen, the estimate's elsewhere
    (``mocap`` None: the estimate's)."""
    out = np.array(estimate, dtype=float)
    if mocap is not None:
        mocap = np.asarray(mocap, dtype=float)
        seen = np.all(np.isfinite(mocap), axis=1)
        out[seen] = mocap[seen]
    return out


def fused_tip(mocap, estimate: "ShapeEstimate") -> tuple[np.ndarray, np.ndarray]:
    """The fused tip [m] and its position covariance (3, 3) [m^2]: the mocap's where it saw the tip,
    taken as a measurement (zero: the online CLIK steps on all of the error it shows, as on the
    mocap), the estimate's otherwise (``mocap`` None: the estimate's), whether the estimator stands
    by it or not (:func:`fused_markers` with the defended estimate leaves that tip invalid)."""
    if mocap is not None and np.all(np.isfinite(np.asarray(mocap, dtype=float)[-1])):
        return np.array(mocap[-1], dtype=float), np.zeros((3, 3))
    return np.array(estimate.markers[-1], dtype=float), np.array(estimate.marker_covariance[-1])


@dataclass(frozen=True)
class ShapeEstimate:
    """The estimate at time ``t`` [s]: configuration q (n,) and its covariance (n, n), marker
    positions (n_markers, 3) [m] in arm_base and their covariances (n_markers, 3, 3) [m^2];
    ``distrust``: why the estimator does not stand by it (None: it does)."""
    t: float
    q: np.ndarray
    covariance: np.ndarray
    markers: np.ndarray
    marker_covariance: np.ndarray
    distrust: str | None = None

    @property
    def marker_sigma(self) -> np.ndarray:
        """(n_markers,) [m]: the square root of the largest eigenvalue of each marker's covariance."""
        return np.sqrt(np.linalg.eigvalsh(self.marker_covariance)[:, -1])

    def defended(self, max_sigma: float) -> np.ndarray:
        """(n_markers, 3) [m]: the markers the estimator stands by, NaN rows for the others (all of
        them under a ``distrust``; otherwise those whose standard deviation exceeds ``max_sigma``
        [m]): what a consumer of positions, the online CLIK, may take as one."""
        out = np.array(self.markers, dtype=float)
        if self.distrust is not None:
            out[:] = np.nan
        else:
            out[self.marker_sigma > max_sigma] = np.nan
        return out


@dataclass
class UpdateReport:
    """What one update used: the markers taken and those gated out (indices), the tendon and balance
    innovations' normalised squares (NIS, sums), each marker's NIS (NaN: not seen)."""
    used: list = field(default_factory=list)
    gated: list = field(default_factory=list)
    tendon_nis: float = 0.0
    marker_nis: np.ndarray | None = None


class MarkerGate:
    """The markers' innovation gate both shape estimators share: a marker whose normalised square
    exceeds ``gate`` is an outlier, left out; one that stays out for ``regate`` frames in a row is
    taken again (the estimate had diverged from it: counted in ``diverged``) and kept until it is
    back within the gate."""

    def __init__(self, n_markers: int, gate: float, regate: int):
        self.gate, self.regate = gate, regate
        self.rejected = np.zeros(n_markers, dtype=int)    # frames in a row out of the gate
        self.retaken = np.zeros(n_markers, dtype=bool)    # taken again, not yet back in it
        self.diverged = 0

    def takes(self, k: int, nis: float) -> bool:
        """Whether marker k, whose innovation has the normalised square ``nis``, is taken."""
        if nis > self.gate and not self.retaken[k]:
            self.rejected[k] += 1
            if self.rejected[k] < self.regate:
                return False
            self.diverged += 1
            self.retaken[k] = True
        if nis <= self.gate:
            self.retaken[k] = False
        self.rejected[k] = 0
        return True


class LostRule:
    """When both shape estimators stop standing by their estimate, and when they restart: an update
    whose stiffness scale is on :data:`STIFFNESS_BOUNDS` (no cast arm is so, moving or not), whose
    shortenings disagree with it by :data:`RESTART_NIS` each (where the filter's process model makes
    that meaningful) or that leaves the model's domain is distrusted (:attr:`distrust` says why);
    :data:`RESTART_AFTER` such updates in a row and the estimate is :attr:`lost`."""

    def __init__(self):
        self.bad = 0                 # updates in a row that say the estimate is lost
        self.distrust: str | None = None

    def judge(self, stiffness: float, shortening_nis: float, n_tendons: int, disagreement_counts: bool):
        """An update taken: its stiffness scale and the normalised square of its shortenings'
        innovation over ``n_tendons``; ``disagreement_counts``: whether a disagreement of the
        shortenings alone counts towards a restart (it is said either way)."""
        pinned = not STIFFNESS_BOUNDS[0] < stiffness < STIFFNESS_BOUNDS[1]
        disagree = shortening_nis > RESTART_NIS * n_tendons
        self.bad = self.bad + 1 if pinned or (disagreement_counts and disagree) else 0
        self.distrust = None
        if pinned:
            self.distrust = (f"the tendons need a stiffness {stiffness:.2f} times the model's, at or "
                             f"beyond what a cast arm can be {list(STIFFNESS_BOUNDS)}")
        elif disagree:
            self.distrust = (f"the shortenings disagree with the estimate (normalised square "
                             f"{shortening_nis:.0f} over {n_tendons} tendons)")

    def out_of_domain(self):
        """An update not taken: it left the model's domain."""
        self.bad += 1
        self.distrust = "the update left the model's domain"

    def unstarted(self, reason: str):
        """No start at this sample (``reason``): nothing to stand by until a start succeeds."""
        self.distrust = reason

    @property
    def lost(self) -> bool:
        return self.bad >= RESTART_AFTER

    def restarted(self):
        self.bad, self.distrust = 0, None


class ShapeEstimator:
    """The filter for ``model`` (the controller's) with ``config``. :meth:`start` initialises it at
    the equilibrium of the measured tensions; then :meth:`update` once per sample. The state is
    (q, stiffness scale, friction offsets); :attr:`q` and :attr:`P` are its configuration part's."""

    def __init__(self, model: ArmModel, config: EstimatorConfig):
        self.model, self.config = model, config
        self.data = ArmData(model)
        self._evaluated_at = None     # (q, level) whose markers (and statics at STATICS) self.data holds
        n, nt = model.n, model.n_tendons
        # compliance scale of each coordinate: the random walk follows it
        stiffness = np.abs(np.diag(model.K))
        self.scale = 1.0 / np.sqrt(np.maximum(stiffness, 1e-9 * stiffness.max()))
        self.z = np.concatenate([np.zeros(n), [1.0], np.zeros(nt)])
        self.Pz = np.diag(np.concatenate([(0.05 * self.scale) ** 2, [config.prior_stiffness ** 2],
                                          np.full(nt, config.prior_friction ** 2)]))
        self.t = None
        self.counts = {"updates": 0, "markers_used": 0, "markers_gated": 0, "diverged": 0,
                       "out_of_domain": 0, "restarts": 0, "start_failures": 0}
        self._prior = self.z.copy(), self.Pz.copy()
        self._lost = LostRule()
        self._gate = MarkerGate(model.marker_X.size, config.gate, config.regate)
        self._linear = None          # (dR/dq, A, u) of the last tendon update, for the prediction
        mu = np.array([t.friction for t in model.config.tendons])
        self._bounds = (np.concatenate([[STIFFNESS_BOUNDS[0]], FRICTION_BOUNDS[0] - mu]),   # of z[n:]
                        np.concatenate([[STIFFNESS_BOUNDS[1]], FRICTION_BOUNDS[1] - mu]))
        size, rows = self.z.size, max(n + nt, 3 * model.marker_X.size)     # the updates' largest
        self._update_out = (np.zeros(size), np.zeros((size, rows)), np.zeros((rows, size)), np.zeros(rows),
                            np.zeros(rows))                  # z, K, H, noise, innovation
        self._update_work = new_work(n, nt, model.marker_X.size)
        n_m = model.marker_X.size                            # the markers' Jacobians, covariances,
        self._marker_out = (np.zeros((n_m, 3, n)), np.zeros((n_m, 3, 3)), np.zeros((n_m, 3)),
                            np.zeros(n_m))                   # innovations and NIS

    @property
    def q(self) -> np.ndarray:
        return self.z[:self.model.n]

    @property
    def P(self) -> np.ndarray:
        n = self.model.n
        return self.Pz[:n, :n]

    @property
    def parameters(self) -> tuple[float, np.ndarray]:
        """The estimated stiffness scale of the arm against the model and its tendons' friction
        coefficients."""
        n = self.model.n
        mu = np.array([t.friction for t in self.model.config.tendons]) + self.z[n + 1:]
        return float(self.z[n]), mu

    def start(self, t: float, tension, shortening=None):
        """Start at the equilibrium of ``tension`` [N] (refined by three tendon updates with the
        shortenings [m] when given)."""
        u = np.ascontiguousarray(tension, dtype=float)
        self.z[:self.model.n] = solve_equilibrium(self.model, u).q
        self.t = float(t)
        if shortening is not None:
            for _ in range(3):
                self._tendon_update(np.ascontiguousarray(shortening, dtype=float), u, np.zeros(u.size))
                self._clamp_parameters()

    def _begin(self, t: float, u, s) -> bool:
        """:meth:`start` at this sample; False where it cannot (no equilibrium of the model at the
        tensions ``u``, or a refinement left the model's domain): counted (``start_failures``), the
        filter left unstarted at its prior, :attr:`distrust` saying why; the next sample tries
        again."""
        try:
            self.start(t, u, s)
            return True
        except (EquilibriumError, OutOfDomainError, np.linalg.LinAlgError) as exc:
            self.t, self._linear = None, None
            self.z, self.Pz = (a.copy() for a in self._prior)
            self.counts["start_failures"] += 1
            self._lost.unstarted(f"no start at the measured tensions: {exc}")
            return False

    @property
    def started(self) -> bool:
        return self.t is not None

    @property
    def distrust(self) -> str | None:
        """Why the last update leaves the estimate undefended (None: it does not)."""
        return self._lost.distrust

    def update(self, t: float, shortening, rate, tension, markers=None) -> UpdateReport:
        """One sample at time ``t`` [s]: the tendons' shortenings [m], rates [m/s] and tensions [N],
        and ``markers`` (n_markers, 3) [m] in arm_base with NaN rows for the unseen (None: no
        frame). Returns what was used."""
        s, sd, u = (np.ascontiguousarray(v, dtype=float) for v in (shortening, rate, tension))
        if not self.started and not self._begin(t, u, s):
            return UpdateReport()
        saved = self.z.copy(), self.Pz.copy(), self._linear
        dt = max(0.0, float(t) - self.t)
        self.t = float(t)
        c = self.config
        self._predict(u)
        change = 0.0 if self._linear is None else float(np.linalg.norm(u - self._linear[2]))
        walk = (c.process ** 2 * dt + (c.tension_change * change) ** 2) * self.scale ** 2
        drift = np.full(self.z.size - self.model.n, c.parameter_drift ** 2 * dt)
        self.Pz += np.diag(np.concatenate([walk, drift]))
        report = UpdateReport()
        try:
            report.tendon_nis, shortening_nis = self._tendon_update(s, u, sd)
            if markers is not None:
                self._marker_update(np.asarray(markers, dtype=float), report, sd)
            self._evaluate_markers()                                              # in the domain
            stiffness = self.z[self.model.n]
            self._clamp_parameters()
            # shortenings that disagree count only at rest: a move outruns the static balance
            self._lost.judge(stiffness, shortening_nis, s.size, disagreement_counts=at_rest(sd, c.rest_speed))
        except (OutOfDomainError, np.linalg.LinAlgError):   # left the model's domain, or a
            self.counts["out_of_domain"] += 1                   # singular innovation: not taken
            self.z, self.Pz, self._linear = saved
            self.Pz[np.diag_indices(self.model.n)] += (c.tension_change * self.scale) ** 2 * 1e-2
            self._lost.out_of_domain()
        if self._lost.lost:                       # lost: start again from the tensions' equilibrium
            self.counts["restarts"] += 1
            self.z, self.Pz = (a.copy() for a in self._prior)
            self._linear = None
            self._lost.restarted()
            self._begin(t, u, s)
        self.counts["updates"] += 1
        return report

    def _clamp_parameters(self):
        """The stiffness scale and friction coefficients into what a cast arm can have."""
        n = self.model.n
        np.clip(self.z[n:], *self._bounds, out=self.z[n:])

    def _predict(self, u):
        """Move q with the change of the tensions since the last update, along the model's static
        sensitivity dq = -(dR/dq)^-1 A du at the last estimate (the arm follows its tensions: the
        random walk is left with what the tensions do not explain)."""
        if self._linear is None:
            return
        jacobian, actuation, u_last = self._linear
        du = u - u_last
        if np.any(du):
            try:
                step = -np.linalg.solve(jacobian, actuation @ du)
            except np.linalg.LinAlgError:
                return
            if np.max(np.abs(step) / self.scale) <= MAX_PREDICTION:    # beyond: not linear any more
                self.z[:self.model.n] += step

    def estimate(self) -> ShapeEstimate:
        """The current estimate (markers and their covariance from the model's kinematics)."""
        d = self._evaluate_markers(KINEMATICS)
        H, C = self._marker_out[:2]
        marker_moments(d.marker_R, d.marker_J, self.Pz, H, C, self._update_work)
        return ShapeEstimate(self.t if self.t is not None else 0.0, self.q.copy(), self.P.copy(),
                             d.marker_p.copy(), C.copy(), self.distrust)

    # --- updates ---------------------------------------------------------------------------------

    def _tendon_update(self, s, u, sd) -> tuple[float, float]:
        """Iterated update with the shortenings and the static balance
        (:func:`~soft_arm_control.estimator_update.tendon_update`); returns their NIS, and the
        shortenings' alone."""
        c, model, n, d = self.config, self.model, self.model.n, self.data
        speed = float(np.max(np.abs(sd))) if sd.size else 0.0
        self._evaluated_at = None
        z, K, H, noise, innovation = self._update_out
        status, nis, shortening_nis = tendon_update(
            model.kernel_args, d.kernel_args, d.Fg, d.Fel, d.A, d.A0, d.Kt, d.Lc,
            model.rest_tendon_lengths, s, u, self.z, self.Pz, c.iterations, c.balance, c.balance_floor,
            1.0 + c.moving * speed, c.shortening ** 2, speed > c.rest_speed, z, K, H, noise, innovation,
            self._update_work)
        if status == OUT_OF_DOMAIN:
            raise OutOfDomainError("configuration outside the model's domain")
        if status != UPDATED:
            raise np.linalg.LinAlgError("the innovation covariance is not positive definite")
        self.z = z.copy()
        dA = self._update_work[3]                         # dA/d mu at the last linearisation
        self._linear = (H[s.size:s.size + n, :n].copy(), d.A + dA * self.z[n + 1:][None, :], u.copy())
        return nis, shortening_nis

    def _marker_update(self, markers, report: UpdateReport, sd):
        """Update with the seen markers, gated; their noise grows with the tendons' speed ``sd``
        [m/s] as the balance's does (a frame is a few milliseconds old when it arrives). The
        stiffness and friction are left to the tendons."""
        c, n = self.config, self.model.n
        if not np.isfinite(markers).any():           # a frame with every marker hidden tells nothing
            report.marker_nis = np.full(self.model.marker_X.size, np.nan)
            return
        sigma = c.marker * (1.0 + c.moving * (float(np.max(np.abs(sd))) if sd.size else 0.0))
        d = self._evaluate_markers(KINEMATICS)
        H_all, C, nu, nis = self._marker_out
        marker_moments(d.marker_R, d.marker_J, self.Pz, H_all, C, self._update_work)
        marker_innovations(C, np.ascontiguousarray(markers), d.marker_p, sigma ** 2, nu, nis,
                           self._update_work)
        report.marker_nis = nis.copy()
        seen = np.flatnonzero(np.isfinite(nis))       # NaN: not seen (or no innovation covariance)
        z, K, H, noise, innovation = self._update_out
        rows = 0
        for k in seen:
            if not self._gate.takes(k, report.marker_nis[k]):
                report.gated.append(int(k))
                continue
            H[rows:rows + 3, :n] = H_all[k]
            H[rows:rows + 3, n:] = 0.0
            innovation[rows:rows + 3] = nu[k]
            rows += 3
            report.used.append(int(k))
        self.counts["markers_used"] += len(report.used)
        self.counts["markers_gated"] += len(report.gated)
        self.counts["diverged"] = self._gate.diverged
        if rows and not marker_update(H, innovation, rows, sigma ** 2, n, self.z, self.Pz, K, noise,
                                      self._update_work):
            raise np.linalg.LinAlgError("the markers' innovation covariance is not positive definite")

    def _evaluate_markers(self, level: int = STATICS):
        """The workspace at the current q, up to ``level`` (KINEMATICS: the markers' positions and
        Jacobians; STATICS: also the checks of the tendons' domain), with the markers; evaluated
        again only where q moved or a higher level is asked (OutOfDomainError outside the
        model's domain)."""
        held = self._evaluated_at
        if held is not None and held[1] >= level and np.array_equal(held[0], self.q):
            return self.data
        self._evaluated_at = None                   # until the evaluation has filled it
        d = evaluate(self.model, self.data, self.q, level=level, markers=True)
        self._evaluated_at = self.q.copy(), level
        return d
