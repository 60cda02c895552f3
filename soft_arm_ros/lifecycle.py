"""Managed (lifecycle) nodes for the rig's hardware drivers, as ``ros2 lifecycle`` and launch files
drive them: unconfigured -> configure (open the bus or sockets, check that the hardware answers) ->
inactive (the hardware is read, not driven) -> activate (driven) -> active; deactivate, cleanup and
shutdown go back. ros2_control's hardware components use the same states.

:class:`ManagedHardwareNode` adds what rclpy's ``LifecycleNode`` leaves out:

- a transition the current state does not have (``activate`` while unconfigured) is refused with a
  warning that names the state and its transitions; rclpy's own service raises out of the
  executor and would end the driver's process;
- :func:`transition` makes a callback that raises log its reason (rclpy turns it into ``ERROR``
  and says nothing), and runs it holding the node's
  :attr:`~ManagedHardwareNode.hardware_lock`; :meth:`~ManagedHardwareNode.refuse` logs why a
  transition fails;
- a transition asked for through the change_state service holds that lock from start to end, so
  that a thread of the node's own (a driver's cycle) that triggers one, holding it, never runs
  beside another;
- neither waits for the lock longer than its bound (:data:`~.hardware_lock.HOLD_WAIT`): a cycle
  stuck holding it fails the transition with an error naming the cycle, where it would hold the
  executor and every service with it. The node stays where it was, but from shutdown and error
  processing, which rclpy finalizes whatever they return: those still call
  :meth:`~ManagedHardwareNode.release`, whose own bounded wait says what it could not do;
- :attr:`~ManagedHardwareNode.lifecycle_state`, the current state's label;
- cleanup, shutdown and error processing all call the node's :meth:`~ManagedHardwareNode.release`
  (close the hardware), which its ``close()`` on the way out calls too.
"""
from __future__ import annotations

import functools
import traceback

from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

from .hardware_lock import HardwareLock, LockTimeout

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
FINALIZING = ("shutdown", "error")    # transitions that end in finalized, failed or not (rcl's machine)

__all__ = ["FAILURE", "ManagedHardwareNode", "SUCCESS", "transition"]


def transition(callback):
    """Decorate a node's ``on_<transition>`` so that it runs holding the node's ``hardware_lock``
    and an exception in it is logged (then re-raised for rclpy, which enters error processing);
    FAILURE, said, if the lock is not free within its bound."""
    name = callback.__name__[3:]

    @functools.wraps(callback)
    def logged(node, state):
        try:
            with node.hardware_lock.held_by(f"the {name} transition"):
                try:
                    return callback(node, state)
                except Exception:
                    node.get_logger().error(f"{name} failed:\n{traceback.format_exc()}")
                    raise
        except LockTimeout as exc:        # the lock's, before the callback: it holds it then
            failed = node.refuse(name, str(exc))
            if name in FINALIZING:
                node.release()
            return failed
    return logged


class ManagedHardwareNode(LifecycleNode):
    """A ``LifecycleNode`` whose change_state service refuses a transition the current state does
    not have (with a warning) instead of raising out of the executor.

    :attr:`hardware_lock` (re-entrant, :class:`~.hardware_lock.HardwareLock`: it names its holder)
    is held by every transition callback and by whatever touches the hardware from a thread other
    than the executor's."""

    def __init__(self, node_name: str, **kwargs):
        self.hardware_lock = HardwareLock()
        super().__init__(node_name, **kwargs)
        service = self._service_change_state
        change_state = service.callback

        def guarded(request, response):
            """:func:`checked`, holding the hardware lock from start to end (refused if it is not
            free within its bound)."""
            try:
                with self.hardware_lock.held_by("the change_state service"):
                    return checked(request, response)
            except LockTimeout as exc:
                self.get_logger().error(f"transition {request.transition.label or request.transition.id} "
                                        f"refused: {exc}")
                response.success = False
                return response

        def checked(request, response):
            """rclpy's change_state, for the transitions the current state has."""
            wanted = request.transition
            available = {(t[0], t[1]) for t in self._state_machine.available_transitions}
            if not any(label == wanted.label if wanted.label else i == wanted.id for i, label in available):
                self.get_logger().warning(
                    f"transition {wanted.label or wanted.id} refused: the node is {self.lifecycle_state}, "
                    f"whose transitions are {sorted(label for _, label in available)}")
                response.success = False
                return response
            return change_state(request, response)
        service.callback = guarded

    @property
    def lifecycle_state(self) -> str:
        """The current state's label: unconfigured, inactive, active, finalized (or a transition's)."""
        return self._state_machine.current_state[1]

    def release(self):
        """Leave the hardware safe and closed (a driver's own); idempotent."""
        raise NotImplementedError

    @transition
    def on_cleanup(self, state):
        self.release()
        return SUCCESS

    @transition
    def on_shutdown(self, state):
        self.release()
        return SUCCESS

    @transition
    def on_error(self, state):
        self.release()
        return SUCCESS

    def close(self):
        """What ``run_node`` calls on the way out, in any state: :meth:`release`."""
        self.release()

    def refuse(self, transition_name: str, reason: str) -> TransitionCallbackReturn:
        """Log why ``transition_name`` fails and return FAILURE (the node stays where it was)."""
        self.get_logger().error(f"{transition_name} failed: {reason}")
        return FAILURE
