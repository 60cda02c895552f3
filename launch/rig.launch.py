"""The experiment graph on the physical rig (a ROS 2 Jazzy installation): the motor driver and the
mocap bridge replace the simulator and publish the same topics; the controller nodes and the
recorder are unchanged. ``ros2 launch soft_arm rig.launch.py task:=triangle``. Enable the motors
(``ros2 service call /motor_driver/enable std_srvs/srv/SetBool "{data: true}"``) after zeroing them
with the tendons slack (``/motor_driver/zero``)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PARAMETER_FILES = ["arm.yaml", "control.yaml", "plant.yaml", "tasks.yaml", "graph.yaml", "rig.yaml",
                   "mocap.yaml"]
NODES = ["motor_driver", "mocap_bridge", "inner_loop", "clik", "task_runner", "recorder"]


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES]
    task = {"graph.task": LaunchConfiguration("task")}
    return LaunchDescription(
        [DeclareLaunchArgument("task", default_value="triangle")]
        + [Node(package="soft_arm", executable=name, name=name, output="screen",
                parameters=params + [task]) for name in NODES])
