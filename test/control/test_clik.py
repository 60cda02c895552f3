"""Underactuated CLIK: decoupled exponential convergence, equilibrium end points, target checks."""
import numpy as np
import pytest
import scipy.linalg

from soft_arm_control.clik import Clik, ClikGains, TargetError, equilibrium_seeds
from soft_arm_control.collocated import CollocatedData, build_collocated, evaluate_collocated
from soft_arm_control.task_space import TaskSpace
from soft_arm_model import ImexStepper, solve_equilibrium

TRIANGLE = TaskSpace((3, 3, 3, 2), (0, 1, 2, 1))
U_TARGET = np.array([1.5, 0.5, 0.5, 1.5])


@pytest.fixture(scope="module")
def clik(paper_model):
    cm = build_collocated(paper_model, (0, 1, 2, 3))
    return Clik(cm, TRIANGLE, ClikGains(2.0, 5.0), (0.05, 5.0))


@pytest.fixture(scope="module")
def target(paper_model):
    q = solve_equilibrium(paper_model, U_TARGET).q
    return TRIANGLE.evaluate(paper_model, q)[0], q


def test_task_error_and_equilibrium_residual_decay_at_their_rates(paper_model, clik, target):
    """Euler integration of the CLIK law from a configuration off the equilibrium set: e decays
    like exp(-2 t) and G_theta_u like exp(-5 t), independently."""
    x_d, q_eq = target
    x_d = x_d + np.array([0.01, -0.005, 0.005, 0.002])
    q = q_eq + 0.03 * clik.cm.selector[2] + 0.02 * clik.cm.selector[5]
    dt, steps = 2e-3, 250
    e0 = g0 = None
    for k in range(steps + 1):
        info = clik.velocity(q, x_d)
        if k == 0:
            e0, g0 = info.error.copy(), info.G_theta_u.copy()
            assert np.linalg.norm(e0) > 1e-3 and np.linalg.norm(g0) > 1e-5
        if k < steps:
            q = q + dt * info.qdot
    t = steps * dt
    assert np.allclose(info.error, e0 * (1 - 2.0 * dt) ** steps, atol=0.02 * np.abs(e0).max())
    assert np.allclose(info.G_theta_u, g0 * (1 - 5.0 * dt) ** steps, atol=0.02 * np.abs(g0).max())
    assert np.linalg.norm(info.error) / np.linalg.norm(e0) == pytest.approx(np.exp(-2.0 * t), rel=0.05)


def test_projectors_split_the_two_feedbacks(paper_model, clik, target):
    x_d, q_eq = target
    P_eps, P_Z = clik.projectors(q_eq)
    cd = clik.cd
    Z_theta = clik._Z @ cd.J_h_inv
    m = TRIANGLE.m
    assert np.allclose(Z_theta[:m] @ P_eps, np.eye(m), atol=1e-8)    # moves the task ...
    assert np.allclose(Z_theta[m:] @ P_eps, 0.0, atol=1e-8)          # ... not the residual
    assert np.allclose(Z_theta[:m] @ P_Z, 0.0, atol=1e-8)
    assert np.allclose(Z_theta[m:] @ P_Z, np.eye(paper_model.n - m), atol=1e-8)


def test_precomputed_end_point_is_an_equilibrium_that_open_loop_tensions_reach(
        paper_model, clik, target):
    x_d, q_eq = target
    start = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    ref = clik.precompute(x_d, start, tol=1e-9)
    assert np.allclose(ref.x, x_d, atol=1e-9)
    cd = evaluate_collocated(clik.cm, CollocatedData(clik.cm), ref.q)
    assert np.abs(cd.G_theta_u).max() < 1e-7 * np.abs(cd.G).max()
    assert np.allclose(ref.u_ff, U_TARGET, atol=1e-6)
    # constant tensions u_eq from the hanging arm: the simulated arm settles on q_d, tip on target
    stepper = ImexStepper(paper_model, 2e-3)
    q, qd = start.copy(), np.zeros(paper_model.n)
    initial = np.abs(start - ref.q).max()
    for _ in range(6000):
        q, qd = stepper.step(q, qd, ref.u_ff)
    assert np.abs(q - ref.q).max() < 1e-3 * initial
    assert np.allclose(TRIANGLE.evaluate(paper_model, q)[0], x_d, atol=1e-4)


