"""P-satI-D+: the law itself, and regulation of a simulated arm with and without model error."""
import numpy as np
import pytest

from soft_arm_control.actuation_map import ActuationMap, _monomials
from soft_arm_control.collocated import CollocatedData, build_collocated, evaluate_collocated
from soft_arm_control.inner_loop import InnerLoopGains, PSatID
from soft_arm_drivers.sim.simulated_rig import Plant
from soft_arm_model import solve_equilibrium

ALL = (0, 1, 2, 3)
NO_FRICTION = {"tendons.friction": [0.0] * 4}


def _gains(kp=1500.0, kd=120.0, ki=3000.0, u_max=5.0, rate=0.0, n=4):
    return InnerLoopGains(np.full(n, kp), np.full(n, kd), np.full(n, ki), 0.01, 0.05, u_max, rate)


def test_one_step_is_the_paper_law():
    g = InnerLoopGains(np.array([100.0, 200.0]), np.array([3.0, 4.0]), np.array([10.0, 20.0]), 0.01,
                       0.0, 50.0)
    pid = PSatID(g, ActuationMap.identity(), (1, 3), 4, max_time_step=1.0)
    s, sd, s_ref, u_ff = np.array([0, 0.01, 0, 0.02]), np.array([0, 0.1, 0, -0.2]), \
        np.array([0, 0.015, 0, 0.01]), np.array([1.0, 2.0])
    pid.update(0.0, s, sd, s_ref, u_ff)
    u = pid.update(0.5, s, sd, s_ref, u_ff)
    e = np.array([0.005, -0.01])
    xi = 0.5 * 0.01 * np.tanh(e / 0.01)
    expected = g.proportional * e - g.derivative * np.array([0.1, -0.2]) + g.integral * xi + u_ff
    assert np.allclose(u[[1, 3]], expected)
    assert np.allclose(u[[0, 2]], 0.0)      # inactive tendons hold the pretension (0 here)
    assert np.allclose(pid.xi, xi)
    # a moving reference: the derivative term damps the rate error, G_D (thetadot_d - thetadot)
    s_ref_dot = np.array([0.3, 0.05, -0.2, 0.1])
    moving = pid.update(1.0, s, sd, s_ref, u_ff, s_ref_dot)
    assert np.allclose(moving[[1, 3]] - pid.update(1.0, s, sd, s_ref, u_ff)[[1, 3]],
                       g.derivative * s_ref_dot[[1, 3]])


def _law(g, amap, active, state, t, s, sd, s_ref, u_ff, s_ref_dot):
    """The P-satI-D+ law written out in numpy (the module docstring's), one update of ``state``
    (xi, u, t) on the active tendons; the new state."""
    xi_old, u_old, t_old = state
    a = list(active)
    dt = 0.0 if t_old is None else t - t_old
    theta, theta_dot = amap(s)[a], (amap.jacobian(s) @ sd)[a]
    theta_ref_dot = (amap.jacobian(s_ref) @ s_ref_dot)[a]
    e = amap(s_ref)[a] - theta
    xi = xi_old + dt * g.integral_saturation * np.tanh(e / g.integral_saturation)
    u_pd = g.proportional * e + g.derivative * (theta_ref_dot - theta_dot) + u_ff
    u_raw = u_pd + g.integral * xi
    wind = ((u_raw > g.tension_max) & (xi > xi_old)) | ((u_raw < g.tension_min) & (xi < xi_old))
    xi = np.where(wind, xi_old, xi)
    u_a = u_pd + g.integral * xi
    if g.tension_rate_limit > 0:                        # the first update: no step in no time
        step = g.tension_rate_limit * dt
        u_a = np.clip(u_a, u_old[a] - step, u_old[a] + step)
    u = np.full(u_old.size, g.tension_min)
    u[a] = np.clip(u_a, g.tension_min, g.tension_max)
    return xi, u, t


