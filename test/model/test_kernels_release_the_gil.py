"""Every numba kernel of the model and the actuation map releases the interpreter lock (``nogil``),
so a plant stepped in one thread does not stall a driver or an executor in another thread of the
same process (the emulated rig's ``virtual`` bus mode, the simulator node's executor)."""
import importlib

from numba.core.registry import CPUDispatcher

from soft_arm_model.kernels import evaluate

MODULES = ("soft_arm_model.kernels", "soft_arm_model.lie", "soft_arm_model.statics",
           "soft_arm_model.integrators", "soft_arm_control.actuation_map")


def test_every_kernel_is_compiled_without_the_gil():
    kernels = {f"{name}.{attr}": obj for name in MODULES
               for attr, obj in vars(importlib.import_module(name)).items()
               if isinstance(obj, CPUDispatcher) and obj.__module__ == name}
    assert len(kernels) >= 25 and evaluate in kernels.values()
    holding = [k for k, d in kernels.items() if not d.targetoptions.get("nogil")]
    assert not holding, f"kernels that hold the GIL: {holding}"
