"""The dynamic fit's segment simulation: what it samples is the stepper's motion, a segment the
model cannot follow is refused, not returned; its Jacobian takes the step it states, and its
threads change nothing."""
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from soft_arm_model import ImexStepper, OutOfDomainError, build_model, load_arm_config, solve_equilibrium
from soft_arm_model.dynamic_identification import _LOG_STEP, DynamicProblem, SegmentData, simulate_changes

STEP = 0.002        # s, the fit's time step
ROTOR = 0.5         # kg


def _segment(arm, tensions, t_input, t_s, t_m):
    n_markers = len(arm.marker_positions)
    return SegmentData(t_input=np.asarray(t_input, dtype=float), tension=np.asarray(tensions, dtype=float),
                       t_start=0.0, u_start=np.zeros(4), t_s=np.asarray(t_s, dtype=float),
                       ds=np.zeros((len(t_s), 4)), t_m=np.asarray(t_m, dtype=float),
                       dp=np.zeros((len(t_m), n_markers, 3)))


def test_the_changes_are_the_steppers_motion_sampled_at_their_stamps():
    """Tension 1 N on tendon 1 from 0.01 s, then tendon 3 from 0.05 s (held between stamps);
    shortenings every 4 ms and markers at three stamps off the step grid: the segment's changes are
    a step-by-step run of the stepper's, sampled at the nearest step, to the bit."""
    arm = load_arm_config()
    tensions = [[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 1.0, 0.0]]
    t_input = [0.0, 0.01, 0.05]
    t_s = np.arange(1, 31) * 0.004
    t_m = [0.0309, 0.0701, 0.1193]
    ds, dp = simulate_changes(arm, ROTOR, _segment(arm, tensions, t_input, t_s, t_m), STEP)

    model = build_model(arm)
    stepper = ImexStepper(model, STEP, rotor_mass=np.full(4, ROTOR))
    q, qd = solve_equilibrium(model, np.zeros(4)).q, np.zeros(model.n)
    stepper.prepare(q, qd, True)
    s_ref = model.rest_tendon_lengths - stepper.data.Lc
    p_ref = stepper.data.marker_p.copy()
    want_s, want_m = {}, {}
    for k in range(int(round(0.12 / STEP)) + 1):
        t = k * STEP
        stepper.prepare(q, qd, True)
        want_s[k] = (model.rest_tendon_lengths - stepper.data.Lc) - s_ref
        want_m[k] = stepper.data.marker_p - p_ref
        j = np.searchsorted(t_input, t, side="right") - 1
        q, qd = stepper.advance(np.array(tensions[j]))
    nearest = [int(np.ceil(t / STEP - 0.5)) for t in t_s]
    np.testing.assert_array_equal(ds, np.array([want_s[k] for k in nearest]))
    np.testing.assert_array_equal(dp, np.array([want_m[int(np.ceil(t / STEP - 0.5))] for t in t_m]))
    assert np.abs(ds[-1]).max() > 1e-3                       # the tendons did move


def test_a_segment_pulled_out_of_the_models_domain_is_refused_not_returned():
    arm = load_arm_config()
    segment = _segment(arm, [[200.0] * 4], [0.0], np.linspace(0.002, 0.5, 250), [0.5])
    with pytest.raises(OutOfDomainError, match="left the model's domain"):
        simulate_changes(arm, ROTOR, segment, STEP)


def _problem(pool=None):
    """Two short segments of the model's own motion as the data (changes measured as zero)."""
    arm = load_arm_config()
    segments = [_segment(arm, [[0.0] * 4, [1.0, 0.0, 0.0, 0.0]], [0.0, 0.01], np.arange(1, 21) * 0.004,
                         [0.03, 0.07]),
                _segment(arm, [[0.0] * 4, [0.0, 0.0, 1.0, 0.5]], [0.0, 0.02], np.arange(1, 16) * 0.004,
                         [0.05])]
    return DynamicProblem(arm, ROTOR, segments, 2e-4, 2e-5, STEP, pool)