@pytest.mark.parametrize("polynomial", [False, True])
def test_the_compiled_update_is_the_law_with_either_map(polynomial):
    """Random states, references (fixed, and moving every other update) and feedforwards that
    saturate, wind up and meet the rate limit: the compiled update equals the law written out, with
    the identity and with a polynomial map."""
    rng = np.random.default_rng(3)
    exps = _monomials(4, 2)
    amap = ActuationMap(exps, np.eye(4, len(exps), 1) + 0.05 * rng.standard_normal((4, len(exps))),
                        0.0, 0.0, 0) if polynomial else ActuationMap.identity()
    g = InnerLoopGains(np.array([1500.0, 900.0, 1200.0]), np.array([120.0, 80.0, 100.0]),
                       np.array([3000.0, 1000.0, 2000.0]), 0.01, 0.05, 5.0, 40.0)
    active = (0, 2, 3)
    pid, state = PSatID(g, amap, active, 4, max_time_step=0.5), (np.zeros(3), np.full(4, 0.05), None)
    outputs = []
    for k in range(300):
        s, sd = 0.02 * rng.standard_normal(4), 0.1 * rng.standard_normal(4)
        s_ref, u_ff = 0.02 * rng.standard_normal(4), rng.uniform(0.0, 6.0, 3)
        s_ref_dot = 0.1 * rng.standard_normal(4) if k % 2 else None
        dt = 0.002 if k % 3 else 0.2                    # long steps let the output reach the limits
        t = (state[2] or 0.0) + dt
        u = pid.update(t, s, sd, s_ref, u_ff, s_ref_dot)
        state = _law(g, amap, active, state, t, s, sd, s_ref, u_ff,
                     np.zeros(4) if s_ref_dot is None else s_ref_dot)
        np.testing.assert_allclose(u, state[1], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(pid.xi, state[0], rtol=1e-12, atol=1e-15)
        outputs.append((dt, u[list(active)]))
    steps = [np.abs(u1 - u0) for (_, u0), (dt, u1) in zip(outputs, outputs[1:]) if dt == 0.002]
    assert any(np.any(u == 5.0) for _, u in outputs) and any(np.any(u == 0.05) for _, u in outputs)
    assert any(np.any(np.isclose(d, 40.0 * 0.002)) for d in steps)            # rate limited


def test_rejects_bad_input_and_keeps_its_state():
    pid = PSatID(_gains(), ActuationMap.identity(), ALL, 4)
    z = np.zeros(4)
    pid.update(1.0, z, z, z + 0.001, z)
    xi = pid.xi.copy()
    with pytest.raises(ValueError, match="non-finite"):
        pid.update(1.1, np.array([0, np.nan, 0, 0]), z, z, z)
    for stamp in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="no finite time"):
            pid.update(stamp, z, z, z + 0.001, z)
    assert np.array_equal(pid.xi, xi) and pid.t == 1.0 and pid.clock.steps == 0
    with pytest.raises(ValueError, match=">= 0"):
        _gains(kp=-1.0)
    with pytest.raises(ValueError, match="tension_min < tension_max"):
        InnerLoopGains(np.ones(4), np.ones(4), np.ones(4), 0.01, 5.0, 1.0)


def test_rate_limit_and_clipping():
    pid = PSatID(_gains(rate=10.0), ActuationMap.identity(), ALL, 4)
    z = np.zeros(4)
    u0 = pid.update(0.0, z, z, z, z)
    u1 = pid.update(0.01, z, z, z + 1.0, z)          # a huge error asks for far more than 5 N
    assert np.allclose(u1 - u0, 0.1)                   # 10 N/s over 10 ms
    for k in range(2, 200):
        u = pid.update(0.01 * k, z, z, z + 1.0, z)
        assert np.all(u <= 5.0) and np.all(u >= 0.05)
    assert np.allclose(u, 5.0)


