"""The shape estimator's compiled updates against the same filter written in numpy (the oracles
below: the measurement models of soft_arm_control.shape_estimation, composed of numpy calls), on
random states, tensions and covariances, at rest and moving, and with random markers taken."""
import numpy as np
import pytest

from soft_arm_control.estimator_update import (OUT_OF_DOMAIN, UPDATED, marker_innovations, marker_moments,
                                               marker_update, new_work, tendon_update)
from soft_arm_control.shape_estimation import load_estimator_config
from soft_arm_model import ArmData, build_model, evaluate, solve_equilibrium, tendon_lengths
from soft_arm_model.dynamics import KINEMATICS
from soft_arm_model.statics import static_tangents


def oracle(model, config, z_prior, P, s, u, speed):
    """The iterated tendon update in numpy: (z, P, nis, shortening nis, H, K)."""
    c, n = config, model.n
    data = ArmData(model)
    z = z_prior.copy()
    inflation, moving = 1.0 + c.moving * speed, speed > c.rest_speed
    for _ in range(c.iterations):
        q, k, dmu = z[:n], z[n], z[n + 1:]
        r1, Jr, dA = static_tangents(model, q, u, data=data)
        d = data
        tendon_force = dA * u[None, :]
        r = r1 + (k - 1.0) * d.Fel + tendon_force @ dmu
        H_r = np.hstack([Jr + (k - 1.0) * d.Kt, d.Fel[:, None], tendon_force])
        H_s = np.hstack([-d.A0.T, np.zeros((s.size, 1 + dmu.size))])
        sigma_r = (c.balance * (np.abs(d.Fel) + np.abs(d.A @ u)) + c.balance_floor) * inflation
        H = np.vstack([H_s, H_r])
        y = np.concatenate([s - (model.rest_tendon_lengths - d.Lc), -r])
        noise = np.concatenate([np.full(s.size, c.shortening ** 2), sigma_r ** 2])
        innovation = y - H @ (z_prior - z)
        S = H @ P @ H.T + np.diag(noise)
        K = np.linalg.solve(S, H @ P).T
        if moving:
            K[n:] = 0.0
        z = z_prior + K @ innovation
        nis = float(innovation @ np.linalg.solve(S, innovation))
    A = np.eye(P.shape[0]) - K @ H
    P_new = A @ P @ A.T + (K * noise) @ K.T
    m = s.size
    shortening_nis = float(innovation[:m] @ np.linalg.solve(S[:m, :m], innovation[:m]))
    return z, 0.5 * (P_new + P_new.T), nis, shortening_nis, H, K


def compiled(model, config, z_prior, P, s, u, speed):
    n, nt = model.n, model.n_tendons
    data = ArmData(model)
    N, rows = z_prior.size, n + nt
    z, K, H = np.zeros(N), np.zeros((N, rows)), np.zeros((rows, N))
    noise, innovation = np.zeros(rows), np.zeros(rows)
    P = P.copy()
    status, nis, shortening_nis = tendon_update(
        model.kernel_args, data.kernel_args, data.Fg, data.Fel, data.A, data.A0, data.Kt, data.Lc,
        model.rest_tendon_lengths, s, u, z_prior, P, config.iterations, config.balance,
        config.balance_floor, 1.0 + config.moving * speed, config.shortening ** 2, speed > config.rest_speed,
        z, K, H, noise, innovation, new_work(n, nt, model.marker_X.size))
    return status, (z, P, nis, shortening_nis, H, K)


def relative(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), 1e-300)


@pytest.fixture(scope="module")
def model():
    return build_model()


@pytest.mark.parametrize("seed", range(8))
def test_the_compiled_update_is_the_numpy_update(model, seed):
    rng = np.random.default_rng(seed)
    config = load_estimator_config()
    n, nt = model.n, model.n_tendons
    u = rng.uniform(0.0, 2.0, nt)
    q_true = solve_equilibrium(model, u).q
    s = model.rest_tendon_lengths - tendon_lengths(model, q_true) + rng.normal(0.0, 2e-4, nt)
    k, dmu = rng.uniform(0.7, 1.4), rng.uniform(-0.05, 0.05, nt)
    scale = 1.0 / np.sqrt(np.abs(np.diag(model.K)))              # the estimator's compliance units
    z_prior = np.concatenate([q_true + rng.normal(0.0, 0.05, n) * scale, [k], dmu])
    root = rng.normal(size=(z_prior.size, z_prior.size)) * 1e-2
    P = root @ root.T + np.diag(np.concatenate([(0.05 * scale) ** 2, [1e-2], np.full(nt, 1e-3)]))
    speed = 0.0 if seed % 2 == 0 else 0.05                  # at rest, then moving (no parameter gain)
    status, got = compiled(model, config, z_prior, P, s, u, speed)
    assert status == UPDATED
    want = oracle(model, config, z_prior, P, s, u, speed)
    for name, a, b in zip(("z", "P", "nis", "shortening nis", "H", "K"), got, want):
        assert relative(a, b) < 1e-9, (name, relative(a, b))
    assert relative(got[0][:n], z_prior[:n]) > 0.01            # the update moved the state
    if speed:
        assert np.all(got[5][n:] == 0.0)                       # the parameters learn at rest only
    eigenvalues = np.linalg.eigvalsh(got[1])
    assert np.all(eigenvalues > 0) and np.array_equal(got[1], got[1].T)


