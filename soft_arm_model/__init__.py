"""Variable-Strain (geometric variable strain, Cosserat) model of a soft tendon-driven cone.

Public API (Pinocchio style: an immutable model, a scratch workspace, algorithms as functions)::

    from soft_arm_model import load_arm_config, build_model, ArmData, solve_equilibrium
    model = build_model()                      # the paper's arm from config/arm.yaml
    eq = solve_equilibrium(model, [5, 0, 5, 0])
    tip = tip_frame(model, eq.q).p              # [m] in arm_base

See :mod:`soft_arm_model.dynamics` for kinematics and dynamics terms, :mod:`~.statics`,
:mod:`~.integrators` and :mod:`~.workspace`.
"""
from .config import ArmConfig, load_arm_config
from .dynamics import (CORIOLIS, DYNAMICS, KINEMATICS, STATICS, Frame, OutOfDomainError,
                       actuation_coordinates, actuation_matrix, coriolis_matrix, elastic_force, evaluate,
                       forward_dynamics, frame_at, gravity_force, marker_positions, mass_matrix,
                       potential_energies, tendon_lengths, tip_frame, total_energy)
from .integrators import ImexStepper, Ros2Stepper, Trajectory, simulate
from .model import ArmData, ArmModel, build_model
from .parameters import ConfigError
from .statics import (Equilibrium, EquilibriumError, residual_jacobian, solve_equilibrium, static_residual,
                      static_tangents, tangent_at)

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