def test_the_rate_limit_holds_from_the_first_regulated_update_on():
    """The node holds the pretension until the first reference, then regulates: the first update
    after it steps by what the limit allows in no time (nothing; it stepped 4.95 N at once, the
    limit skipped before the loop had a last stamp), each later one by at most 10 N/s x 2 ms."""
    from soft_arm_control.inner_loop import TendonController
    tc = TendonController(4, _gains(rate=10.0), ActuationMap.identity(), ALL)
    s = np.zeros(4)
    for k in range(5):
        assert np.allclose(tc.update(0.002 * k, s, s), 0.05)
    tc.set_reference(s + 0.01, [0.5] * 4)
    outputs = [tc.update(0.002 * k, s, s) for k in range(5, 12)]
    steps = np.diff(np.vstack([np.full(4, 0.05)] + outputs), axis=0)
    assert np.allclose(steps[0], 0.0) and np.all(np.abs(steps) <= 10.0 * 0.002 + 1e-12)
    assert np.allclose(steps[1:], 0.02)                   # the error asks for far more


def test_an_integral_gain_changed_while_holding_a_load_steps_no_tension():
    """The integral holds part of the tension; doubling its gain, or halving it, leaves the output
    of the same sample the same (the state rescaled), and the loop goes on integrating."""
    from dataclasses import replace

    from soft_arm_control.inner_loop import TendonController
    tc = TendonController(4, _gains(ki=3000.0), ActuationMap.identity(), ALL)
    s = np.zeros(4)
    tc.set_reference(s + 2e-4, [0.5] * 4)
    for k in range(200):
        u = tc.update(0.002 * k, s, s)
    assert np.all(tc.pid.xi > 0)
    t = 0.002 * 199
    for ki in (6000.0, 1500.0):
        tc.set_gains(replace(tc.gains, integral=np.full(4, ki)))
        np.testing.assert_allclose(tc.update(t, s, s), u, rtol=0, atol=1e-12)   # the same sample
    assert np.all(tc.update(t + 0.002, s, s) > u)                              # integrating on


def _regulate(ctrl_model, plant_model, u_target, gains, duration, rotor_mass=0.6, dt=1e-3):
    """Inner loop alone on a simulated plant, reference = the controller model's equilibrium at
    u_target. Returns (times, shortening errors, tensions, integral states, plant, q_d)."""
    cm = build_collocated(ctrl_model, ALL, friction=False)
    q_d = solve_equilibrium(ctrl_model, np.asarray(u_target, dtype=float), friction=False).q
    cd = evaluate_collocated(cm, CollocatedData(cm), q_d)
    s_d, u_ff = cd.shortening.copy(), cd.u_eq.copy()
    plant = Plant(plant_model, dt, rotor_mass)
    plant.settle(np.full(4, gains.tension_min))
    pid = PSatID(gains, ActuationMap.identity(), ALL, 4)
    log = []
    for k in range(int(round(duration / dt))):
        t = k * dt
        plant.sense()
        if k % 2 == 0:
            s, sd = plant.tendons()
            u = pid.update(t, s, sd, s_d, u_ff)
            log.append((t, s - s_d, u, pid.xi.copy()))
        plant.step(u)
    t, e, u, xi = (np.array(v) for v in zip(*log))
    return t, e, u, xi, plant, q_d


def test_exact_model_regulates_to_zero_error(model_factory):
    model = model_factory(**NO_FRICTION)
    t, e, u, _, plant, q_d = _regulate(model, model, [1.2, 0.4, 0.9, 0.3], _gains(), 12.0)
    assert np.abs(e[-1]).max() < 1e-5 * np.abs(e[0]).max()
    assert np.abs(plant.q - q_d).max() < 1e-4        # theta_u lands on the model's equilibrium too
    assert np.allclose(u[-1], [1.2, 0.4, 0.9, 0.3], atol=1e-3)


def test_integral_removes_the_offset_under_model_error(model_factory):
    model = model_factory(**NO_FRICTION)
    stiffer = model_factory(**NO_FRICTION, **{"material.youngs_modulus": 1.8e5})
    target = [1.2, 0.4, 0.9, 0.3]
    _, e_i, _, _, _, _ = _regulate(model, stiffer, target, _gains(), 8.0)
    _, e_p, _, _, _, _ = _regulate(model, stiffer, target, _gains(ki=0.0), 8.0)
    assert np.abs(e_p[-1]).max() > 5e-5                # P-D with feedforward leaves an offset
    assert np.abs(e_i[-1]).max() < 0.02 * np.abs(e_p[-1]).max()   # the integral removes it
    assert np.abs(e_p[-1] - e_p[-100]).max() < 1e-6    # and the offset is a steady one