def test_end_point_does_not_depend_on_theta_u(paper_model, clik, target):
    x_d, q_eq = target
    start = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    cd = evaluate_collocated(clik.cm, CollocatedData(clik.cm), q_eq)
    dense = build_collocated(paper_model, (0, 1, 2, 3), selector=scipy.linalg.null_space(cd.B.T).T)
    other = Clik(dense, TRIANGLE, ClikGains(2.0, 5.0), (0.05, 5.0))
    a = clik.precompute(x_d, start, tol=1e-10)
    b = other.precompute(x_d, start, tol=1e-10)
    assert np.abs(a.q - b.q).max() < 1e-6
    assert np.abs(a.u_ff - b.u_ff).max() < 1e-6


def test_bad_targets_are_refused_before_anything_moves(paper_model, clik, target):
    start = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    with pytest.raises(TargetError, match="unreachable"):
        clik.precompute([0.3, 0.3, 0.0, 0.0], start)
    tight = Clik(clik.cm, TRIANGLE, ClikGains(2.0, 5.0), (0.05, 1.0))
    with pytest.raises(TargetError, match=r"infeasible: .*tendon_1 would need 1\.500 N"):
        tight.precompute(target[0], start)
    with pytest.raises(TargetError, match="4 finite coordinates"):
        clik.precompute([0.0, np.nan, 0.0, 0.0], start)
    with pytest.raises(ValueError, match="m = n_a"):
        Clik(clik.cm, TaskSpace((3, 3), (0, 2)), ClikGains(1.0, 1.0), (0.0, 5.0))


def test_seeds_find_the_branch_within_limits(paper_model):
    """A task point with several equilibria: from the hanging arm the continuation lands on a
    branch that needs a negative tension; the seed equilibria, and the search on the tensions
    without them, lead to the admissible one."""
    clik = Clik(build_collocated(paper_model, (0, 1, 2, 3)), TRIANGLE, ClikGains(1.0, 1.0),
                (0.05, 5.0))
    x_d = np.array([0.048, 0.123, -0.282, 0.043])
    start = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    q, _ = clik.solve(x_d, start)
    assert clik.reference(q).u_ff.min() < 0.05
    for seeds in ((), equilibrium_seeds(clik, [0.05, 0.6, 1.2, 2.4])):
        ref = clik.precompute(x_d, start, seeds)
        assert np.all(ref.u_ff >= 0.05) and np.allclose(ref.x, x_d, atol=1e-6)


def test_online_step_keeps_the_last_reference_when_a_step_is_infeasible(paper_model, target):
    x_d, q_eq = target
    tight = Clik(build_collocated(paper_model, (0, 1, 2, 3)), TRIANGLE, ClikGains(2.0, 5.0),
                 (0.05, 1.5 + 1e-9))
    # tendons 1 and 4 are at their limit already: a large measured error asks for more
    ref, info = tight.step(q_eq, x_d, 0.5, x=x_d + np.array([0.0, 0.0, 0.02, 0.0]))
    assert ref is None and np.linalg.norm(info.error) > 0.01
    ref, _ = tight.step(q_eq, x_d, 1e-3, x=x_d)
    assert ref is not None and np.allclose(ref.q, q_eq, atol=1e-6)


COILING = TaskSpace((3, 3), (0, 2))


@pytest.fixture(scope="module")
def coiling_clik(paper_model):
    cm = build_collocated(paper_model, (2, 3), held_tension=0.05)
    return Clik(cm, COILING, ClikGains(5.0, 20.0), (0.05, 5.0))


def _model_x(model, u34):
    u = np.concatenate([[0.05, 0.05], np.clip(u34, 0.05, 5.0)])
    return COILING.evaluate(model, solve_equilibrium(model, u).q)[0]