def test_the_jacobian_is_the_forward_difference_of_its_fixed_step_also_at_the_start():
    """At p = 0 (the fit's start) each column is (r(p + h e_i) - r(p)) / h with h = _LOG_STEP in
    the log parameter: a step relative to |p| would be zero there (scipy's relative step falls back
    to 1.5e-8, noise-dominated on a simulated residual)."""
    pb = _problem()
    for p in (np.zeros(2), np.array([-0.25, 0.18])):
        J = pb.jacobian(p)
        r0 = pb.residual(p)
        for i in range(2):
            want = (pb.residual(p + _LOG_STEP * np.eye(2)[i]) - r0) / _LOG_STEP
            np.testing.assert_array_equal(J[:, i], want)
        assert np.abs(J).max() > 0.0


def test_threads_simulate_what_the_callers_thread_does_to_the_bit():
    """The segments of a residual and of a Jacobian run on two threads; each simulation is
    deterministic, so the residual and the Jacobian are the caller's thread's, bit for bit."""
    p = np.array([0.3, -0.2])
    serial = _problem()
    with ThreadPoolExecutor(2) as pool:
        threaded = _problem(pool)
        np.testing.assert_array_equal(threaded.residual(p), serial.residual(p))
        np.testing.assert_array_equal(threaded.jacobian(p), serial.jacobian(p))
    assert threaded.evaluations == serial.evaluations == 3     # the residual at p is reused


def _decay(noise_seed=0):
    """y = a exp(-b t) + noise, weighted residual and its exact Jacobian in (log a, log b)."""
    t = np.linspace(0.0, 3.0, 60)
    y = 2.0 * np.exp(-1.3 * t) + 0.01 * np.random.default_rng(noise_seed).standard_normal(t.size)
    calls = []

    def residual(x):
        calls.append(np.array(x))
        return (np.exp(x[0]) * np.exp(-np.exp(x[1]) * t) - y) / 0.01

    def jacobian(x):
        e = np.exp(x[0]) * np.exp(-np.exp(x[1]) * t)
        return np.column_stack([e, -e * np.exp(x[1]) * t]) / 0.01
    return residual, jacobian, calls


def test_the_fit_stops_within_a_twentieth_of_a_standard_error_of_the_optimum():
    """From far off (a 3x, b 0.4x) on a curved problem: the optimum scipy finds at tight tolerances,
    within 0.05 standard errors in each parameter, and no residual evaluated after the last step
    that the data could tell from none."""
    from scipy.optimize import least_squares

    from soft_arm_model.dynamic_identification import levenberg_marquardt, standard_errors
    for seed in range(5):
        residual, jacobian, calls = _decay(seed)
        x0 = np.log([6.0, 0.5])
        x, r, J, converged = levenberg_marquardt(residual, jacobian, x0, 30)
        evaluated = np.array(calls)
        best = least_squares(residual, x0, jac=jacobian, xtol=1e-14, ftol=1e-14, gtol=1e-14)
        se = standard_errors(J, r)
        assert converged and np.all(np.abs(x - best.x) < 0.05 * se), (x - best.x) / se
        np.testing.assert_array_equal(r, residual(x))
        assert np.array_equal(evaluated[-1], x)                   # the last point evaluated is the fit's
        assert np.any(np.abs(evaluated[-1] - evaluated[-2]) >= 0.05 * se)     # and its step mattered


def test_a_fit_at_its_optimum_evaluates_nothing_more_and_one_without_evaluations_says_so():
    from scipy.optimize import least_squares

    from soft_arm_model.dynamic_identification import levenberg_marquardt
    residual, jacobian, calls = _decay(1)
    best = least_squares(residual, np.log([2.0, 1.3]), jac=jacobian, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    calls.clear()
    x, _, _, converged = levenberg_marquardt(residual, jacobian, best.x, 30)
    assert converged and len(calls) == 1 and np.array_equal(x, best.x)
    _, _, _, converged = levenberg_marquardt(residual, jacobian, np.log([6.0, 0.5]), 2)
    assert not converged
