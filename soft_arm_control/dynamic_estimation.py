"""Proprioceptive shape estimation in motion: an extended Kalman filter whose process model is the
arm's Variable-Strain dynamics. ROS-free; the ``shape_estimator`` node runs it when
``estimator.process_model`` is ``dynamic``.

The state is z = (q, qd, k, dmu, b, m_p): the configuration of the controller's model and its rate,
the arm's stiffness scale against the model, the offsets of the tendons' friction coefficients, the
offsets of the tendons' routing from the model's (per tendon its offset as a fraction of the radius,
its start and end angles [rad]: :mod:`soft_arm_model.routing`) and a payload at the tip [kg].
Between samples it is carried by the model's own time step (:mod:`soft_arm_model.integrators`'
linearly implicit Euler step, the rotors' reflected mass m [kg] on every tendon) under the
measured tensions u [N], at the estimated routing and payload::

    (M + h D + h^2 k K_t + A m A0^T) qd+
        = M qd + A m A0^T qd + h (F_g - C qd - k F_el - A (u + m Adot0^T qd) + m_p J_tip^T g),
    q+ = q + h qd+,

with A at the estimated friction (A + dA/dmu dmu). The step's Jacobian takes the static balance's
analytic tangent dR/dq for the forces' dependence on q (the elastic tangent, the gravity Hessian,
the tendons' geometric stiffness: :func:`~soft_arm_model.kernels.static_tangent`), the implicit
part exactly, and the routing's derivatives of A and A0
(:func:`~soft_arm_model.routing.routing_derivatives`); the derivatives of M, C and the rotors'
coupling with q are left out (second order at the estimator's 4 ms:
``test/control/test_dynamic_estimation.py`` bounds them at 5 %). What the model does not explain
enters as a generalised impulse per step of standard deviation h (``force`` times the magnitude of
the elastic, tendon and damping forces of each coordinate, + ``force_floor``) and the tensions' own
noise ``tension`` [N] through A.

Measurements, each sample: the shortenings s = L_c(0) - L_c(q) (Jacobian -A0^T, noise
``shortening`` [m]) and their rates -A0^T qd (the encoders' velocities, noise ``encoder_rate``
[m/s]), which with the dynamics between samples fix the arm's motion in the tendons' directions
while the model carries the rest; the markers when seen, gated as in
:class:`~soft_arm_control.shape_estimation.ShapeEstimator`, their noise ``marker`` [m] grown by the
distance the marker travels in ``marker_age`` [s] at its estimated velocity (a frame is a few
milliseconds old when it arrives).

Where the arm is not the model. The stiffness and friction are learnt from the tendons once the
arm has settled at a rest, and in motion only with markers seen; on the tendons alone, in motion,
they are considered (below). A sustained move is where the model's other errors (the tendons'
friction reversing every half period, the damping) are largest, and the tendons alone cannot tell
those from the stiffness and friction: learnt through the fast circle (1.5 cm at 0.2 m/s), they
walked from 1.17 to 1.40 (the plant's 1.15) and 0.10 to 0.00-0.21 in ten seconds, and the tip's
estimate 6-8 mm off with them. Nor does a rest teach them as soon as the tendons stop (every tendon
slower than ``rest_speed``): the four tendons fix four of the configuration's directions, and in the
others the estimate still relaxes towards the balance at the model's own rate; stiffness and friction
learnt meanwhile take that transient up and keep it, a bias at every rest that the next rests do
not undo. They are learnt once the tendons have rested :data:`SETTLING` time constants of the
slowest mode of the model's dynamics linearised at the estimate where the rest began
(:attr:`settling_time`: 2-8 s at the arm's poses, the longest where it hangs slack). On the blind
triangle (``bench/bench_sensing.py``'s ``filters``) the tip at rest went from 0.67 to 0.30 mm
(median; 0.36 mm at two time constants, 0.28 at four), and on a plant that is the model but for
its damping from 0.62 to 0.10 mm. The routing and the payload are not
learnt from the tendons at all: four lengths cannot tell a tendon running a few hundredths of a
radius off its path from a different bend, nor a payload on the last few centimetres that no
tendon reaches from the shape's own droop. Without markers they are
*considered* (Schmidt): their prior uncertainty (``prior.tendon_offset``, ``prior.tendon_angle``,
``prior.payload``) is carried into the configuration's covariance through the dynamics and the
shortenings, so that the reported uncertainty includes what they may do, and their estimate stays;
with markers seen they are learnt like the rest of the state. The payload is not even weighed in
the configuration's gain without markers: at a bend, a gram at the tip moves it by 10-35 mm and the
shortenings by 0.1-1 mm, so a tendon's unexplained millimetre (friction, a strain the basis lacks)
taken as payload would move the tip by centimetres. The configuration is estimated as if the
payload were its estimate, and the covariance, updated in the Joseph form for that gain, keeps the
droop the payload may cause. Neither drifts (a cast arm's routing
does not move); the stiffness and friction drift by ``parameter_drift``. :attr:`routing_sigma` and
:attr:`payload` say how much of them the markers have told.

A second opinion at rest. What neither the states above nor their priors cover (a strain the basis
lacks, a stiffness or friction learnt wrongly in motion) leaves the estimate biased with a
covariance that does not say so. At rest the arm is in its static balance,
and the static filter (:class:`~soft_arm_control.shape_estimation.ShapeEstimator`, run on the same
samples: the balance is its process model, so at rest it answers from the model's statics, not from
the history of a move) is an independent estimate of the same configuration. Whenever every tendon is
slower than ``rest_speed`` and the static filter stands by its estimate, their difference (:attr:`gap`:
in q, and at every marker [m]) is taken as a sample of the model's bias and held through the moves
until the next rest; the reported covariances add its outer products, of q's to the configuration's
and of each marker's to that marker's (a bias of centimetres is not linear in q; the filter's own
state and gain are not changed). Where the two tips differ by more than their covariances allow
(normalised square above ``gate``), the estimate is distrusted until the two agree at a rest, and
the disagreement counted (``disagreements``). In motion, where nobody asks it, the static filter
only keeps up: it updates at most every :data:`SECOND_OPINION_PERIOD`; at rest on every sample (its
covariance, which the gate weighs, is its steady state at the estimator's rate).

The payload's spread at rest. The payload's share above is linear, the estimate's derivative with
respect to the payload, and the droop of a few grams at a bend is not: it turns as it grows (4.6 g
at the tip, 1.6 of the robustness campaign's standard deviations: the tip 37 mm from the estimate in
a direction the share does not reach, a NEES of 66 after 300 samples at rest against a 99 % bound of
11). The second opinion cannot see it, since it shares the model. Where the filter is told of a
payload (``prior.payload`` above zero), a second filter of this kind runs beside it on the model
with the payload's sigma point at the tip, its payload known: :data:`PAYLOAD_POINT` standard
deviations above the model's tip mass, on the one side a payload can be (it only adds mass; the
model's tip mass is the part that is known), with the weight :data:`PAYLOAD_WEIGHT` that carries the
prior's second moment. It is this filter and not the static one, because the spread must be the
reported estimate's own answer to the payload: this filter weighs the shortenings against the
routing's uncertainty and rests nearer the payload-free balance, so that the static filter's answer
is two to three times smaller (on robustness draw 4, the routing a few hundredths of a radius off,
it left a NEES of 14 at a bend where this one leaves 2.4). It updates on the second opinion's
samples but at most every :data:`SECOND_OPINION_PERIOD`, at rest too, one dynamics step between them
(its estimates count, not its covariance, and at rest a sample differs little from the next); at
rest, whenever it updates and both stand by their estimates, the weighted outer product of its
difference from this estimate is the payload's spread (:attr:`payload_spread`, in q and at every
marker), held through the moves and added to the reported covariances as the gap is. The filter's
own state and gain are not changed. With the markers seen the spread shrinks to what they leave
(they pin the tip).

The public interface is :class:`~soft_arm_control.shape_estimation.ShapeEstimator`'s (``update``,
``estimate``, ``counts``, ``distrust``, ``parameters``), so that a consumer takes either; the
restarts and the distrust are the same rules, and the second opinion's disagreement besides.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from soft_arm_model import ArmData, ArmModel, build_model, solve_equilibrium
from soft_arm_model import kernels
from soft_arm_model.dynamics import DYNAMICS, KINEMATICS, STATICS, OutOfDomainError
from soft_arm_model.statics import EquilibriumError
from soft_arm_model.routing import (new_routing_work, routing_arrays, routing_derivatives, routing_of,
                                    tendon_ends)

from .dynamic_estimator_steps import gain_update, noise_parameters, predict_step, tendon_rows
from .shape_estimation import (FRICTION_BOUNDS, STIFFNESS_BOUNDS, EstimatorConfig, LostRule, MarkerGate,
                               ShapeEstimate, ShapeEstimator, UpdateReport, at_rest)

ROUTING_BOUNDS = (0.15, 0.15)   # a tendon's offset (fraction of the radius), angles [rad] off the model's
PAYLOAD_BOUNDS = (0.0, 0.1)     # kg at the tip
SECOND_OPINION_PERIOD = 1 / 60  # s: in motion the static filter updates at most this often
# how many time constants of the model's slowest mode a rest lasts before the tendons teach the
# stiffness and friction: e^-3, 5 % of the transient of the arrival, is left (module docstring)
SETTLING = 3.0
# the payload's sigma point, this many standard deviations of prior.payload above the model's tip
# mass, and its weight: the one point that carries the prior's second moment (PAYLOAD_WEIGHT *
# PAYLOAD_POINT**2 = 1) on the side a payload can be
PAYLOAD_POINT = np.sqrt(3.0)
PAYLOAD_WEIGHT = 1.0 / 3.0


def _due(last: float | None, t: float) -> bool:
    """Whether a filter last updated at ``last`` [s] (None: never) is due at ``t`` [s]: at least
    :data:`SECOND_OPINION_PERIOD` later, or the clock went back."""
    since = None if last is None else float(t) - last
    return since is None or not 0.0 <= since < SECOND_OPINION_PERIOD - 1e-9


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (which its owner still writes through ``a``): the compiled kernels
    take the model's arrays read-only, and a writable one would compile each of them a second time."""
    view = a.view()
    view.setflags(write=False)
    return view


