"""SE(3) helpers against matrix exponentials and finite differences."""
import math

import numpy as np
import pytest
from scipy.linalg import expm

from soft_arm_model.lie import (TANGENT_SCRATCH, ad_apply_columns, ad_matrix, expmap, inverse_adjoint_apply,
                                inverse_adjoint_apply_vector, tangent, tangent_rate, tangent_rate_apply)


def _hat(x):
    H = np.zeros((4, 4))
    w = x[:3]
    H[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    H[:3, 3] = x[3:]
    return H


@pytest.mark.parametrize("scale", [0.0, 1e-5, 0.05, 0.3, 0.49, 0.51, 1.0, 3.0])
def test_exp_tangent_and_rates(scale):
    rng = np.random.default_rng(int(scale * 1000))
    x = rng.normal(size=6) * scale
    xd = rng.normal(size=6)
    R, p = np.empty((3, 3)), np.empty(3)
    expmap(x, R, p)
    G = expm(_hat(x))
    np.testing.assert_allclose(R, G[:3, :3], atol=1e-14)
    np.testing.assert_allclose(p, G[:3, 3], atol=1e-14)
    ad = np.empty((6, 6))
    ad_matrix(x, ad)
    T_ref = sum(np.linalg.matrix_power(ad, k) / math.factorial(k + 1) for k in range(40))
    work = np.zeros((TANGENT_SCRATCH, 6, 6))
    T, Td = np.empty((6, 6)), np.empty((6, 6))
    tangent(x, T, work)
    np.testing.assert_allclose(T, T_ref, atol=1e-13)
    tangent_rate(x, xd, Td, work)
    eps = 1e-6
    Tp, Tm = np.empty((6, 6)), np.empty((6, 6))
    tangent(x + eps * xd, Tp, np.zeros_like(work))
    tangent(x - eps * xd, Tm, np.zeros_like(work))
    np.testing.assert_allclose(Td, (Tp - Tm) / (2 * eps), atol=1e-8)
    out = np.empty(6)
    tangent(x, T, work)
    tangent_rate_apply(x, xd, out, work)
    np.testing.assert_allclose(out, Td @ xd, atol=1e-12)


def test_inverse_adjoint():
    rng = np.random.default_rng(0)
    x = rng.normal(size=6)
    R, p = np.empty((3, 3)), np.empty(3)
    expmap(x, R, p)
    P = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    Ad_inv = np.block([[R.T, np.zeros((3, 3))], [-R.T @ P, R.T]])
    X = rng.normal(size=(6, 5))
    out = np.empty_like(X)
    inverse_adjoint_apply(R, p, X, out, 5)
    np.testing.assert_allclose(out, Ad_inv @ X, atol=1e-14)
    out[:] = 7.0                      # only the columns asked for are written
    inverse_adjoint_apply(R, p, X, out, 3)
    np.testing.assert_allclose(out[:, :3], Ad_inv @ X[:, :3], atol=1e-14)
    assert np.all(out[:, 3:] == 7.0)
    v = np.empty(6)
    inverse_adjoint_apply_vector(R, p, X[:, 2].copy(), v)
    np.testing.assert_allclose(v, Ad_inv @ X[:, 2], atol=1e-14)


def test_ad_apply_columns_writes_the_columns_asked_for():
    rng = np.random.default_rng(1)
    x = rng.normal(size=6)
    Y = rng.normal(size=(6, 7))
    ad = np.empty((6, 6))
    ad_matrix(x, ad)
    out = np.full((6, 7), 3.0)
    ad_apply_columns(x, Y, out, -0.5, False, 2, 5)
    np.testing.assert_allclose(out[:, 2:5], -0.5 * ad @ Y[:, 2:5], atol=1e-14)
    assert np.all(out[:, :2] == 3.0) and np.all(out[:, 5:] == 3.0)
    ad_apply_columns(x, Y, out, 1.0, True, 0, 7)
    np.testing.assert_allclose(out[:, 2:5], 0.5 * ad @ Y[:, 2:5], atol=1e-13)
    np.testing.assert_allclose(out[:, 5:], 3.0 + ad @ Y[:, 5:], atol=1e-13)