@pytest.mark.parametrize("x_d", [(0.06, -0.36), (-0.10, -0.30)])
def test_an_infeasible_target_leads_to_the_closest_feasible_point_within_the_limits(
        paper_model, coiling_clik, x_d):
    """Targets out of the reach of tensions in [0.05, 5] N: every step's tensions stay within the
    limits, the steps are reported as constrained, and the reference ends at the closest point the
    limits allow (found independently by minimising the distance over the tensions)."""
    from scipy.optimize import minimize
    x_d = np.array(x_d)
    q = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    constrained = 0
    for _ in range(600):
        ref, info = coiling_clik.step(q, x_d, 0.02)
        assert ref is not None and not info.held
        assert np.all(ref.u_ff >= 0.05) and np.all(ref.u_ff <= 5.0)
        constrained += info.constrained
        q = ref.q
    assert constrained > 100
    starts = [(0.1, 0.1), (2.0, 0.1), (0.1, 2.0), (2.0, 2.0), tuple(ref.u_ff)]
    best = min((minimize(lambda u: np.linalg.norm(_model_x(paper_model, u) - x_d), s, method="Nelder-Mead",
                         options={"xatol": 1e-5, "fatol": 1e-9}) for s in starts), key=lambda r: r.fun)
    assert np.linalg.norm(ref.x - x_d) > 0.01                    # the target is out of reach
    assert np.linalg.norm(ref.x - _model_x(paper_model, best.x)) < 5e-4
    assert np.linalg.norm(ref.x - x_d) - best.fun < 5e-4


@pytest.mark.parametrize("x_d", [(0.06, -0.36), (-0.10, -0.30)])
def test_the_closest_feasible_point_is_the_minimum_over_the_tensions(paper_model, coiling_clik, x_d):
    """The search on the tensions (analytic dx/du) ends where Nelder-Mead on the distance ends, with
    tensions within the limits; a feasible target is returned as itself."""
    from scipy.optimize import minimize
    x_d = np.array(x_d)
    start = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    ref = coiling_clik.closest_feasible(x_d, [start], margin=0.0)
    assert np.all(ref.u_ff >= 0.05 - 1e-9) and np.all(ref.u_ff <= 5.0)
    starts = [(0.1, 0.1), (2.0, 0.1), (0.1, 2.0), (2.0, 2.0)]
    best = min((minimize(lambda u: np.linalg.norm(_model_x(paper_model, u) - x_d), s, method="Nelder-Mead",
                         options={"xatol": 1e-6, "fatol": 1e-10}) for s in starts), key=lambda r: r.fun)
    assert np.linalg.norm(ref.x - x_d) > 0.01
    assert np.linalg.norm(ref.x - x_d) <= best.fun + 1e-5
    assert np.linalg.norm(ref.x - _model_x(paper_model, best.x)) < 5e-4
    feasible = _model_x(paper_model, (1.3, 0.8))
    assert np.max(np.abs(coiling_clik.closest_feasible(feasible, [start]).x - feasible)) < 1e-6


def test_the_closest_point_a_refusal_offers_keeps_its_margin_from_the_limits(paper_model):
    """A target out of reach is refused with the closest point whose tensions keep
    ``closest_margin`` from both limits: farther from the target than the closest point on the
    limits, and a feasible target of its own (precompute returns it)."""
    x_d = np.array([0.06, -0.36])
    start = solve_equilibrium(paper_model, np.full(4, 0.05)).q
    cm = build_collocated(paper_model, (2, 3), held_tension=0.05)
    found = {}
    for margin in (0.0, 0.4):
        clik = Clik(cm, COILING, ClikGains(5.0, 20.0), (0.05, 5.0), closest_margin=margin)
        with pytest.raises(TargetError) as info:
            clik.precompute(x_d, start)
        found[margin] = closest = info.value.closest
        assert np.all(closest.u_ff >= 0.05 + margin - 1e-9) and np.all(closest.u_ff <= 5.0 - margin + 1e-9)
    # on the limit itself (no margin), the closest point is infeasible by a rounding error
    assert np.max(np.abs(clik.precompute(found[0.4].x, start).x - found[0.4].x)) < 1e-6
    assert np.min(found[0.4].u_ff) == pytest.approx(0.45, abs=1e-6)      # on the margin, not inside
    assert np.linalg.norm(found[0.4].x - x_d) > np.linalg.norm(found[0.0].x - x_d) + 1e-3