class DynamicShapeEstimator:
    """The filter for ``model`` (the controller's) with ``config`` and the rotors' reflected mass
    ``rotor_mass`` [kg] on every tendon. :meth:`update` once per sample; :attr:`q`, :attr:`qd` and
    :attr:`P` are the state's configuration, rate and the configuration's covariance (the filter's,
    without the second opinion's :attr:`gap` and the :attr:`payload_spread`, which :meth:`estimate`
    adds), :attr:`routing` the tendons' estimated routing ((3, n_tendons): offset fractions, start
    and end angles [rad]), :attr:`settling_time` how long the latest rest must last before the tendons
    teach the stiffness and friction [s] (infinite before the first rest)."""

    def __init__(self, model: ArmModel, config: EstimatorConfig, rotor_mass: float,
                 second_opinion: bool = True):
        """``second_opinion``: run the static filter beside it at rest, and the payload's sigma
        point where ``config.prior_payload`` is above zero (module docstring); the sigma point's
        own filter runs without."""
        self.model, self.config = model, config
        self.rotor = np.full(model.n_tendons, float(rotor_mass))
        self.data = ArmData(model)
        n, nt = model.n, model.n_tendons
        self.N = 2 * n + 1 + 4 * nt + 1
        # where each part starts: stiffness scale, friction offsets, routing offsets, the tip's payload
        self._k, self._mu, self._beta, self._load = 2 * n, 2 * n + 1, 2 * n + 1 + nt, 2 * n + 1 + 4 * nt
        stiffness = np.abs(np.diag(model.K))
        self.scale = 1.0 / np.sqrt(np.maximum(stiffness, 1e-9 * stiffness.max()))
        self.z = np.concatenate([np.zeros(2 * n), [1.0], np.zeros(4 * nt), [0.0]])
        routing_sigma = np.repeat([config.prior_tendon_offset, config.prior_tendon_angle,
                                   config.prior_tendon_angle], nt)
        self.Pz = np.diag(np.concatenate([(0.05 * self.scale) ** 2, (0.05 * self.scale) ** 2,
                                          [config.prior_stiffness ** 2],
                                          np.full(nt, config.prior_friction ** 2),
                                          routing_sigma ** 2, [config.prior_payload ** 2]]))
        self._prior = self.z.copy(), self.Pz.copy()
        # the estimate's error per kg of the payload's prior error: the payload's share of the
        # covariance is prior_payload^2 * share share^T (the gain without markers leaves it out)
        self._share = np.zeros(self.N)
        self._share[self._load] = 1.0
        self.t = None
        self.u = None
        self.counts = {"updates": 0, "markers_used": 0, "markers_gated": 0, "diverged": 0,
                       "out_of_domain": 0, "restarts": 0, "disagreements": 0, "start_failures": 0}
        # the second opinion at rest (module docstring): the static filter on the same samples, and
        # the configuration's difference from it at the latest rest
        self.second = None
        if second_opinion:
            self.second = ShapeEstimator(model, replace(config, process_model="static"))
        self.gap = np.zeros(n), np.zeros((model.marker_X.size, 3))
        # the payload's spread at rest (module docstring): this filter on the model with the payload's
        # sigma point at the tip, its payload known, one step between its samples
        self._payload_filter = None
        if second_opinion and config.prior_payload > 0.0:
            tip_mass = model.config.tip_mass + PAYLOAD_POINT * config.prior_payload
            known = replace(config, prior_payload=0.0,
                            max_substep=max(config.max_substep, SECOND_OPINION_PERIOD))
            heavier = build_model(replace(model.config, tip_mass=tip_mass))
            self._payload_filter = DynamicShapeEstimator(heavier, known, rotor_mass, second_opinion=False)
        self.payload_spread = np.zeros((n, n)), np.zeros((model.marker_X.size, 3, 3))
        self._payload_t: float | None = None          # the sigma point's filter's last update [s]
        self._second_t: float | None = None           # the static filter's last update [s]
        self._disagree: str | None = None
        self._lost = LostRule()
        self._gate = MarkerGate(model.marker_X.size, config.gate, config.regate)
        # the model's tendon arrays at the estimated routing (the other kernel arguments are the model's)
        g = model.config.geometry
        self._drawn = routing_of(model.config)
        self._geometry = (model.X, model.tendon_active, g.base_radius,
                          (g.tip_radius - g.base_radius) / g.length, tendon_ends(model.config))
        self._t_arrays = tuple(np.array(a) for a in (model.tendon_d, model.tendon_dp, model.tendon_dpp))
        self._t_read = tuple(_read_only(a) for a in self._t_arrays)     # what the kernels are given
        args = list(model.kernel_args)
        args[12:15] = self._t_read
        self.args = tuple(args)
        a = model.kernel_args
        self._routing_args = (a[0], a[1], a[2], a[17], a[18], a[19], a[20])
        self._routing_work = new_routing_work(model)
        rest = ArmData(model)
        kernels.evaluate(*model.kernel_args, np.zeros(n), np.zeros(n), 0, False, *rest.kernel_args)
        self._xi_rest, self._q_rest = rest.xi.copy(), np.zeros(n)
        self._L0 = np.array(model.rest_tendon_lengths)
        self._dA, self._dA0 = np.zeros((3, n, nt)), np.zeros((3, n, nt))
        self._dLc, self._dL0 = np.zeros((3, nt)), np.zeros((3, nt))
        self._rest_at = None              # the routing that _L0 and _dL0 are of (they depend on nothing else)
        self._adot = np.zeros(nt)
        self._jac = np.zeros((n, n))
        self._dA_dmu = np.zeros((n, nt))
        self._rotors = bool(np.any(self.rotor))
        self._noise = noise_parameters(config)
        self._parts = np.array([self._k, self._mu, self._beta, self._load])
        self._F = np.zeros((self.N, self.N))
        self._tendon_rows = np.zeros((2 * nt, self.N)), np.zeros(2 * nt), np.zeros(2 * nt)
        self._tendon_noise = np.array([config.shortening, config.encoder_rate])
        # the parameters' bounds, from the stiffness scale to the payload
        mu = np.array([t.friction for t in model.config.tendons])
        self._bounds = tuple(np.concatenate([[STIFFNESS_BOUNDS[i]], FRICTION_BOUNDS[i] - mu,
                                             np.full(nt, sign * ROUTING_BOUNDS[0]),
                                             np.full(2 * nt, sign * ROUTING_BOUNDS[1]), [PAYLOAD_BOUNDS[i]]])
                             for i, sign in ((0, -1.0), (1, 1.0)))
        self._evaluated_at = None    # (q, qd, level) whose terms self.data holds
        self._rested: float | None = None    # how long the tendons have rested [s] (None: moving)
        self.settling_time = np.inf          # the current rest's (module docstring) [s]

    @property
    def q(self) -> np.ndarray:
        return self.z[:self.model.n]

    @property
    def qd(self) -> np.ndarray:
        n = self.model.n
        return self.z[n:2 * n]

    @property
    def P(self) -> np.ndarray:
        n = self.model.n
        return self.Pz[:n, :n]

    @property
    def parameters(self) -> tuple[float, np.ndarray]:
        """The estimated stiffness scale of the arm against the model and its tendons' friction
        coefficients."""
        mu = np.array([t.friction for t in self.model.config.tendons]) + self.z[self._mu:self._beta]
        return float(self.z[self._k]), mu

    @property
    def routing(self) -> np.ndarray:
        return self._drawn + self.z[self._beta:self._load].reshape(3, -1)

    @property
    def routing_sigma(self) -> np.ndarray:
        """(3, n_tendons): the routing's standard deviations (the prior's where the tendons cannot
        tell it)."""
        return np.sqrt(np.diag(self.Pz)[self._beta:self._load]).reshape(3, -1)

    @property
    def payload(self) -> tuple[float, float]:
        """The estimated payload at the tip [kg] and its standard deviation."""
        return float(self.z[self._load]), float(np.sqrt(self.Pz[self._load, self._load]))

    @property
    def started(self) -> bool:
        return self.t is not None

    @property
    def distrust(self) -> str | None:
        """Why the last update leaves the estimate undefended (None: it does not)."""
        return self._lost.distrust or self._disagree

    def start(self, t: float, tension, shortening=None):
        """Start at rest at the model's equilibrium of ``tension`` [N] (the shortenings [m] are the
        first update's measurement; the argument is the static estimator's interface)."""
        u = np.ascontiguousarray(tension, dtype=float)
        n = self.model.n
        self._set_routing()
        self.z[:n] = solve_equilibrium(self.model, u).q
        self.z[n:2 * n] = 0.0
        self.t, self.u = float(t), u.copy()
        self._rested = None

    def _begin(self, t: float, u, s) -> bool:
        """:meth:`start` at this sample; False where the model has no equilibrium at the tensions
        ``u``: counted (``start_failures``), the filter left unstarted at its prior, :attr:`distrust`
        saying why; the next sample tries again."""
        try:
            self.start(t, u, s)
            return True
        except (EquilibriumError, OutOfDomainError, np.linalg.LinAlgError) as exc:
            self.t = None
            self.z, self.Pz = (a.copy() for a in self._prior)
            self._share[:] = 0.0
            self._share[self._load] = 1.0
            self._set_routing()
            self.counts["start_failures"] += 1
            self._lost.unstarted(f"no start at the measured tensions: {exc}")
            return False

    # --- the model at the estimated routing -----------------------------------------------------

    def _set_routing(self):
        X, active, r0, taper, ends = self._geometry
        routing_arrays(X, active, r0, taper, self.routing, ends, *self._t_arrays)
        self._evaluated_at = None

    def _evaluate(self, q, v, level: int, markers: bool):
        if not kernels.evaluate(*self.args, q, v, level, markers, *self.data.kernel_args):
            self._evaluated_at = None
            raise OutOfDomainError("the state left the model's domain")
        self._evaluated_at = (q.copy(), v.copy(), level) if markers else None

    def _holds(self, q, v, level: int) -> bool:
        """Whether self.data holds the terms of (q, v) up to ``level`` at the current routing (the
        rate counts from the dynamics on)."""
        held = self._evaluated_at
        return (held is not None and held[2] >= level and np.array_equal(held[0], q)
                and (level < DYNAMICS or np.array_equal(held[1], v)))

    def _routing_derivatives(self, q, with_rest: bool):
        """dA, dA0 and dL_c with respect to the routing at q (evaluated in self.data), and with
        ``with_rest`` dL_0 and L_0 (the straight arm's: computed again only when the routing has
        changed since, which without markers it never does)."""
        m = self.model
        X, active, r0, taper, ends = self._geometry
        routing = self.routing
        if with_rest and self._rest_at is not None and np.array_equal(routing, self._rest_at):
            with_rest = False
        elif with_rest:
            self._rest_at = None
        if not routing_derivatives(*self._routing_args, X, active, r0, taper, ends, m.friction_mu,
                                   routing, self.data.xi, q, self._xi_rest, self._q_rest, with_rest,
                                   self._L0, self._dA, self._dA0, self._dLc, self._dL0, self._routing_work):
            raise OutOfDomainError("a degenerate tendon tangent")
        if with_rest:
            self._rest_at = routing

    # --- prediction ------------------------------------------------------------------------------

    def _predict(self, h: float, u) -> np.ndarray:
        """One step of length ``h`` [s] under tensions u [N]: the state and its covariance
        (:func:`~soft_arm_control.dynamic_estimator_steps.predict_step`); returns the step's Jacobian
        (N, N), valid until the next prediction."""
        m, d = self.model, self.data
        n = m.n
        q, v = self.z[:n].copy(), self.z[n:2 * n].copy()
        if not self._holds(q, v, DYNAMICS):         # the last update leaves its state's terms
            self._evaluate(q, v, DYNAMICS, True)
        if self._rotors:
            kernels.tendon_rate_bias(m.kernel_args[0], m.kernel_args[1], d.xi, v, self._t_read[0],
                                     self._t_read[1], m.kernel_args[15], self._adot)
        kernels.static_tangent(*self.args, q, u, True, *d.kernel_args, self._jac, self._dA_dmu)
        self._routing_derivatives(q, False)
        self.Pz = predict_step(d.M, m.D, d.Kt, d.A, d.A0, self._dA_dmu, self._jac, self._dA, self._dA0,
                               d.Fg, d.Cqd, d.Fel, d.marker_J[-1], d.marker_R[-1], m.gravity, self.rotor,
                               self._adot, np.ascontiguousarray(u, dtype=float), float(h), self._noise,
                               self._parts, self.z, self.Pz, self._share, self._F)
        return self._F

    # --- update ------------------------------------------------------------------------------------

    def update(self, t: float, shortening, rate, tension, markers=None) -> UpdateReport:
        """One sample at time ``t`` [s]: the tendons' shortenings [m], rates [m/s] and tensions [N],
        and ``markers`` (n_markers, 3) [m] in arm_base with NaN rows for the unseen (None: no
        frame). Returns what was used."""
        s, sd, u = (np.ascontiguousarray(v, dtype=float) for v in (shortening, rate, tension))
        if not self.started and not self._begin(t, u, s):
            return UpdateReport()
        c = self.config
        dt = float(t) - self.t
        if not 0.0 <= dt <= c.max_time_step:
            dt = 1.0 / c.rate
        saved = self.z.copy(), self.Pz.copy(), self._share.copy()
        report = UpdateReport()
        try:
            settled = self._settled(dt, sd, u)
            steps = int(np.ceil(dt / c.max_substep - 1e-9))
            u_mean = 0.5 * (u + self.u)
            for _ in range(steps):
                self._predict(dt / steps, u_mean)
            self._measure(s, sd, markers, report, settled)
            self._clamp_parameters()
            self._set_routing()
            # in the domain; and the next prediction's terms, the state unchanged until then
            self._evaluate(self.q, self.qd, DYNAMICS, True)
            # the dynamics follow a moving arm: shortenings that disagree count, moving or not
            self._lost.judge(self.z[self._k], report.tendon_nis, s.size, disagreement_counts=True)
        except (OutOfDomainError, np.linalg.LinAlgError):
            self.counts["out_of_domain"] += 1
            self.z, self.Pz, self._share = saved
            self._set_routing()
            self._lost.out_of_domain()
        self.t, self.u = float(t), u.copy()
        if self._lost.lost:
            self.counts["restarts"] += 1
            self.z, self.Pz = (a.copy() for a in self._prior)
            self._share[:] = 0.0
            self._share[self._load] = 1.0
            self._lost.restarted()
            self._begin(t, u, s)
        if self.second is not None:
            self._second_opinion(t, s, sd, u, markers)
        self.counts["updates"] += 1
        return report

    def _settled(self, dt: float, sd, u) -> bool:
        """Whether the tendons (their rates ``sd`` [m/s], under tensions ``u`` [N], both contiguous
        float arrays as :meth:`update` makes them) have rested :attr:`settling_time` [s] by this
        sample, ``dt`` [s] after the last (the filter's own step, whatever the clock did). A
        rest's settling time is fixed as it starts, from the estimate then: :data:`SETTLING` time
        constants of the slowest mode of the model's dynamics linearised there (the mass with the
        rotors' through the tendons, the damping, the static tangent at the estimated stiffness);
        infinite where no mode of the linearisation decays."""
        if not at_rest(sd, self.config.rest_speed):
            self._rested = None
            return False
        if self._rested is not None:
            self._rested += dt
            return self._rested >= self.settling_time
        m, d = self.model, self.data
        n = m.n
        q, v = self.q.copy(), self.qd.copy()
        if not self._holds(q, v, DYNAMICS):
            self._evaluate(q, v, DYNAMICS, True)
        kernels.static_tangent(*self.args, q, u, True, *d.kernel_args, self._jac, self._dA_dmu)
        mass = d.M + (d.A * self.rotor) @ d.A0.T
        stiffness = self._jac + (self.z[self._k] - 1.0) * d.Kt
        linear = np.zeros((2 * n, 2 * n))
        linear[:n, n:] = np.eye(n)
        linear[n:, :n] = -np.linalg.solve(mass, stiffness)
        linear[n:, n:] = -np.linalg.solve(mass, m.D)
        decay = -float(np.max(np.linalg.eigvals(linear).real))      # the slowest mode's [1/s]
        self.settling_time = SETTLING / decay if decay > 0.0 else np.inf
        self._rested = 0.0
        return False

    def _second_opinion(self, t, s, sd, u, markers):
        """The static filter's update on the same sample; at rest, where both stand by their
        estimates, the gap between them and whether the two tips agree within their covariances."""
        second, heavier = self.second, self._payload_filter
        resting = at_rest(sd, self.config.rest_speed)
        if not resting and not _due(self._second_t, t):
            return                              # in motion it only keeps up (a clock step updates it)
        self._second_t = float(t)
        second.update(t, s, sd, u, markers)
        weighed = heavier is not None and _due(self._payload_t, t)
        if weighed:
            self._payload_t = float(t)
            heavier.update(t, s, sd, u, markers)
        if not resting or second.distrust is not None or self._lost.distrust is not None:
            return
        mine, theirs = self._estimate(), second.estimate()
        self.gap = self.q - second.q, mine.markers - theirs.markers
        if weighed and heavier.distrust is None:
            dq, dp = heavier.q - self.q, heavier.marker_positions() - mine.markers
            self.payload_spread = (PAYLOAD_WEIGHT * np.outer(dq, dq),
                                   PAYLOAD_WEIGHT * np.einsum("ki,kj->kij", dp, dp))
        gap = self.gap[1][-1]
        nis = float(gap @ np.linalg.solve(mine.marker_covariance[-1] + theirs.marker_covariance[-1], gap))
        self._disagree = None
        if nis > self.config.gate:
            self.counts["disagreements"] += 1
            self._disagree = (f"at rest the static balance puts the tip {1e3 * np.linalg.norm(gap):.0f} mm "
                              f"from the estimate (normalised square {nis:.0f})")

    def _clamp_parameters(self):
        """The stiffness scale, friction offsets, routing and payload into what a cast arm can have
        (:attr:`_bounds`)."""
        low, high = self._bounds
        np.clip(self.z[self._k:], low, high, out=self.z[self._k:])

    def _measure(self, s, sd, markers, report, settled: bool):
        m, c, d = self.model, self.config, self.data
        n, N = m.n, self.N
        q, v = self.z[:n].copy(), self.z[n:2 * n].copy()
        self._evaluate(q, v, STATICS, True)
        self._routing_derivatives(q, True)
        H, y, r = self._tendon_rows
        report.tendon_nis = tendon_rows(d.A0, v, self._dL0, self._dLc, self._dA0, self._L0, d.Lc, s, sd,
                                        self._tendon_noise, self._beta, self.Pz, H, y, r)
        if markers is not None:
            markers = np.asarray(markers, dtype=float)
            nm = m.marker_X.size
            report.marker_nis = np.full(nm, np.nan)
            seen = np.flatnonzero(np.all(np.isfinite(markers), axis=1))
            # every seen marker's position Jacobian, noise and innovation at once (k, 3, n)
            Hq = d.marker_R[seen] @ d.marker_J[seen, 3:]
            travel = np.linalg.norm(Hq @ v, axis=1) * c.marker_age
            var = c.marker ** 2 + travel ** 2
            ys = markers[seen] - d.marker_p[seen]
            Ss = Hq @ self.Pz[:n, :n] @ Hq.transpose(0, 2, 1) + var[:, None, None] * np.eye(3)
            nis = np.einsum("ka,ka->k", ys, np.linalg.solve(Ss, ys[:, :, None])[:, :, 0])
            taken = []                                 # indices into seen
            for i, j in enumerate(seen.tolist()):
                report.marker_nis[j] = d2 = float(nis[i])
                if not self._gate.takes(j, d2):
                    report.gated.append(j)
                    continue
                taken.append(i)
                report.used.append(j)
            self.counts["markers_used"] += len(report.used)
            self.counts["markers_gated"] += len(report.gated)
            self.counts["diverged"] = self._gate.diverged
            if taken:                                  # the tendons' rows, then 3 per marker taken
                rows = H.shape[0]
                stacked = np.zeros((rows + 3 * len(taken), N))
                stacked[:rows] = H
                stacked[rows:, :n] = Hq[taken].reshape(-1, n)
                H = stacked
                y = np.concatenate([y, ys[taken].ravel()])
                r = np.concatenate([r, np.repeat(var[taken], 3)])
        # blind (no marker taken): the payload's leverage -- a tendon's millimetre it would explain
        # moves the tip by centimetres -- so the gain is the filter's as if the payload were its
        # estimate: the covariance without the payload's share, which the Joseph form keeps for
        # this gain; the tendons alone do not tell the routing and the payload from the rest:
        # considered, not learnt; nor, in motion or before a rest has settled, the stiffness and
        # friction (module docstring)
        blind = not report.used
        updated, P = gain_update(H, y, r, self.z, self.Pz, self._share, self.config.prior_payload ** 2,
                                 blind, blind and not settled, self._k, self._beta)
        if not updated:
            raise np.linalg.LinAlgError("the innovation covariance is not positive definite")
        self.Pz = P

    def estimate(self) -> ShapeEstimate:
        """The current estimate (markers and their covariance from the model's kinematics), its
        covariances the filter's, the second opinion's :attr:`gap` and the :attr:`payload_spread`."""
        q_gap, marker_gap = self.gap
        q_spread, marker_spread = self.payload_spread
        return self._estimate(np.outer(q_gap, q_gap) + q_spread,
                              np.einsum("ki,kj->kij", marker_gap, marker_gap) + marker_spread)

    def marker_positions(self) -> np.ndarray:
        """The markers (n_markers, 3) [m] in arm_base at the estimated configuration."""
        if not self._holds(self.q, self.qd, KINEMATICS):
            self._evaluate(self.q.copy(), self.qd.copy(), KINEMATICS, True)
        return self.data.marker_p.copy()

    def _estimate(self, q_bias=0.0, marker_bias=0.0) -> ShapeEstimate:
        """The estimate with ``q_bias`` (n, n) added to the configuration's covariance and
        ``marker_bias`` (n_markers, 3, 3) to the markers' (0: the filter's own)."""
        markers = self.marker_positions()
        d = self.data
        H = d.marker_R @ d.marker_J[:, 3:]
        C = H @ self.P @ H.transpose(0, 2, 1) + marker_bias
        return ShapeEstimate(self.t if self.t is not None else 0.0, self.q.copy(), self.P + q_bias,
                             markers, C, self.distrust)
