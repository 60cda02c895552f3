"""Dynamics: energy balance, time stepping, statics failure reporting."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from soft_arm_model import (ArmData, EquilibriumError, ImexStepper, actuation_matrix, evaluate,
                            forward_dynamics, simulate, solve_equilibrium, tip_frame, total_energy)


def _released(model):
    """A bent initial state (equilibrium under tension) released with zero tension."""
    return solve_equilibrium(model, [1.0, 0.0, 1.0, 0.0]).q


@pytest.mark.parametrize("tip_mass", [0.0, 0.01])
def test_energy_is_conserved_without_damping_and_actuation(model_factory, tip_mass):
    m = model_factory(**{"material.viscosity": 0.0, "discretisation.legendre_order": [1, 0],
                         "discretisation.gauss_points": [5, 3], "tip_mass": tip_mass})
    q0 = _released(m)
    data = ArmData(m)

    def rhs(t, x):
        return np.concatenate([x[m.n:], forward_dynamics(m, x[:m.n], x[m.n:], np.zeros(4), data=data)])

    sol = solve_ivp(rhs, (0, 1.0), np.concatenate([q0, np.zeros(m.n)]), method="DOP853",
                    rtol=1e-11, atol=1e-13, t_eval=np.linspace(0, 1, 21))
    energy = np.array([total_energy(m, x[:m.n], x[m.n:], data) for x in sol.y.T])
    kinetic_peak = max(evaluate(m, data, x[:m.n], x[m.n:]).energies[0] for x in sol.y.T)
    assert kinetic_peak > 1e-4  # the arm really moves
    assert np.abs(energy - energy[0]).max() / kinetic_peak < 1e-6


def test_damped_energy_decays_monotonically(paper_model):
    m = paper_model
    traj = simulate(m, _released(m), np.zeros(m.n), lambda t: np.zeros(4), 1.0, dt=1e-3)
    data = ArmData(m)
    energy = np.array([total_energy(m, q, qd, data) for q, qd in zip(traj.q[::10], traj.qd[::10])])
    assert energy[0] - energy[-1] > 1e-3
    assert np.all(np.diff(energy) <= 1e-12)


def test_imex_step_is_stable_at_1ms_and_settles_on_the_static_equilibrium(paper_model):
    m = paper_model
    u = np.array([5.0, 0.0, 5.0, 0.0])
    q0 = solve_equilibrium(m, np.zeros(4)).q
    traj = simulate(m, q0, np.zeros(m.n), lambda t: u if t >= 0.1 else np.zeros(4), 8.0, dt=1e-3)
    assert np.all(np.isfinite(traj.q))
    target = solve_equilibrium(m, u).q
    np.testing.assert_allclose(tip_frame(m, traj.q[-1]).p, tip_frame(m, target).p, atol=1e-5)


def test_imex_converges_at_first_order(paper_model):
    m = paper_model
    q0 = _released(m)
    tips = {}
    for dt in (4e-3, 2e-3, 1e-3, 5e-4):
        tr = simulate(m, q0, np.zeros(m.n), lambda t: np.zeros(4), 0.2, dt=dt)
        tips[dt] = tip_frame(m, tr.q[-1]).p
    e1 = np.linalg.norm(tips[4e-3] - tips[5e-4])
    e2 = np.linalg.norm(tips[2e-3] - tips[5e-4])
    e3 = np.linalg.norm(tips[1e-3] - tips[5e-4])
    assert e1 > e2 > e3 and e1 / e2 > 1.6


def test_equilibrium_failure_is_reported_not_returned(model_factory):
    m = model_factory(**{"material.axial_law": "linear", "material.youngs_modulus": 2e4})
    with pytest.raises(EquilibriumError) as err:
        solve_equilibrium(m, [20.0, 20.0, 20.0, 20.0])
    assert 0.0 <= err.value.reached < 1.0


def test_stepper_rejects_bad_step(paper_model):
    with pytest.raises(ValueError, match="dt must be > 0"):
        ImexStepper(paper_model, 0.0)


def _rotor_ode(m, rotor, data):
    """The continuous dynamics with rotors, written out from the Lagrangian
    T_rotor = 1/2 sum m_k (A0_k^T qd)^2: (M + A0 m A0^T) qdd = F - A0 m (Adot0^T qd) (frictionless)."""
    def rhs(t, x):
        q, qd = x[:m.n], x[m.n:]
        h = 1e-6
        a_plus = actuation_matrix(m, q + h * qd, friction=False, data=data)
        a_minus = actuation_matrix(m, q - h * qd, friction=False, data=data)
        adot_qd = (a_plus - a_minus).T @ qd / (2 * h)
        d = evaluate(m, data, q, qd)
        lhs = d.M + d.A0 @ np.diag(rotor) @ d.A0.T
        force = d.Fg - d.Cqd - m.D @ qd - d.Fel - d.A0 @ (rotor * adot_qd)
        return np.concatenate([qd, np.linalg.solve(lhs, force)])
    return rhs


def test_rotor_inertia_conserves_energy_and_matches_the_stepper(model_factory):
    m = model_factory(**{"material.viscosity": 0.0, "discretisation.legendre_order": [1, 0],
                         "discretisation.gauss_points": [5, 3], "tendons.friction": [0.0] * 4})
    rotor = np.array([0.6, 0.3, 0.6, 0.2])
    data = ArmData(m)
    rhs = _rotor_ode(m, rotor, data)
    q0 = _released(m)
    sol = solve_ivp(rhs, (0, 0.5), np.concatenate([q0, np.zeros(m.n)]), method="DOP853",
                    rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 0.5, 11))

    def energy(x):
        q, qd = x[:m.n], x[m.n:]
        s_rate = actuation_matrix(m, q, friction=False, data=data).T @ qd
        return total_energy(m, q, qd, data) + 0.5 * np.sum(rotor * s_rate ** 2)

    e = np.array([energy(x) for x in sol.y.T])
    rotor_kinetic = max(0.5 * np.sum(rotor * (actuation_matrix(m, x[:m.n], friction=False,
                                                               data=data).T @ x[m.n:]) ** 2)
                        for x in sol.y.T)
    assert rotor_kinetic > 1e-5                       # the rotors do take part in the motion
    assert np.abs(e - e[0]).max() < 1e-6 * (e.max() - e.min() + rotor_kinetic)
    # the stepper's velocity update is the same acceleration: qd+ = qd + h qdd + O(h^2)
    x = sol.y[:, 5]
    q, qd = x[:m.n], x[m.n:]
    qdd = rhs(0.0, x)[m.n:]
    for h in (1e-5, 1e-6):
        _, qd_next = ImexStepper(m, h, friction=False, rotor_mass=rotor).step(q, qd, np.zeros(4))
        assert np.abs((qd_next - qd) / h - qdd).max() < 1e-2 * np.abs(qdd).max() * h / 1e-5


def test_rotor_mass_is_checked(paper_model):
    with pytest.raises(ValueError, match="rotor_mass must be 4 masses"):
        ImexStepper(paper_model, 1e-3, rotor_mass=[1.0, -1.0, 0.0, 0.0])


@pytest.mark.parametrize("method", ["imex", "ros2"])
def test_simulate_takes_the_steps_the_stepper_takes_one_by_one(paper_model, method):
    """simulate() steps in one compiled loop (Stepper.run): the same arithmetic as step() called
    step by step, with the rotors' term and tensions that change over the run."""
    from soft_arm_model.integrators import STEPPERS
    m = paper_model
    rotor = [0.6, 0.0, 0.3, 0.0]

    def tension(t):
        return np.array([2.0 + 3.0 * np.sin(20.0 * t), 0.0, 1.0 + t, 0.5])

    q0 = _released(m)
    traj = simulate(m, q0, np.zeros(m.n), tension, 0.05, dt=2e-3, rotor_mass=rotor, method=method)
    stepper = STEPPERS[method](m, 2e-3, rotor_mass=rotor)
    q, qd = q0, np.zeros(m.n)
    for i in range(traj.t.size - 1):
        q, qd = stepper.step(q, qd, tension(traj.t[i]))
        np.testing.assert_array_equal(traj.q[i + 1], q)
        np.testing.assert_array_equal(traj.qd[i + 1], qd)
    assert np.abs(traj.q[-1] - q0).max() > 1e-3          # it did move