def test_a_feasible_step_is_the_unconstrained_clik_step(paper_model, coiling_clik):
    q = solve_equilibrium(paper_model, np.array([0.05, 0.05, 1.0, 0.5])).q
    x_d = _model_x(paper_model, (1.3, 0.8))
    info = coiling_clik.velocity(q, x_d)
    expected = coiling_clik.reference(q + 0.01 * info.qdot)
    ref, step = coiling_clik.step(q, x_d, 0.01)
    assert not step.constrained and not step.held
    assert np.array_equal(ref.q, expected.q) and np.array_equal(ref.u_ff, expected.u_ff)


def test_the_outer_loop_reports_an_infeasible_goal_instead_of_holding(paper_model, coiling_clik):
    from soft_arm_control.outer_loop import OuterLoop
    start = coiling_clik.reference(solve_equilibrium(paper_model, np.full(4, 0.05)).q)
    outer = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=50.0)
    outer.goal(0.0, np.array([0.06, -0.36]), "online")
    moved = 0
    for k in range(1, 200):
        ref = outer.frame(k * 0.02, outer.reference.x)      # the model's x stands in for the mocap
        moved += ref is not None
    report = outer.reports[-1].as_dict()
    assert moved == report["online_steps"] == 199
    assert report["status"] == "constrained" and report["infeasible_steps"] > 100
    assert report["held_steps"] == 0
    # the bounded steps end at the closest point whose tensions keep the CLIK's own margin from the
    # limits (a thousandth of the range, closest_feasible's default): 4 s at a task gain of 5/s
    # leave e^-20 of the 1.8 cm the error had to fall; a micrometre is a hundredth of the 0.1 mm
    # between that point and the closest one on the limits themselves
    closest = coiling_clik.closest_feasible(np.array([0.06, -0.36]), [start.q])
    assert report["closest_error"] == pytest.approx(np.linalg.norm(closest.x - [0.06, -0.36]), abs=1e-6)
    outer.goal(4.0, np.array(start.x), "online")             # a feasible goal is reported as such
    for k in range(1, 20):
        outer.frame(4.0 + k * 0.02, outer.reference.x)
    assert outer.reports[-1].status == "ok" and len(outer.reports) == 2


def test_a_goal_the_arm_does_not_follow_is_reported_stalled(paper_model, coiling_clik):
    """Every step feasible, but the measured error does not fall (the arm stays where it is): the
    report says stalled after stall_time, and not before; a goal the arm follows is reached."""
    from soft_arm_control.outer_loop import OuterLoop
    start = coiling_clik.reference(solve_equilibrium(paper_model, [0.05, 0.05, 1.0, 1.0]).q)
    outer = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=50.0, reach_tolerance=1e-3,
                      stall_time=1.0)
    x_d = np.array(start.x) + [0.004, 0.003]
    outer.goal(0.0, x_d, "online")
    statuses = []
    for k in range(1, 80):
        outer.frame(k * 0.02, np.array(start.x))               # the arm does not move
        statuses.append(outer.reports[-1].status)
    report = outer.reports[-1].as_dict()
    assert report["infeasible_steps"] == report["held_steps"] == 0
    assert statuses[49] == "ok" and statuses[50] == "stalled" and report["status"] == "stalled"
    assert report["reached"] is False and abs(report["error"] - 0.005) < 1e-9
    outer.goal(2.0, x_d, "online")
    for k in range(1, 400):
        outer.frame(2.0 + k * 0.02, outer.reference.x)     # the arm follows the model
    report = outer.reports[-1].as_dict()
    assert report["status"] == "ok" and report["reached"] is True and report["stalled_steps"] == 0


