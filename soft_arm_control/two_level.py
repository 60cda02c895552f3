"""The paper's two-level controller for one task, in one object (ROS-free): the outer loop (CLIK,
its precomputed/online/replay/track protocol) handing the inner loop (P-satI-D+ on the task's
tendons) its reference. The harness runs it in process; the graph runs the same two loops as the
clik and inner_loop nodes."""
from __future__ import annotations

import numpy as np

from .actuation_map import ActuationMap, actuation_map_for
from .clik import ClikPoint
from .collocated import full_tensions
from .config import ControlConfig, TaskConfig
from .inner_loop import tendon_controller_for
from .outer_loop import outer_loop_for


class TwoLevelController:
    """The paper's controller for one task, as the nodes run it: the outer loop (CLIK, its
    precomputed/online/replay/track protocol) and the inner loop (P-satI-D+ on the task's tendons).

    Setting ``reference`` (a ClikPoint) hands the inner loop its shortenings and feedforward, with
    the outer loop's reference rate;
    ``inner`` computes tensions for all tendons from measured shortenings.
    """

    def __init__(self, model, control: ControlConfig, task: TaskConfig,
                 actuation_map: ActuationMap | None = None):
        self.model, self.control, self.task = model, control, task
        self.outer = outer_loop_for(model, control, task)
        self.clik = self.outer.clik
        self.actuation_map = actuation_map or actuation_map_for(model, control)
        self.tendons = tendon_controller_for(model.n_tendons, control, task.tendons,
                                             self.actuation_map)
        self._reference = None

    @property
    def reference(self) -> ClikPoint | None:
        return self._reference

    @reference.setter
    def reference(self, ref: ClikPoint):
        self._reference = ref
        self.tendons.set_reference(ref.shortening, full_tensions(self.clik.cm, ref.u_ff),
                                   self.outer.reference_rate)

    def inner(self, t: float, s, s_dot) -> np.ndarray:
        """Tensions [N] of all tendons at time t [s] from measured shortenings [m] and rates [m/s]."""
        return self.tendons.update(t, s, s_dot)
