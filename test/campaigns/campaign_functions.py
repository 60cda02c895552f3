"""Run functions for the engine's tests, imported by the Dask workers from this file."""
import os
import time


def square(spec: dict) -> dict:
    """``x`` squared, and the worker's process id."""
    return {"value": spec["x"] ** 2, "pid": os.getpid()}


def slow(spec: dict) -> dict:
    """Write this worker's process id to ``spec['dir']/<x>.<pid>``, sleep ``spec['sleep']`` s."""
    with open(os.path.join(spec["dir"], f"{spec['x']}.{os.getpid()}"), "w", encoding="utf-8"):
        pass
    time.sleep(spec["sleep"])
    return {"value": spec["x"] ** 2, "pid": os.getpid()}


def raising(spec: dict) -> dict:
    """Raise ValueError for ``x == 2``; ``x`` squared otherwise."""
    if spec["x"] == 2:
        raise ValueError("the plant of x = 2 cannot be built")
    return {"value": spec["x"] ** 2}


def kernels_loaded(spec: dict) -> dict:
    """Whether this worker had the plant's compiled step loaded before the run asked for it."""
    import sys
    integrators = sys.modules.get("soft_arm_model.integrators")
    return {"loaded": bool(integrators is not None and integrators._imex_prepare.signatures)}
