"""Time stepping of the arm: a linearly implicit (IMEX) Euler step, stable at millisecond steps.

The axial and torsional modes of the soft cone are stiff (hundreds of Hz, heavily damped), so the
elastic and damping forces are taken implicitly, linearised about the current state, and the rest
(gravity, Coriolis, tendons) explicitly:

    (M + h D + h^2 K_t) qd+ = M qd + h (F_g - C qd - F_el(q) - A u),    q+ = q + h qd+

This is first-order accurate and unconditionally stable for the linear stiff part.

Motor rotors on the tendons (direct drive) add their reflected mass m_k = J_k / r_k^2 [kg] to the
tendon coordinate: with an inextensible tendon the rotor turns with the shortening s_k, and the
tension that reaches the body is u_k - m_k s_k'' with s'' = -(A0^T qdd + Adot0^T qd). So u is the
tension the motor applies (torque / radius) and

    (M + A diag(m) A0^T) qdd + ... = ... - A (u + diag(m) Adot0^T qd),

with Adot0^T qd in closed form from the strains and their rates
(:func:`~soft_arm_model.kernels.tendon_rate_bias`).

:class:`Ros2Stepper` is the second-order alternative: the two-stage Rosenbrock-W method ROS2
(Verwer, Spee, Blom and Hundsdorfer, SIAM J. Sci. Comput. 20(4), 1999) on y = (q, qd), with the
same linear part (the elastic tangent and the damping) as its W matrix:

    W = M_eff + g h D + (g h)^2 K_t,  g = 1 + 1/sqrt(2),
    (I - g h J) k1 = f(y),  (I - g h J) k2 = f(y + h k1) - 2 k1,  y+ = y + h (3 k1 + k2) / 2,

with J = [[0, I], [-M_eff^-1 K_t, -M_eff^-1 D]]. ROS2 is second order whatever W is (a W-method),
so the explicit forces' own derivatives are not needed, and L-stable, so the stiff axial and
torsional modes are damped at any step as the Euler step damps them. It costs two evaluations of
the dynamics per step where the Euler step costs one; its error falls with h^2 where the Euler
step's falls with h, so at the Euler step's accuracy it steps four to five times further
(``bench/bench_model.py`` measures both against a fine reference).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_arm_model import kernels

from .dynamics import OutOfDomainError
from .lie import nonallocating_strict
from .model import ArmData, ArmModel
from .statics import _lu_solve


@nonallocating_strict
def _imex_prepare(model_args, data_args, rotor_mass, q, qd, markers, adot_qd):
    """Evaluate the workspace at (q, qd) (dynamics level, markers if asked) and, with rotors, the
    tendon acceleration term Adot0^T qd into adot_qd."""
    if not kernels.evaluate(*model_args, q, qd, 2, markers, *data_args):
        return False
    for k in range(adot_qd.shape[0]):
        adot_qd[k] = 0.0
    for k in range(rotor_mass.shape[0]):
        if rotor_mass[k] != 0.0:
            kernels.tendon_rate_bias(model_args[0], model_args[1], data_args[0], qd, model_args[12],
                                     model_args[13], model_args[15], adot_qd)
            break
    return True


@nonallocating_strict
def _imex_advance(rotor_mass, adot_qd, M, Cqd, Fg, Fel, Kt, Au, A0, D, work, q, qd, u, f_ext, h, q_out,
                  qd_out):
    """The IMEX update from the prepared workspace (M .. A0 at (q, qd); Au: A or A0); f_ext: an
    external generalised force, taken explicitly. ``work``: (the step's matrix and its LU factors
    (2, n, n), its right-hand side (1, n), the pivots (n,) int). False if the step's matrix is
    singular. The system is solved by :func:`~soft_arm_model.statics._lu_solve`, as the statics'
    are: nothing allocated per step, and the same rounding whatever kernels the BLAS picks. The
    arguments are :func:`_ros2_advance`'s but the model's and the workspace's, which this step does
    not evaluate: a call from Python unboxes each array it is passed, and those two tuples' fifty
    arrays made a step of the simulated rig a tenth slower (``bench/bench_model.py``'s
    ``rig_step``)."""
    mats, vecs, piv = work
    lhs, lu, rhs = mats[0], mats[1], vecs[0]
    n = q.shape[0]
    n_t = u.shape[0]
    for a in range(n):
        acc = 0.0
        for b in range(n):
            lhs[a, b] = M[a, b] + h * D[a, b] + (h * h) * Kt[a, b]
            acc += M[a, b] * qd[b]
        rhs[a] = acc
    for k in range(n_t):              # the rotors' reflected mass on the tendon coordinates
        m = rotor_mass[k]
        if m == 0.0:
            continue
        s_rate = 0.0
        for b in range(n):
            s_rate += A0[b, k] * qd[b]
        for a in range(n):
            f = Au[a, k] * m
            for b in range(n):
                lhs[a, b] += f * A0[b, k]
            rhs[a] += f * s_rate
    for a in range(n):
        acc = Fg[a] - Cqd[a] - Fel[a] + f_ext[a]
        for k in range(n_t):
            acc -= Au[a, k] * (u[k] + rotor_mass[k] * adot_qd[k])
        rhs[a] += h * acc
    if not _lu_solve(lhs, rhs, qd_out, lu, piv):
        return False
    for a in range(n):
        q_out[a] = q[a] + h * qd_out[a]
    return True


ROS2_GAMMA = 1.0 + 1.0 / np.sqrt(2.0)


@nonallocating_strict
def _ros2_balance(M, Cqd, Fg, Fel, Au, A0, D, rotor_mass, adot_qd, qd, u, f_ext, M_eff, force):
    """At the evaluated state: M_eff = M + Au diag(m) A0^T (the mass with the rotors' reflected
    mass) and force = F_g - C qd - F_el - D qd - Au (u + m Adot0^T qd) + f_ext."""
    n, n_t = M.shape[0], rotor_mass.shape[0]
    for a in range(n):
        acc = Fg[a] - Cqd[a] - Fel[a] + f_ext[a]
        for b in range(n):
            M_eff[a, b] = M[a, b]
            acc -= D[a, b] * qd[b]
        for k in range(n_t):
            acc -= Au[a, k] * (u[k] + rotor_mass[k] * adot_qd[k])
        force[a] = acc
    for k in range(n_t):
        if rotor_mass[k] != 0.0:
            for a in range(n):
                s = Au[a, k] * rotor_mass[k]
                for b in range(n):
                    M_eff[a, b] += s * A0[b, k]


@nonallocating_strict
def _ros2_advance(model_args, data_args, rotor_mass, adot_qd, M, Cqd, Fg, Fel, Kt, Au, A0, D, work,
                  q, qd, u, f_ext, h, q_out, qd_out):
    """One ROS2 step from the prepared workspace (at (q, qd)); evaluates the workspace again at the
    second stage. ``work``: (5 n x n matrices, 8 n-vectors, n pivots). Returns False if a linear
    system is singular or the second stage is outside the model's domain."""
    mats, vecs, piv = work
    M1, W, lu, K1, M2 = mats[0], mats[1], mats[2], mats[3], mats[4]
    force, rhs, k1q, k1v, k2v = vecs[0], vecs[1], vecs[2], vecs[3], vecs[4]
    q2, v2, a2 = vecs[5], vecs[6], vecs[7]
    n = q.shape[0]
    g = ROS2_GAMMA * h
    _ros2_balance(M, Cqd, Fg, Fel, Au, A0, D, rotor_mass, adot_qd, qd, u, f_ext, M1, force)
    for a in range(n):
        acc = force[a]
        for b in range(n):
            W[a, b] = M1[a, b] + g * D[a, b] + g * g * Kt[a, b]
            acc -= g * Kt[a, b] * qd[b]
        rhs[a] = acc
    if not _lu_solve(W, rhs, k1v, lu, piv):
        return False
    for a in range(n):
        k1q[a] = qd[a] + g * k1v[a]
        q2[a] = q[a] + h * k1q[a]
        v2[a] = qd[a] + h * k1v[a]
    # the second stage's right-hand side needs K_t of the first: keep it before the evaluation
    for a in range(n):
        for b in range(n):
            K1[a, b] = Kt[a, b]
    if not _imex_prepare(model_args, data_args, rotor_mass, q2, v2, False, adot_qd):
        return False
    _ros2_balance(M, Cqd, Fg, Fel, Au, A0, D, rotor_mass, adot_qd, v2, u, f_ext, M2, force)
    if not _lu_solve(M2, force, a2, lu, piv):
        return False
    # g2 = (v2 - 2 k1q, a2 - 2 k1v); rhs = M1 g2v - g K1 g2q; k2q = g2q + g k2v
    for a in range(n):
        acc = 0.0
        for b in range(n):
            acc += M1[a, b] * (a2[b] - 2.0 * k1v[b]) - g * K1[a, b] * (v2[b] - 2.0 * k1q[b])
        rhs[a] = acc
    if not _lu_solve(W, rhs, k2v, lu, piv):
        return False
    for a in range(n):
        k2q = v2[a] - 2.0 * k1q[a] + g * k2v[a]
        q_out[a] = q[a] + h * (1.5 * k1q[a] + 0.5 * k2q)
        qd_out[a] = qd[a] + h * (1.5 * k1v[a] + 0.5 * k2v[a])
    return True