def test_an_update_that_leaves_the_domain_says_so_and_leaves_the_covariance(model):
    config = load_estimator_config()
    n, nt = model.n, model.n_tendons
    z_prior = np.concatenate([np.full(n, 1e3), [1.0], np.zeros(nt)])   # strains no arm can take
    P = np.eye(z_prior.size) * 1e-3
    status, (_, P_after, *_rest) = compiled(model, config, z_prior, P, np.zeros(nt), np.ones(nt), 0.0)
    assert status == OUT_OF_DOMAIN
    assert np.array_equal(P_after, P)


@pytest.mark.parametrize("taken", [1, 2, 4])
def test_the_compiled_marker_update_is_the_numpy_update(model, taken):
    """Markers move q only: the gain's rows of the stiffness and friction are zero."""
    rng = np.random.default_rng(taken)
    n, nt, nm = model.n, model.n_tendons, model.marker_X.size
    N, rows = n + 1 + nt, 3 * taken
    root = rng.normal(size=(N, N)) * 1e-2
    P = root @ root.T + np.eye(N) * 1e-4
    H = np.zeros((max(n + nt, 3 * nm), N))
    H[:rows, :n] = rng.normal(size=(rows, n)) * 0.1
    innovation = np.zeros(H.shape[0])
    innovation[:rows] = rng.normal(size=rows) * 1e-3
    z0 = rng.normal(size=N)
    sigma2 = 5e-4 ** 2
    Hr, y = H[:rows], innovation[:rows]                       # the oracle
    S = Hr @ P @ Hr.T + np.eye(rows) * sigma2
    K_want = np.linalg.solve(S, Hr @ P).T
    K_want[n:] = 0.0
    A = np.eye(N) - K_want @ Hr
    P_want = A @ P @ A.T + sigma2 * K_want @ K_want.T
    z, P_got = z0.copy(), P.copy()
    K, noise = np.zeros((N, H.shape[0])), np.zeros(H.shape[0])
    assert marker_update(H, innovation, rows, sigma2, n, z, P_got, K, noise, new_work(n, nt, nm))
    assert relative(z, z0 + K_want @ y) < 1e-9 and relative(z - z0, K_want @ y) < 1e-9
    assert relative(K[:, :rows], K_want) < 1e-9 and np.all(z[n:] == z0[n:])
    assert relative(P_got, 0.5 * (P_want + P_want.T)) < 1e-9 and np.array_equal(P_got, P_got.T)


@pytest.mark.parametrize("seed", range(4))
def test_the_markers_moments_and_innovations_are_the_numpy_ones(model, seed):
    """Each marker's Jacobian R J[3:] and covariance H P H^T, and each seen marker's normalised
    innovation square against numpy's; a marker with a NaN coordinate is not seen."""
    rng = np.random.default_rng(seed)
    n, nt, nm = model.n, model.n_tendons, model.marker_X.size
    N = n + 1 + nt
    q = solve_equilibrium(model, rng.uniform(0.0, 2.0, nt)).q
    d = evaluate(model, ArmData(model), q, level=KINEMATICS, markers=True)
    root = rng.normal(size=(N, N)) * 1e-2
    Pz = root @ root.T + np.eye(N) * 1e-4
    work = new_work(n, nt, nm)
    H, C = np.zeros((nm, 3, n)), np.zeros((nm, 3, 3))
    marker_moments(d.marker_R, d.marker_J, Pz, H, C, work)
    H_want = np.einsum("kij,kjn->kin", d.marker_R, d.marker_J[:, 3:, :])
    C_want = np.einsum("kin,nm,kjm->kij", H_want, Pz[:n, :n], H_want)
    assert relative(H, H_want) < 1e-12 and relative(C, C_want) < 1e-12
    assert np.array_equal(C, np.swapaxes(C, 1, 2))
    markers = d.marker_p + rng.normal(0.0, 1e-3, (nm, 3))
    markers[seed % nm, seed % 3] = np.nan
    sigma2 = 5e-4 ** 2
    nu, nis = np.zeros((nm, 3)), np.zeros(nm)
    marker_innovations(C, markers, d.marker_p, sigma2, nu, nis, work)
    for k in range(nm):
        if k == seed % nm:
            assert np.isnan(nis[k])
            continue
        y = markers[k] - d.marker_p[k]
        want = y @ np.linalg.solve(C_want[k] + sigma2 * np.eye(3), y)
        assert np.array_equal(nu[k], y) and abs(nis[k] - want) <= 1e-10 * want
