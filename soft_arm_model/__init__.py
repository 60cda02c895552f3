"""Variable-Strain (geometric variable strain, Cosserat) model of a soft tendon-driven cone.

Public API (Pinocchio style: an immutable model, a scratch workspace, algorithms as functions)::

    from soft_arm_model import load_arm_config, build_model, ArmData, solve_equilibrium
    model = build_model()                      # the paper's arm from config/arm.yaml
    eq = solve_equilibrium(model, [5, 0, 5, 0])
    tip = tip_frame(model, eq.q).p              # [m] in arm_base

See :mod:`soft_arm_model.dynamics` for kinematics and dynamics terms, :mod:`~.statics`,
:mod:`~.integrators` and :mod:`~.workspace`.
"""
from importlib import import_module

# Where each public name lives. The package imports them on first use (PEP 562), so that a process
# that reads only the parameters (the recorder, the motor driver) does not import numba and the
# kernels: about 0.2 s of CPU at each of their start-ups.
_HOMES = {
    "config": ("ArmConfig", "load_arm_config"),
    "dynamics": ("CORIOLIS", "DYNAMICS", "KINEMATICS", "STATICS", "Frame", "OutOfDomainError",
                 "actuation_coordinates", "actuation_matrix", "coriolis_matrix", "elastic_force",
                 "evaluate", "forward_dynamics", "frame_at", "gravity_force", "marker_positions",
                 "mass_matrix", "potential_energies", "tendon_lengths", "tip_frame", "total_energy"),
    "integrators": ("ImexStepper", "Ros2Stepper", "Trajectory", "simulate"),
    "model": ("ArmData", "ArmModel", "build_model"),
    "parameters": ("ConfigError",),
    "statics": ("Equilibrium", "EquilibriumError", "residual_jacobian", "solve_equilibrium",
                "static_residual", "static_tangents", "tangent_at"),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}


def __getattr__(name: str):
    module = _HOME_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOME_OF))


__all__ = [
    "ArmConfig", "ConfigError", "load_arm_config", "ArmModel", "ArmData", "build_model",
    "KINEMATICS", "STATICS", "DYNAMICS", "CORIOLIS", "Frame", "OutOfDomainError", "evaluate",
    "tip_frame", "frame_at", "marker_positions", "elastic_force", "gravity_force",
    "actuation_matrix", "tendon_lengths", "actuation_coordinates", "potential_energies",
    "mass_matrix", "coriolis_matrix", "total_energy", "forward_dynamics",
    "Equilibrium", "EquilibriumError", "solve_equilibrium", "residual_jacobian", "static_residual",
    "static_tangents", "tangent_at", "ImexStepper", "Ros2Stepper",
    "Trajectory", "simulate",
]
