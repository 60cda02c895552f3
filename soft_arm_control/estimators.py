"""The shape estimator a configuration names: :class:`~.shape_estimation.ShapeEstimator` (the
static balance carries the estimate between samples) or
:class:`~.dynamic_estimation.DynamicShapeEstimator` (the arm's dynamics do), by
``estimator.process_model``. Both take the same samples and give the same estimates."""
from __future__ import annotations

from soft_arm_model import ArmModel

from .dynamic_estimation import DynamicShapeEstimator
from .shape_estimation import EstimatorConfig, ShapeEstimator


def shape_estimator(model: ArmModel, config: EstimatorConfig, rotor_mass: float):
    """The estimator of ``config.process_model`` for ``model`` (the controller's), the rotors'
    reflected mass ``rotor_mass`` [kg] on every tendon (``control.rotor_mass``: the dynamics'
    inertia along the tendons)."""
    if config.process_model == "dynamic":
        return DynamicShapeEstimator(model, config, rotor_mass)
    return ShapeEstimator(model, config)
