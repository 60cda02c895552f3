"""The analytic tangent of the static balance (``kernels.static_tangent``) and the tendons' rate
bias of the dynamics (``kernels.tendon_rate_bias``) against central differences, term by term, on
every strain basis the project builds; and the equilibria the solver finds with the tangent against
those the finite-difference oracle finds."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from soft_arm_model import ArmData, evaluate, kernels, static_tangents, statics, tangent_at, tip_frame
from soft_arm_model.dynamics import DYNAMICS, KINEMATICS, STATICS
from soft_arm_model.model import R_BASE
from soft_arm_model.references import tendon_load_tip

EPS = 1e-4           # central-difference step [rad or strain] (fourth-order stencil)
RTOL = 1e-6          # relative Frobenius error allowed
MU = 16              # index of the friction coefficients in model.kernel_args

SHEAR = {"discretisation.modes.shear_y": True, "discretisation.modes.shear_z": True}
BASES = {
    "paper": {},
    "shear, orders 2 and 1": {**SHEAR, "discretisation.legendre_order": [2, 1]},
    "tip mass, shear": {**SHEAR, "tip_mass": 0.02},
    "one division, order 4": {"discretisation.division_ends": [0.38], "discretisation.legendre_order": [4],
                              "discretisation.gauss_points": [9],
                              "discretisation.allow_tendon_end_inside_division": True},
    "bending only, linear axial law": {"discretisation.modes.torsion": False,
                                       "discretisation.modes.axial": False,
                                       "material.axial_law": "linear",
                                       "discretisation.legendre_order": [4, 2],
                                       "discretisation.gauss_points": [8, 3]},
    "orders 0, three divisions": {"discretisation.division_ends": [0.2, 0.325, 0.38],
                                  "discretisation.legendre_order": [0, 1, 0],
                                  "discretisation.gauss_points": [3, 3, 2]},
}


@pytest.fixture(scope="module")
def models(model_factory):
    return {name: model_factory(**over) for name, over in BASES.items()}


def _draw(model, rng):
    """A configuration (angles ~0.5 rad, strains ~0.05), tensions in [0, 5] N, friction
    coefficients in [0, 1]."""
    scale = np.array([0.05 if ("axial" in lab or "shear" in lab) else 0.5
                      for lab in model.coordinate_labels])
    return (rng.normal(size=model.n) * scale, rng.uniform(0.0, 5.0, model.n_tendons),
            rng.uniform(0.0, 1.0, model.n_tendons))


class _Terms:
    """The kernels on ``model`` with the friction coefficients ``mu``: the static terms at q and
    the analytic tangent."""

    def __init__(self, model, mu):
        mu = np.array(mu, dtype=float)
        mu.setflags(write=False)        # as the model's: a writable one would compile the kernels again
        self.args = model.kernel_args[:MU] + (mu,) + model.kernel_args[MU + 1:]
        self.model = model
        self.data = ArmData(model)

    def forces(self, q, u, friction):
        """(F_el, F_g, A u) at q."""
        d = self.data
        assert kernels.evaluate(*self.args, q, q, 1, False, *d.kernel_args)
        return d.Fel.copy(), d.Fg.copy(), (d.A if friction else d.A0) @ u

    def tangent(self, q, u, friction):
        """(dR/dq, dA/d mu) at q."""
        self.forces(q, u, friction)
        jac = np.zeros((self.model.n, self.model.n))
        dmu = np.zeros((self.model.n, self.model.n_tendons))
        kernels.static_tangent(*self.args, q, u, friction, *self.data.kernel_args, jac, dmu)
        return jac, dmu


def _central(f, x, eps=EPS):
    """Central differences of f at x, the fourth-order stencil: its truncation error (~eps^4) and
    its rounding (~1e-16 |f| / eps) both far below RTOL where a tendon's small geometric stiffness
    beside its large force would lose the second-order stencil's rounding to cancellation."""
    cols = []
    for b in range(x.size):
        e = np.zeros(x.size)
        e[b] = eps
        cols.append((8.0 * (f(x + e) - f(x - e)) - (f(x + 2 * e) - f(x - 2 * e))) / (12 * eps))
    return np.stack(cols, axis=1)


