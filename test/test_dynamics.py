"""Dynamics: energy balance, time stepping, statics failure reporting."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from soft_arm_model import (ArmData, EquilibriumError, ImexStepper, evaluate, forward_dynamics,
                            simulate, solve_equilibrium, tip_frame, total_energy)


def _released(model):
    """A bent initial state (equilibrium under tension) released with zero tension."""
    return solve_equilibrium(model, [1.0, 0.0, 1.0, 0.0]).q


def test_energy_is_conserved_without_damping_and_actuation(model_factory):
    m = model_factory(**{"material.viscosity": 0.0, "discretisation.legendre_order": [1, 0],
                         "discretisation.gauss_points": [5, 3]})
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