@nonallocating_strict
def _run(prepare_args, advance_args, second_order, f_ext, h, u, q, qd):
    """Steps from (q[0], qd[0]) under the tensions u[i] held over step i, into the rows of q and qd:
    ROS2 steps if ``second_order``, else Euler steps; the number of steps taken (see
    :meth:`ImexStepper.run`)."""
    model_args, data_args, rotor_mass, adot = prepare_args
    for i in range(u.shape[0] - 1):
        if not _imex_prepare(model_args, data_args, rotor_mass, q[i], qd[i], False, adot):
            return i
        if second_order:
            ok = _ros2_advance(model_args, data_args, *advance_args, q[i], qd[i], u[i], f_ext, h, q[i + 1],
                               qd[i + 1])
        else:
            ok = _imex_advance(*advance_args, q[i], qd[i], u[i], f_ext, h, q[i + 1], qd[i + 1])
        if not ok:
            return i
    return u.shape[0] - 1


class ImexStepper:
    """Advances (q, qd) by fixed steps ``dt`` [s] under tendon tensions u [N]; owns its workspace.

    ``rotor_mass``: reflected rotor mass [kg] per tendon (rotor inertia / pulley radius^2), or None.
    ``step`` does both halves; ``prepare`` then ``advance`` split them, so that a caller can read the
    workspace ``data`` at the current state (tendon lengths, markers: the sensors) before choosing u.
    """

    def __init__(self, model: ArmModel, dt: float, friction: bool = True, rotor_mass=None):
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        rotor = np.zeros(model.n_tendons) if rotor_mass is None else \
            np.array(rotor_mass, dtype=float).reshape(-1)
        if rotor.shape != (model.n_tendons,) or not np.all(np.isfinite(rotor)) or np.any(rotor < 0):
            raise ValueError(f"rotor_mass must be {model.n_tendons} masses >= 0 kg, got {rotor_mass}")
        self.model, self.dt, self.friction = model, float(dt), friction
        self.data = d = ArmData(model)
        self._adot = np.zeros(model.n_tendons)
        self._no_force = np.zeros(model.n)
        self._prepare_args = (model.kernel_args, d.kernel_args, rotor)
        self._advance_args = (rotor, self._adot, d.M, d.Cqd, d.Fg, d.Fel, d.Kt, d.A if friction else d.A0,
                              d.A0, model.D, self._new_work(model.n))
        self._state = None

    second_order = False      # the compiled loop's choice of step (:func:`_run`)

    @staticmethod
    def _new_work(n: int) -> tuple:
        """The step's scratch: (n x n matrices, n-vectors, n pivots), as its advance kernel reads it."""
        return np.zeros((2, n, n)), np.zeros((1, n)), np.zeros(n, dtype=np.int64)

    @property
    def compiled_args(self) -> tuple:
        """(prepare arguments, advance arguments) of the compiled halves of the step,
        ``_imex_prepare(*prepare_args[:3], q, qd, markers, prepare_args[3])`` and
        ``_imex_advance(*advance_args, q, qd, u, f_ext, dt, q_out, qd_out)`` (False: the step's
        matrix is singular; :class:`Ros2Stepper`'s step is ``_ros2_advance(*prepare_args[:2],
        *advance_args, ...)``): for a compiled loop that steps without Python in between (the
        workspace is ``data``'s)."""
        return self._prepare_args + (self._adot,), self._advance_args

    def prepare(self, q, qd, markers: bool = False):
        """Evaluate ``data`` at (q, qd) (dynamics terms, markers if asked). Raises OutOfDomainError
        if the state is outside the model's domain."""
        q = np.ascontiguousarray(q, dtype=float)
        qd = np.ascontiguousarray(qd, dtype=float)
        if not _imex_prepare(*self._prepare_args, q, qd, markers, self._adot):
            raise OutOfDomainError("the state left the model's domain")
        self._state = (q, qd)

    def advance(self, u, f_ext=None):
        """(q, qd) one step after the prepared state under tensions u [N] and an optional external
        generalised force ``f_ext`` (e.g. a payload's weight through a Jacobian), both held over the
        step (new arrays). Raises OutOfDomainError if the step cannot be taken."""
        if self._state is None:
            raise RuntimeError("advance() needs a prepare() first")
        q, qd = self._state
        self._state = None
        q_out = np.empty_like(q)
        qd_out = np.empty_like(qd)
        f_ext = self._no_force if f_ext is None else np.ascontiguousarray(f_ext, dtype=float)
        if not self._advance_kernel(q, qd, np.ascontiguousarray(u, dtype=float), f_ext, q_out, qd_out):
            raise OutOfDomainError("the step left the model's domain, or its linear system is singular")
        return q_out, qd_out

    def _advance_kernel(self, q, qd, u, f_ext, q_out, qd_out) -> bool:
        """The step from the prepared workspace into q_out, qd_out; False if it cannot be taken."""
        return _imex_advance(*self._advance_args, q, qd, u, f_ext, self.dt, q_out, qd_out)

    def step(self, q, qd, u):
        """Return (q, qd) one step later (new arrays). Raises OutOfDomainError if the state leaves
        the model's domain."""
        self.prepare(q, qd)
        return self.advance(u)

    def run(self, q, qd, u) -> int:
        """Step from (q[0], qd[0]) under the tensions u[i] [N] held over step i (u: (N + 1, n_t)),
        into the rows 1..N of q and qd ((N + 1, n) each, C-ordered), in one compiled loop; the
        number of steps taken: fewer than N if a state left the model's domain or a step's linear
        system was singular (the rows after it are left as they were)."""
        return _run(self._prepare_args + (self._adot,), self._advance_args, self.second_order,
                    self._no_force, self.dt, u, q, qd)