def _assert_close(analytic, reference, what):
    err = np.linalg.norm(analytic - reference) / np.linalg.norm(reference)
    assert err <= RTOL, f"{what}: relative Frobenius error {err:.2e} > {RTOL:g}"


@pytest.mark.parametrize("basis", list(BASES))
@pytest.mark.parametrize("friction", [True, False], ids=["friction", "frictionless"])
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_the_static_tangent_agrees_with_central_differences_term_by_term(models, basis, friction, seed):
    m = models[basis]
    q, u, mu = _draw(m, np.random.default_rng(seed))
    terms = _Terms(m, mu)
    jac, _ = terms.tangent(q, u, friction)
    jac_unloaded, _ = terms.tangent(q, np.zeros_like(u), friction)
    Kt = terms.data.Kt.copy()
    # the whole tangent, then each term apart: elastic, gravity (u = 0), tendons (u minus u = 0)
    _assert_close(jac, _central(lambda x: sum((1, -1, 1)[i] * f for i, f in
                                              enumerate(terms.forces(x, u, friction))), q), "dR/dq")
    _assert_close(Kt, _central(lambda x: terms.forces(x, u, friction)[0], q), "K_t")
    _assert_close(Kt - jac_unloaded, _central(lambda x: terms.forces(x, u, friction)[1], q), "dF_g/dq")
    _assert_close(jac - jac_unloaded, _central(lambda x: terms.forces(x, u, friction)[2], q),
                  "d(A u)/dq")


@pytest.mark.parametrize("basis", list(BASES))
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_the_tendons_rate_bias_agrees_with_central_differences_along_the_rates(models, basis, seed):
    """(dA0/dt)^T qd, the rotors' share of the tendon acceleration, against the derivative of
    A0(q + e qd)^T qd in e."""
    m = models[basis]
    rng = np.random.default_rng(seed)
    q = _draw(m, rng)[0]
    qd = 20.0 * _draw(m, rng)[0]                 # rates of some 10 rad/s
    terms = _Terms(m, np.zeros(m.n_tendons))
    analytic = np.zeros(m.n_tendons)
    terms.forces(q, np.zeros(m.n_tendons), False)
    a = terms.args
    kernels.tendon_rate_bias(a[0], a[1], terms.data.xi, qd, a[12], a[13], a[15], analytic)

    def rate(e):
        terms.forces(q + e[0] * qd, np.zeros(m.n_tendons), False)
        return terms.data.A0.T @ qd
    _assert_close(analytic, _central(rate, np.zeros(1), EPS / np.abs(qd).max())[:, 0], "(dA0/dt)^T qd")


@pytest.mark.parametrize("where", ["straight", "5 N on tendons 1 and 3"])
def test_the_static_tangent_holds_at_rest_and_at_a_loaded_equilibrium(models, where):
    """The straight arm (the straight tendons' turning rate at the friction smoothing's floor) and
    a curled equilibrium (wrap angles of several radians)."""
    m = models["paper"]
    u = np.array([5.0, 0.0, 5.0, 0.0])
    q = np.zeros(m.n) if where == "straight" else statics.solve_equilibrium(m, u).q
    terms = _Terms(m, m.friction_mu)
    jac, _ = terms.tangent(q, u, True)
    _assert_close(jac, _central(lambda x: sum((1, -1, 1)[i] * f for i, f in
                                              enumerate(terms.forces(x, u, True))), q), "dR/dq")
    jac_unloaded, _ = terms.tangent(q, np.zeros_like(u), True)
    _assert_close(jac - jac_unloaded, _central(lambda x: terms.forces(x, u, True)[2], q), "d(A u)/dq")


