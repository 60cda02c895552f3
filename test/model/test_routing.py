"""The tendons' routing: the arrays of a routing are the model's, and the derivatives of the tendon
terms with respect to it agree with central differences of the whole model rebuilt at the perturbed
routing."""
from dataclasses import replace

import numpy as np
import pytest

from soft_arm_model import ArmData, build_model, evaluate, load_arm_config, solve_equilibrium
from soft_arm_model.routing import (ROUTING_STEP, new_routing_work, routing_arrays, routing_derivatives,
                                    routing_of, tendon_ends)

RELATIVE = 1e-6


@pytest.fixture(scope="module")
def arm():
    return load_arm_config()


def _rebuilt(arm, k, j, step):
    """The model with tendon k's routing parameter j (offset fraction, start angle, end angle) moved
    by ``step``."""
    field = ("offset_fraction", "start_angle", "end_angle")[j]
    tendons = list(arm.tendons)
    tendons[k] = replace(tendons[k], **{field: getattr(tendons[k], field) + step})
    return build_model(replace(arm, tendons=tuple(tendons)))


def _derivatives(model, q, routing=None):
    n, nt = model.n, model.n_tendons
    g, a = model.config.geometry, model.kernel_args
    d = evaluate(model, ArmData(model), q, level=1)
    rest = evaluate(model, ArmData(model), np.zeros(n), level=0)
    out = np.zeros(nt), np.zeros((3, n, nt)), np.zeros((3, n, nt)), np.zeros((3, nt)), np.zeros((3, nt))
    routing = routing_of(model.config) if routing is None else routing
    taper = (g.tip_radius - g.base_radius) / g.length
    ok = routing_derivatives(a[0], a[1], a[2], a[17], a[18], a[19], a[20], model.X, model.tendon_active,
                             g.base_radius, taper, tendon_ends(model.config), model.friction_mu, routing,
                             d.xi, q, rest.xi.copy(), np.zeros(n), True, *out, new_routing_work(model))
    assert ok
    return out


def test_a_routing_gives_the_models_arrays(arm):
    model = build_model(arm)
    g = arm.geometry
    arrays = [np.zeros_like(model.tendon_d) for _ in range(3)]
    routing_arrays(model.X, model.tendon_active, g.base_radius, (g.tip_radius - g.base_radius) / g.length,
                   routing_of(arm), tendon_ends(arm), *arrays)
    for mine, model_s in zip(arrays, (model.tendon_d, model.tendon_dp, model.tendon_dpp)):
        assert np.array_equal(mine, model_s)


@pytest.mark.parametrize("tensions", [[4.0, 1.0, 2.0, 0.5], [0.5, 3.0, 0.2, 2.5]])
def test_the_routing_derivatives_match_central_differences_of_the_rebuilt_model(arm, tensions):
    model = build_model(arm)
    q = solve_equilibrium(model, np.array(tensions)).q
    L0, dA, dA0, dLc, dL0 = _derivatives(model, q)
    d_lc = evaluate(model, ArmData(model), q, level=1).Lc.copy()
    assert np.allclose(L0, model.rest_tendon_lengths, rtol=0, atol=1e-15)
    step = 1e-5
    for k in range(model.n_tendons):
        for j in range(3):
            plus, minus = _rebuilt(arm, k, j, step), _rebuilt(arm, k, j, -step)
            dp, dm = (evaluate(m, ArmData(m), q, level=1) for m in (plus, minus))
            for name, mine, central in (
                    ("A", dA[j, :, k], (dp.A[:, k] - dm.A[:, k]) / (2 * step)),
                    ("A0", dA0[j, :, k], (dp.A0[:, k] - dm.A0[:, k]) / (2 * step))):
                assert np.linalg.norm(mine - central) <= RELATIVE * np.linalg.norm(central), (name, k, j)
            central = (dp.Lc[k] - dm.Lc[k]) / (2 * step)
            # dLc is a forward difference of a 0.4 m length at ROUTING_STEP: a few ulps of L_c's sum
            # (how many depends on the compiler's summation order) divided by the step, 1e-9 m
            # (1e-6 of dLc) on their own; a wrong term is off by the whole derivative, 1e-3
            floor = 16 * np.finfo(float).eps * abs(d_lc[k]) / ROUTING_STEP
            assert abs(dLc[j, k] - central) <= RELATIVE * abs(central) + floor, ("Lc", k, j)
            # the straight arm's length moves by 2e-4 m per unit offset, not at all with the angles of
            # an uncrossed tendon: an absolute bound (3e-10 m over a 0.03 offset)
            central = (plus.rest_tendon_lengths[k] - minus.rest_tendon_lengths[k]) / (2 * step)
            assert abs(dL0[j, k] - central) <= 1e-8, ("L0", k, j)


def test_the_derivatives_are_taken_at_the_routing_given(arm):
    """At another routing than the model's, the derivatives are that routing's: those of the model
    rebuilt there (a kernel that read the model's own arrays would give the drawing's)."""
    model = build_model(arm)
    q = solve_equilibrium(model, np.array([3.0, 0.5, 1.0, 2.0])).q
    moved = routing_of(arm) + np.array([[0.05], [0.04], [-0.03]])
    tendons = tuple(replace(t, offset_fraction=f, start_angle=s, end_angle=e)
                    for t, (f, s, e) in zip(arm.tendons, moved.T))
    rebuilt = build_model(replace(arm, tendons=tendons))
    here = _derivatives(model, q, moved)
    there = _derivatives(rebuilt, q)
    drawing = _derivatives(model, q)
    for mine, theirs, drawn in zip(here, there, drawing):
        assert np.allclose(mine, theirs, rtol=1e-9, atol=1e-12)
        assert np.abs(mine - drawn).max() > 1e-5 * np.abs(drawn).max()
