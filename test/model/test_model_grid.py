"""Models share the grid their discretisation fixes (basis, sub-steps, quadrature), and a shared
grid is never another arm's: every model equals the one built with nothing cached."""
from dataclasses import replace

import numpy as np

from soft_arm_model import build_model, load_arm_config
from soft_arm_model.config import with_basis
from soft_arm_model.model import _grid


def _arrays(model):
    return [np.asarray(a) for a in model.kernel_args if isinstance(a, np.ndarray)] + \
        [model.K, model.D, model.rest_tendon_lengths, model.rest_theta]


def _variants(arm):
    tendons = tuple(replace(t, friction=t.friction + 0.01 * k) for k, t in enumerate(arm.tendons))
    return [arm,
            with_basis(arm, (3, 0), shear=True),
            with_basis(arm, (1, 2), shear=False),
            replace(arm, marker_positions=tuple(0.9 * x for x in arm.marker_positions)),
            replace(arm, material=replace(arm.material, youngs_modulus=2.0 * arm.material.youngs_modulus)),
            replace(arm, tendons=tendons, tip_mass=arm.tip_mass + 0.002)]


def test_every_model_equals_the_one_built_with_nothing_cached():
    """Six arms (bases, markers, material, tendons), built twice in turn so that the second round
    comes from the cache: each model's arrays equal, to the bit and in dtype, those of a model
    built after the cache is emptied."""
    arms = _variants(load_arm_config())
    built = [build_model(a) for a in arms + arms]
    for arm, model in zip(arms + arms, built):
        _grid.cache_clear()
        fresh = build_model(arm)
        assert model.n == fresh.n and model.coordinate_labels == fresh.coordinate_labels
        for got, want in zip(_arrays(model), _arrays(fresh), strict=True):
            assert got.dtype == want.dtype and got.shape == want.shape
            np.testing.assert_array_equal(got, want)


def test_arms_on_one_discretisation_share_its_grid_read_only():
    """Material and tendons change nothing of the grid: the arrays are the same objects, and a
    model cannot write into what its neighbours read."""
    arm = load_arm_config()
    a, b = build_model(arm), build_model(_variants(arm)[-1])
    assert a.B is b.B and a.B1 is b.B1 and a.friction_Q is b.friction_Q
    assert not a.B.flags.writeable and not a.kernel_args[19].flags.writeable      # col_lo
    assert not np.array_equal(a.friction_mu, b.friction_mu)