@pytest.mark.parametrize("basis", ["paper", "shear, orders 2 and 1"])
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_the_friction_derivative_agrees_with_central_differences(models, basis, seed):
    m = models[basis]
    q, u, mu = _draw(m, np.random.default_rng(seed))
    _, dmu = _Terms(m, mu).tangent(q, u, True)
    reference = _central(lambda x: _Terms(m, x).forces(q, u, True)[2], mu)
    _assert_close(dmu * u, reference, "d(A u)/d mu")
    # dA/d mu does not depend on the tensions: the same with one tendon slack
    u[0] = 0.0
    _, dmu_slack = _Terms(m, mu).tangent(q, u, True)
    np.testing.assert_allclose(dmu_slack, dmu, rtol=0, atol=1e-14 * np.abs(dmu).max())
    _, dmu0 = _Terms(m, mu).tangent(q, u, False)
    assert not dmu0.any()


def test_the_public_tangents_are_the_kernels(models):
    m = models["paper"]
    q, u, _ = _draw(m, np.random.default_rng(7))
    r, jac, dmu = static_tangents(m, q, u)
    terms = _Terms(m, m.friction_mu)
    Fel, Fg, Au = terms.forces(q, u, True)
    np.testing.assert_allclose(r, Fel - Fg + Au, rtol=0, atol=1e-14 * np.abs(r).max())
    jac_k, dmu_k = terms.tangent(q, u, True)
    np.testing.assert_array_equal(jac, jac_k)
    np.testing.assert_array_equal(dmu, dmu_k)
    # the backward pass alone on a workspace the caller evaluated at q (statics with the markers, as
    # the CLIK evaluates; dynamics, as its dynamic reference does; kinematics after statics) gives
    # the same numbers
    data = ArmData(m)
    for levels in ((STATICS,), (DYNAMICS,), (STATICS, KINEMATICS)):
        for level in levels:
            evaluate(m, data, q, level=level, markers=True)
        np.testing.assert_array_equal(tangent_at(m, data, q, u), jac)
    evaluate(m, data, q + 0.01, level=STATICS)                  # another q's workspace: another tangent
    assert np.linalg.norm(tangent_at(m, data, q, u) - jac) > 1e-3 * np.linalg.norm(jac)
    # and the forward-difference oracle the solver used before agrees to its own accuracy
    pb = statics._Problem(m, ArmData(m), True, oracle=True)
    _, jac_fd = pb.linearise(q, u)
    assert np.linalg.norm(jac - jac_fd) / np.linalg.norm(jac) < 1e-5


NO_GRAVITY = {"gravity": [0.0, 0.0, 0.0]}
CASES = {   # (overrides, tensions [N], friction)
    "paper, 5 N on tendons 1 and 3": ({}, [5.0, 0.0, 5.0, 0.0], True),
    "paper, mixed": ({}, [2.0, 0.0, 3.0, 0.0], True),
    "paper, crossed pair": ({}, [0.0, 0.0, 3.0, 3.0], True),
    "paper, all four, frictionless": ({}, [2.0, 2.0, 2.0, 2.0], False),
    "hanging under gravity": ({}, [0.0, 0.0, 0.0, 0.0], True),
    "tip mass, shear": ({**SHEAR, "tip_mass": 0.02}, [1.0, 0.0, 1.0, 0.0], True),
    "exact tendon load, crossed": ({**NO_GRAVITY, "discretisation.legendre_order": [5, 0],
                                    "discretisation.gauss_points": [11, 3]}, [0.0, 0.0, 2.0, 0.0], False),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_solver_finds_the_equilibria_the_finite_difference_oracle_finds(model_factory, case):
    over, u, friction = CASES[case]
    m = model_factory(**over)
    eq = statics.solve_equilibrium(m, u, friction=friction)
    before = statics._solve(statics._Problem(m, ArmData(m), friction, oracle=True), u, None, None,
                            1e-10, 25, 1.0 / 4096)
    tip, tip_before = tip_frame(m, eq.q).p, tip_frame(m, before.q).p
    assert np.linalg.norm(tip - tip_before) <= 1e-9, (tip, tip_before)
    assert eq.iterations <= before.iterations + 1 and eq.load_steps == before.load_steps
    if case.startswith("exact tendon load"):
        assert np.linalg.norm(tip - tendon_load_tip(m.config, u, R_BASE)) < 2e-4
