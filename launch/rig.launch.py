"""The experiment graph on the physical rig (a ROS 2 Jazzy installation): the motor driver and the
mocap bridge replace the simulator and publish the same topics; the controller nodes and the
recorder are unchanged. ``ros2 launch soft_arm rig.launch.py task:=triangle [feedback:=fused]``
(``feedback``: what the clik closes its loop on, as in sim.launch.py).

The two drivers are managed nodes. The launch configures both (the driver finds its motors, the
bridge its Motive server; a failure is in their log and ``ros2 lifecycle get``) and activates the
bridge. The motors stay inactive (polled, out of motor mode) until the operator, with the tendons
slack, zeroes and activates them and starts the task::

    ros2 service call /motor_driver/zero std_srvs/srv/Trigger
    ros2 lifecycle set /motor_driver activate
    ros2 service call /task_runner/start std_srvs/srv/Trigger

``ros2 lifecycle set /motor_driver deactivate`` before stopping the launch (no node should join or
leave the graph while the motors are driven); ``ros2 service call /motor_driver/estop
std_srvs/srv/Trigger`` stops them in any state. The drivers and the inner loop run under
SCHED_FIFO 20 (``chrt``: needs an rtprio limit or CAP_SYS_NICE)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.conditions import IfCondition
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

# arm.yaml last: an identified arm put in its place carries the mocap calibration and estimator
# priors of its fit, which win over mocap.yaml's and estimator.yaml's
PARAMETER_FILES = ["control.yaml", "plant.yaml", "tasks.yaml", "graph.yaml", "rig.yaml", "mocap.yaml",
                   "estimator.yaml", "arm.yaml"]
# the clik's mocap/markers per feedback (soft_arm_experiments.orchestration.FEEDBACK_TOPICS)
FEEDBACK = {"mocap": "mocap/markers", "fused": "fused/markers", "estimate": "estimate/markers"}
NODES = ["motor_driver", "mocap_bridge", "inner_loop", "clik", "task_runner", "recorder"]
REALTIME = {"motor_driver", "mocap_bridge", "inner_loop"}
MANAGED = {"motor_driver": "inactive", "mocap_bridge": "active"}     # the state the launch brings each to


def _transition(node, transition_id):
    return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(node),
                                       transition_id=transition_id))


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES]
    task = {"graph.task": LaunchConfiguration("task")}
    start = {"task_runner": {"wait_for_start": True}}
    feedback = LaunchConfiguration("feedback")
    topic = PythonExpression([repr(FEEDBACK), "['", feedback, "']"])
    actions = [DeclareLaunchArgument("task", default_value="triangle"),
               DeclareLaunchArgument("feedback", default_value="mocap", choices=list(FEEDBACK)),
               Node(package="soft_arm", executable="shape_estimator", name="shape_estimator",
                    output="screen", parameters=params,
                    condition=IfCondition(PythonExpression(["'", feedback, "' != 'mocap'"])))]
    for name in NODES:
        options = dict(package="soft_arm", executable=name, name=name, output="screen",
                       parameters=params + [task] + ([start[name]] if name in start else [])
                       + ([{"control.clik.feedback": feedback}] if name == "clik" else []),
                       prefix="chrt -f 20" if name in REALTIME else None,
                       remappings=[("mocap/markers", topic)] if name == "clik" else [])
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