def test_a_goal_that_ends_away_from_its_target_is_reported_unreached(paper_model, coiling_clik):
    from soft_arm_control.outer_loop import OuterLoop
    start = coiling_clik.reference(solve_equilibrium(paper_model, [0.05, 0.05, 1.0, 1.0]).q)
    outer = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=50.0, stall_time=10.0)
    x_d = np.array(start.x) + [0.004, 0.003]
    outer.goal(0.0, x_d, "online")
    for k in range(1, 20):
        outer.frame(k * 0.02, np.array(start.x))          # the arm lags behind, not yet a stall
    assert outer.reports[-1].status == "ok" and outer.reports[-1].reached is False
    outer.finish()
    assert outer.reports[-1].status == "unreached"


def test_only_a_track_goal_s_online_steps_give_the_inner_loop_a_reference_rate(paper_model, coiling_clik):
    """``reference_rate`` is the online step's change of the shortenings over the CLIK period in a
    goal whose mode is among ``rate_modes`` (a track goal by default), zero otherwise and from every
    new goal on."""
    from soft_arm_control.outer_loop import OuterLoop
    from soft_arm_control.trajectories import Trajectory
    start = coiling_clik.reference(solve_equilibrium(paper_model, [0.05, 0.05, 1.0, 1.0]).q)
    outer = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=50.0)
    x0 = np.array(start.x)
    outer.goal(0.0, x0, "track", trajectory=Trajectory("circle", 0.005, 2.0))
    rates = []
    for k in range(1, 30):
        before = outer.reference.shortening
        ref = outer.frame(k * 0.02, outer.reference.x)
        assert ref is not None
        assert np.allclose(outer.reference_rate, (ref.shortening - before) / 0.02)
        rates.append(np.abs(outer.reference_rate[2:]).max())
    assert min(rates) > 1e-4                      # the path moves the task's tendons all along
    outer.goal(1.0, x0 + [0.002, 0.0], "online")
    assert np.all(outer.reference_rate == 0.0)
    for k in range(1, 10):
        assert outer.frame(1.0 + k * 0.02, outer.reference.x) is not None
        assert np.all(outer.reference_rate == 0.0)    # not among rate_modes: the paper's damping
    both = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=50.0, rate_modes=("online", "track"))
    both.goal(0.0, x0 + [0.002, 0.0], "online")
    both.frame(0.02, both.reference.x)
    assert np.abs(both.reference_rate).max() > 1e-4


def test_the_dynamic_reference_balances_the_path_s_forces_to_first_order(paper_model, coiling_clik):
    """Along a path with velocity eps v and acceleration eps a from an equilibrium q, the forces
    f = (M + m_r A A0^T) qddot + D qdot are linear in eps; the dynamic reference q + dq must hold
    the task point and balance f where the tendons cannot: G_theta_u(q + dq) + (J_h^-T f)_u and
    x(q + dq) - x(q) vanish to second order in eps, and the feedforward is G_theta_a(q + dq) plus
    the actuated part of J_h^-T f. Without motion it is the quasi-static reference itself."""
    from soft_arm_control.collocated import equilibrium_jacobian
    from soft_arm_model.dynamics import mass_matrix
    cm = coiling_clik.cm
    q = solve_equilibrium(paper_model, [0.05, 0.05, 1.0, 1.0]).q
    x0 = coiling_clik.reference(q).x
    v, a = np.array([0.02, -0.01]), np.array([0.8, 1.5])
    residuals = []
    for eps in (0.2, 0.1, 0.05):
        point = coiling_clik.dynamic_reference(q, eps * v, eps * a, rotor_mass=0.6)
        cd = evaluate_collocated(cm, CollocatedData(cm), q)
        Z = np.vstack([COILING.evaluate(paper_model, q)[1], equilibrium_jacobian(cm, cd)])
        qdot, qddot = (np.linalg.solve(Z, np.concatenate([eps * w, np.zeros(paper_model.n - 2)]))
                       for w in (v, a))
        A, A0 = cd.arm.A, cd.arm.A0
        f = mass_matrix(paper_model, q) @ qddot + 0.6 * A @ (A0.T @ qddot) + paper_model.D @ qdot
        forces = np.linalg.solve(cd.J_h.T, f)
        at = evaluate_collocated(cm, CollocatedData(cm), point.q)
        assert np.allclose(point.u_ff, at.u_eq + forces[:2], atol=1e-12)
        residuals.append((np.linalg.norm(at.G_theta_u + forces[2:]), np.linalg.norm(point.x - x0),
                          np.linalg.norm(forces[2:])))
    for (r1, dx1, f1), (r2, dx2, f2) in zip(residuals, residuals[1:]):
        assert f2 == pytest.approx(f1 / 2, rel=1e-6)            # the forces are linear in eps
        assert r2 < 0.3 * r1 and dx2 < 0.3 * dx1                 # the residuals are second order
    assert residuals[-1][0] < 0.02 * residuals[-1][2] and residuals[-1][1] < 1e-5
    still = coiling_clik.dynamic_reference(q, np.zeros(2), np.zeros(2), rotor_mass=0.6)
    ref = coiling_clik.reference(q)
    assert np.allclose(still.q, ref.q) and np.allclose(still.u_ff, ref.u_ff)