class Ros2Stepper(ImexStepper):
    """Advances (q, qd) by fixed steps ``dt`` [s] with the second-order Rosenbrock-W step ROS2 (module
    docstring); the same interface, rotors and external force as :class:`ImexStepper`.

    ``advance`` evaluates the workspace again at the step's second stage: ``data`` describes the
    prepared state only until then.
    """

    second_order = True

    @staticmethod
    def _new_work(n: int) -> tuple:
        return np.zeros((5, n, n)), np.zeros((8, n)), np.zeros(n, dtype=np.int64)

    def _advance_kernel(self, q, qd, u, f_ext, q_out, qd_out) -> bool:
        """The ROS2 step from the prepared workspace; False if its second stage is outside the
        model's domain or a linear system is singular."""
        return _ros2_advance(*self._prepare_args[:2], *self._advance_args, q, qd, u, f_ext, self.dt, q_out,
                             qd_out)


STEPPERS = {"imex": ImexStepper, "ros2": Ros2Stepper}


@dataclass(frozen=True)
class Trajectory:
    """Sampled simulation: times t [s] (N,), coordinates q (N, n), rates qd (N, n), tensions u (N, n_t)."""
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    u: np.ndarray


def simulate(model: ArmModel, q0, qd0, tension, duration: float, dt: float = 1e-3,
             friction: bool = True, rotor_mass=None, method: str = "imex") -> Trajectory:
    """Simulate ``duration`` [s] with the ``method``'s step (``imex``: :class:`ImexStepper`, first
    order; ``ros2``: :class:`Ros2Stepper`, second order); ``tension(t)`` returns tensions [N] at
    time t, held over each step (``rotor_mass``: see :class:`ImexStepper`)."""
    if method not in STEPPERS:
        raise ValueError(f"method must be one of {sorted(STEPPERS)}, got {method!r}")
    stepper = STEPPERS[method](model, dt, friction, rotor_mass)
    steps = int(round(duration / dt))
    t = np.arange(steps + 1) * dt
    q = np.zeros((steps + 1, model.n))
    qd = np.zeros((steps + 1, model.n))
    u = np.zeros((steps + 1, model.n_tendons))
    q[0], qd[0] = q0, qd0
    for i in range(steps + 1):        # open loop: the tensions depend on time alone
        u[i] = tension(t[i])
    taken = stepper.run(q, qd, u)
    if taken < steps:
        raise OutOfDomainError(f"the state left the model's domain, or a step's linear system is singular, "
                               f"at t = {t[taken]:.6g} s")
    return Trajectory(t, q, qd, u)
