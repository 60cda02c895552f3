"""The identification experiment on the physical rig (a ROS 2 Jazzy installation): the excitation
node plays ``identification.yaml``'s tensions open loop through the motor driver (the one node the
driver takes commands from here: ``rig.motors.command_publisher``) while the recorder keeps the bag
that ``soft-arm-identify`` fits. ``ros2 launch soft_arm identification.launch.py``.

As in ``rig.launch.py``, the launch configures both managed drivers and activates the bridge; the
motors wait for the operator, who, with the tendons slack, zeroes and activates them and starts the
excitation::

    ros2 service call /motor_driver/zero std_srvs/srv/Trigger
    ros2 lifecycle set /motor_driver activate
    ros2 service call /excitation/start std_srvs/srv/Trigger

The excitation sends nothing more once it has played its schedule (a few minutes): deactivate the
motors (``ros2 lifecycle set /motor_driver deactivate``), then stop the launch."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import EmitEvent, RegisterEventHandler
from launch.events import matches_action
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

PARAMETER_FILES = ["arm.yaml", "control.yaml", "graph.yaml", "identification.yaml", "rig.yaml",
                   "mocap.yaml"]
NODES = ["motor_driver", "mocap_bridge", "excitation", "recorder"]
REALTIME = {"motor_driver", "mocap_bridge"}
MANAGED = {"motor_driver": "inactive", "mocap_bridge": "active"}     # the state the launch brings each to
OWN = {"excitation": {"wait_for_start": True},
       "motor_driver": {"rig.motors.command_publisher": "/excitation"}}


def _transition(node, transition_id):
    return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(node),
                                       transition_id=transition_id))


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES] + [{"graph.task": "identification"}]
    actions = []
    for name in NODES:
        options = dict(package="soft_arm", executable=name, name=name, output="screen",
                       parameters=params + ([OWN[name]] if name in OWN else []),
                       prefix="chrt -f 20" if name in REALTIME else None)
        if name not in MANAGED:
            actions.append(Node(**options))
            continue
        node = LifecycleNode(namespace="", **options)
        actions.append(node)
        if MANAGED[name] == "active":
            actions.append(RegisterEventHandler(OnStateTransition(
                target_lifecycle_node=node, goal_state="inactive",
                entities=[_transition(node, Transition.TRANSITION_ACTIVATE)])))
        actions.append(_transition(node, Transition.TRANSITION_CONFIGURE))
    return LaunchDescription(actions)
