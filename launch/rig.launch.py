"""The experiment graph on the physical rig (a ROS 2 Jazzy installation): the motor driver and the
mocap bridge replace the simulator and publish the same topics; the controller nodes and the
recorder are unchanged. ``ros2 launch soft_arm rig.launch.py task:=triangle``, then, with the
tendons slack, ``ros2 service call /motor_driver/zero std_srvs/srv/Trigger``, ``ros2 service call
/motor_driver/enable std_srvs/srv/SetBool "{data: true}"`` and ``ros2 service call
/task_runner/start std_srvs/srv/Trigger``; disable the motors before stopping the launch (no node
should join or leave the graph while they are enabled). The drivers and the inner loop run under
SCHED_FIFO 20 (``chrt``: needs an rtprio limit or CAP_SYS_NICE)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PARAMETER_FILES = ["arm.yaml", "control.yaml", "plant.yaml", "tasks.yaml", "graph.yaml", "rig.yaml",
                   "mocap.yaml"]
NODES = ["motor_driver", "mocap_bridge", "inner_loop", "clik", "task_runner", "recorder"]
REALTIME = {"motor_driver", "mocap_bridge", "inner_loop"}


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES]
    task = {"graph.task": LaunchConfiguration("task")}
    start = {"task_runner": {"wait_for_start": True}}
    return LaunchDescription(
        [DeclareLaunchArgument("task", default_value="triangle")]
        + [Node(package="soft_arm", executable=name, name=name, output="screen",
                parameters=params + [task] + ([start[name]] if name in start else []),
                prefix="chrt -f 20" if name in REALTIME else None) for name in NODES])