def test_saturation_keeps_tensions_in_limits_and_the_integral_bounded(model_factory):
    """A reference that needs 4.5 N with a 3 N ceiling: tensions stay in [0.05, 3] N and the
    integral stops growing once the output saturates (conditional integration)."""
    model = model_factory(**NO_FRICTION)
    t, e, u, xi, _, _ = _regulate(model, model, [4.5, 0.3, 0.3, 0.3], _gains(u_max=3.0), 6.0)
    assert u.min() >= 0.05 and u.max() <= 3.0
    assert np.allclose(u[-1, 0], 3.0)
    late = t > 3.0
    assert np.abs(xi[late, 0] - xi[late][0, 0]).max() < 1e-12   # frozen on the saturated tendon
    assert np.abs(xi).max() < 0.01 * 6.0               # below the rate bound e_sat x time


def test_tendon_controller_regulates_the_task_tendons_and_honours_the_feedforward_switch():
    from soft_arm_control.inner_loop import TendonController
    s = np.array([0.01, 0.02, 0.03, 0.04])
    with_ff = TendonController(4, _gains(), ActuationMap.identity(), (2, 3))
    without = TendonController(4, _gains(), ActuationMap.identity(), (2, 3), feedforward=False)
    assert np.allclose(with_ff.update(0.0, s, 0 * s), 0.05)          # no reference: pretension
    for tc in (with_ff, without):
        tc.set_reference(s, [0.3, 0.4, 1.5, 2.5])                     # on target: only u_ff left
    assert np.allclose(with_ff.update(0.0, s, 0 * s), [0.3, 0.4, 1.5, 2.5])
    assert np.allclose(without.update(0.0, s, 0 * s), [0.3, 0.4, 0.05, 0.05])
    with pytest.raises(ValueError, match="finite"):
        with_ff.set_reference([np.nan] * 4, [0.3] * 4)


def test_a_reference_rate_counts_for_its_hold_time_and_then_as_a_fixed_reference():
    """The rate of a moving reference enters the derivative term from the first update after it
    arrived for ``rate_hold`` seconds of the inner loop's own time, then counts as zero (a
    reference that stops coming is not one that keeps moving); a new reference starts it again;
    a reference without rates is fixed; a bad rate is refused."""
    from soft_arm_control.inner_loop import TendonController
    s, kd = np.array([0.01, 0.02, 0.03, 0.04]), 120.0
    rate = np.array([0.0, 0.0, 0.01, -0.02])
    tc = TendonController(4, _gains(kd=kd), ActuationMap.identity(), (2, 3), rate_hold=0.01)
    u_ff = [0.3, 0.4, 1.5, 2.5]
    tc.set_reference(s, u_ff, rate)
    assert np.allclose(tc.update(5.0, s, 0 * s), [0.3, 0.4, 1.5 + kd * 0.01, 2.5 - kd * 0.02])
    assert np.allclose(tc.update(5.01, s, 0 * s)[2:], [1.5 + kd * 0.01, 2.5 - kd * 0.02])
    assert np.allclose(tc.update(5.012, s, 0 * s)[2:], [1.5, 2.5])        # expired
    tc.set_reference(s, u_ff, rate)                                        # a new one
    assert np.allclose(tc.update(5.014, s, 0 * s)[2:], [1.5 + kd * 0.01, 2.5 - kd * 0.02])
    tc.set_reference(s, u_ff)                                              # fixed
    assert np.allclose(tc.update(5.016, s, 0 * s)[2:], [1.5, 2.5])
    with pytest.raises(ValueError, match="shortening rates"):
        tc.set_reference(s, u_ff, [0.0, np.inf, 0.0, 0.0])
    with pytest.raises(ValueError, match="shortening rates"):
        tc.set_reference(s, u_ff, [0.0, 0.0])