def test_a_track_goal_hands_the_inner_loop_the_dynamic_reference_and_integrates_the_static_one(
        paper_model, coiling_clik):
    """With ``track_dynamics`` the command differs from the CLIK's own reference, which stays on
    the equilibrium set; the command's rate is what the inner loop gets; a fixed goal's command is
    the reference."""
    from soft_arm_control.outer_loop import OuterLoop
    from soft_arm_control.trajectories import Trajectory
    start = coiling_clik.reference(solve_equilibrium(paper_model, [0.05, 0.05, 1.0, 1.0]).q)
    path = Trajectory("circle", 0.01, 1.0)
    plain = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=100.0)
    dynamic = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=100.0, track_dynamics=True,
                        rotor_mass=0.6)
    for outer in (plain, dynamic):
        first = outer.goal(0.0, np.array(start.x), "track", trajectory=path)
        assert first is outer.command
    assert np.array_equal(plain.command.q, start.q) and not np.allclose(dynamic.command.q, start.q)
    for k in range(1, 40):
        t = k * 0.01
        before = dynamic.command.shortening
        out = dynamic.frame(t, dynamic.reference.x)
        plain.frame(t, plain.reference.x)
        assert out is dynamic.command and out is not dynamic.reference
        assert np.allclose(dynamic.reference_rate, (out.shortening - before) / 0.01)
        assert np.linalg.norm(dynamic.reference.x - out.x) < 1e-4     # the same task point
    # the CLIK's own references are the same with and without the dynamic command
    assert np.allclose(dynamic.reference.q, plain.reference.q, atol=1e-9)
    dynamic.goal(1.0, np.array(start.x), "online")
    assert dynamic.command is dynamic.reference


def test_a_path_faster_than_the_tendons_is_reported_saturated(paper_model, coiling_clik):
    """A track goal whose dynamic reference needs tensions outside the limits (here: rotors of
    1000 kg on a 1 cm circle at 1 Hz) counts those steps and is saturated, a WARN; with the rotor
    of control.yaml the same path is ok."""
    from soft_arm_control.outer_loop import OuterLoop
    from soft_arm_control.trajectories import Trajectory
    start = coiling_clik.reference(solve_equilibrium(paper_model, [0.05, 0.05, 1.0, 1.0]).q)
    path = Trajectory("circle", 0.01, 1.0)
    reports = {}
    for rotor in (0.6, 1000.0):
        outer = OuterLoop(coiling_clik, start, switch_delay=0.0, rate=100.0, track_dynamics=True,
                          rotor_mass=rotor)
        outer.goal(0.0, np.array(start.x), "track", trajectory=path)
        for k in range(1, 60):
            outer.frame(k * 0.01, outer.reference.x)
        reports[rotor] = outer.reports[-1].as_dict()
    assert reports[0.6]["saturated_steps"] == 0 and reports[0.6]["status"] == "ok"
    assert 0 < reports[1000.0]["saturated_steps"] <= 59 and reports[1000.0]["status"] == "saturated"
    # every status has its level and message on the clik node's /diagnostics
    from soft_arm_control.clik_node import LEVELS, MESSAGES
    from soft_arm_control.outer_loop import STATUSES
    assert set(LEVELS) == set(MESSAGES) == set(STATUSES)
