"""thetabar_a(L_c): the paper's approximation of the friction-aware actuation coordinates."""
import numpy as np
import pytest

from soft_arm_control.actuation_map import ActuationMap, _sample, fit_actuation_map


@pytest.fixture(scope="module")
def fitted(paper_model):
    return fit_actuation_map(paper_model, [0.0, 2.5, 5.0], degree=2, validation_samples=20)


def test_fit_is_close_and_reports_its_error(paper_model, fitted):
    assert fitted.samples == 81
    assert 0 < fitted.rms_error < 2e-3 and fitted.max_error < 5e-3
    rng = np.random.default_rng(7)
    s, theta = _sample(paper_model, rng.uniform(0, 5, (5, 4)))
    assert np.abs(theta - s).max() > 5e-3                   # friction matters: theta_a != s
    err = np.array([fitted(x) - y for x, y in zip(s, theta)])
    assert np.abs(err).max() < 2.5 * fitted.max_error       # independent samples agree with it
    assert np.abs(fitted(np.zeros(4))).max() < fitted.max_error  # the straight arm: the origin


def _static_sensitivity(model, u, h=1e-4):
    """d theta_a / d s along the model's equilibria at tensions u (by tension differences)."""
    cols_s, cols_t = [], []
    for e in np.eye(4):
        (sp,), (tp,) = _sample(model, [u + h * e])
        (sm,), (tm,) = _sample(model, [u - h * e])
        cols_s.append((sp - sm) / (2 * h))
        cols_t.append((tp - tm) / (2 * h))
    return np.array(cols_t).T @ np.linalg.inv(np.array(cols_s).T)


def test_jacobian_matches_finite_differences_and_the_static_sensitivity(paper_model, fitted):
    """At shortenings the arm takes at rest the fitted Jacobian is the model's own d theta_a / d s
    along equilibria to within 50 % (a degree-2 fit of a curved map), and, like it, has eigenvalues
    with positive real parts (more shortening, larger theta_a: the proportional term restores)."""
    for u in ([1.0, 0.2, 0.5, 0.8], [0.3, 2.0, 1.0, 0.1], [0.5, 0.5, 3.0, 2.0]):
        u = np.array(u)
        (s,), _ = _sample(paper_model, [u])
        jac = fitted.jacobian(s)
        h = 1e-7
        fd = np.column_stack([(fitted(s + h * e) - fitted(s - h * e)) / (2 * h) for e in np.eye(4)])
        assert np.allclose(jac, fd, atol=1e-6)
        true = _static_sensitivity(paper_model, u)
        assert np.linalg.norm(jac - true) < 0.5 * np.linalg.norm(true)
        assert np.linalg.eigvals(jac).real.min() > 0.3 and np.linalg.eigvals(true).real.min() > 0.3


def test_the_fit_is_not_monotone_and_says_so(paper_model, fitted):
    """thetabar_a's slope has a symmetric part with a negative eigenvalue (slope_margin, the smallest
    over the validation equilibria), and the map is not even one-to-one where the arm goes: from
    shortenings 15 mm off an equilibrium's, Newton's method finds other shortenings in the fitted
    range with the same thetabar_a. A loop on it can rest there (docs/decisions/0021)."""
    rng = np.random.default_rng(20)
    S, _ = _sample(paper_model, rng.uniform(0, 5, (20, 4)))
    margins = [np.linalg.eigvalsh(0.5 * (J + J.T)).min() for J in map(fitted.jacobian, S)]
    assert fitted.slope_margin < 0 and min(margins) < 0
    assert ActuationMap.identity().slope_margin > 0
    assert ActuationMap.identity().report() == {"coordinates": "shortenings"}
    assert fitted.report()["slope_margin"] == fitted.slope_margin and "slope margin -" in fitted.describe()
    others = 0
    for s_d in S:
        target = fitted(s_d)
        for _ in range(10):
            s = s_d + rng.normal(0.0, 0.015, 4)
            for _ in range(50):
                s = s - np.linalg.solve(fitted.jacobian(s), fitted(s) - target)
            if (np.linalg.norm(fitted(s) - target) < 1e-10 and np.linalg.norm(s - s_d) > 5e-3
                    and np.all(s > -3e-3) and np.all(s < S.max(axis=0))):
                others += 1
                break
    assert others >= 2


def test_identity_without_friction():
    ident = ActuationMap.identity()
    s = np.array([0.01, -0.02, 0.0, 0.005])
    assert np.array_equal(ident(s), s) and np.array_equal(ident.jacobian(s), np.eye(4))


def test_too_few_equilibria_is_an_error(paper_model):
    with pytest.raises(ValueError, match="needs at least"):
        fit_actuation_map(paper_model, [0.0, 1.0], degree=3)


def test_a_kept_fit_is_the_fit_and_another_arm_gets_its_own(tmp_path, monkeypatch, model_factory):
    """The fit kept across processes is the one fitted now (bit for bit), a corrupted file is fitted
    again, and another arm, or other settings, never get a kept map of another."""
    from soft_arm_control import actuation_map as am
    monkeypatch.setenv("SOFT_ARM_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(am, "_FITTED", {})
    model = model_factory()
    kept = am.cached_fit(model, (0.0, 2.5), 1, 5)
    files = list(tmp_path.glob("actuation_maps/*.npz"))
    assert len(files) == 1
    monkeypatch.setattr(am, "_FITTED", {})                       # a new process: from the file
    again = am.cached_fit(model, (0.0, 2.5), 1, 5)
    fresh = am.fit_actuation_map(model, (0.0, 2.5), 1, 5)
    np.testing.assert_array_equal(again.coef, fresh.coef)
    assert (again.rms_error, again.samples) == (fresh.rms_error, fresh.samples) and again is not kept
    files[0].write_bytes(b"not a map")
    monkeypatch.setattr(am, "_FITTED", {})
    np.testing.assert_array_equal(am.cached_fit(model, (0.0, 2.5), 1, 5).coef, fresh.coef)
    other = model_factory(**{"material.youngs_modulus": 2.0e5})
    assert am._digest(other, (0.0, 2.5), 1, 5) != am._digest(model, (0.0, 2.5), 1, 5)
    assert am._digest(model, (0.0, 2.5), 1, 6) != am._digest(model, (0.0, 2.5), 1, 5)
    assert not np.allclose(am.cached_fit(other, (0.0, 2.5), 1, 5).coef, fresh.coef)
