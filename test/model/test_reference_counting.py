"""The modules whose kernels compile without numba's reference counting (decisions 0023, 0024):
every kernel in them says whether it counts references. One that leaves it unsaid inherits its
first caller's setting, so that, compiled first under a kernel without counting, one that allocates
would not compile, and whether it did would depend on the order of the calls and on the cache."""
import importlib

import pytest
from numba.core.registry import CPUDispatcher

MODULES = ("soft_arm_model.lie", "soft_arm_model.kernels", "soft_arm_model.statics",
           "soft_arm_model.integrators", "soft_arm_control.estimator_update")


def _kernels(name):
    module = importlib.import_module(name)
    return {key: value for key, value in vars(module).items()
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == name}


@pytest.mark.parametrize("name", MODULES)
def test_every_kernel_says_whether_it_counts_references(name):
    kernels = _kernels(name)
    assert kernels, f"{name} defines no compiled kernel"
    unsaid = sorted(key for key, kernel in kernels.items() if "_nrt" not in kernel.targetoptions)
    assert unsaid == [], f"{name}: {unsaid} inherit their callers' reference counting"


def test_the_steppers_and_solvers_count_none_and_the_allocating_kernels_do():
    """What the decisions say of each part: the hot paths without counting, the workspace's
    constructors and the BLAS product with it."""
    from soft_arm_model import integrators, kernels, statics
    for kernel in (kernels.evaluate, kernels.static_tangent, kernels._magnus_step, integrators._run,
                   integrators._imex_prepare, statics._newton_kernel, statics._lu_solve):
        assert kernel.targetoptions["_nrt"] is False, kernel.py_func.__name__
    for kernel in (kernels._mass_bias, kernels._coriolis_matrix, kernels.new_work):
        assert kernel.targetoptions["_nrt"] is True, kernel.py_func.__name__