def test_simulate_names_the_time_a_state_left_the_models_domain(model_factory):
    """A soft arm crushed by its tendons (the neo-Hookean stretch driven through zero): the run
    stops at the step that left the domain and says when, instead of returning a trajectory."""
    from soft_arm_model import OutOfDomainError
    m = model_factory(**{"material.youngs_modulus": 2e3})
    with pytest.raises(OutOfDomainError, match=r"left the model's domain.* at t = [0-9.e-]+ s"):
        simulate(m, np.zeros(m.n), np.zeros(m.n), lambda t: np.full(4, 500.0 * t), 2.0, dt=1e-3)


@pytest.mark.parametrize("which", ["paper_model", "full_model"])
def test_the_magnus_steps_on_their_divisions_columns_match_steps_over_every_column(which, request):
    """The kinematics pass steps each division on its own columns (Z and S there, J and Jdot up to
    the division's end and zero beyond); stepping every column gives the same frames, Jacobians,
    twists and rates, and the columns beyond a point's division stay exactly zero."""
    from soft_arm_model import kernels
    from soft_arm_model.model import XI_STAR
    from soft_arm_model.dynamics import CORIOLIS
    model = request.getfixturevalue(which)
    rng = np.random.default_rng(3)
    q = solve_equilibrium(model, [1.5, 0.5, 2.0, 0.0]).q + 0.05 * rng.normal(size=model.n)
    qd = rng.normal(size=model.n)
    d = evaluate(model, ArmData(model), q, qd, level=CORIOLIS)
    n, P = model.n, model.X.size
    R, p, J = d.R[0].copy(), d.p[0].copy(), d.J[0].copy()
    eta, psi, Jd = d.eta[0].copy(), d.psi[0].copy(), d.Jd[0].copy()
    h, B1, B2 = model.kernel_args[3], model.kernel_args[4], model.kernel_args[5]
    col_hi = model.kernel_args[20]
    scratch = kernels.new_scratch(n)
    full = np.uint64(n)
    inside = 0                         # points whose division ends before the last column
    for i in range(P - 1):
        R1, p1, J1 = np.empty((3, 3)), np.empty(3), np.empty((6, n))
        eta1, psi1, Jd1 = np.empty(6), np.empty(6), np.empty((6, n))
        kernels._magnus_step(q, qd, XI_STAR, h[i], B1[i], B2[i], np.uint64(0), full, R, p, J, R1, p1, J1,
                             2, eta, psi, Jd, eta1, psi1, Jd1, scratch, np.empty(6), np.empty((6, n)),
                             np.empty((6, n)))
        R, p, J, eta, psi, Jd = R1, p1, J1, eta1, psi1, Jd1
        for mine, reference in ((d.R[i + 1], R), (d.p[i + 1], p), (d.J[i + 1], J), (d.eta[i + 1], eta),
                                (d.psi[i + 1], psi), (d.Jd[i + 1], Jd)):
            scale = max(1.0, np.abs(reference).max())
            np.testing.assert_allclose(mine, reference, rtol=1e-12, atol=1e-12 * scale)
        hi = col_hi[i + 1]
        if 0 < hi < n:                 # a point inside the first division: nothing beyond it moves it
            inside += 1
            assert np.all(d.J[i + 1][:, hi:] == 0.0) and np.all(d.Jd[i + 1][:, hi:] == 0.0)
    assert inside > 0                  # both models have a division that ends before the last column
