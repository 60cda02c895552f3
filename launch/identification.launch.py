"""The identification experiment on the physical rig (a ROS 2 Jazzy installation): the excitation
node plays ``identification.yaml``'s tensions open loop through the motor driver while the recorder
keeps the bag that ``soft-arm-identify`` fits. ``ros2 launch soft_arm identification.launch.py``,
then, with the tendons slack, ``ros2 service call /motor_driver/zero std_srvs/srv/Trigger``,
``ros2 service call /motor_driver/enable std_srvs/srv/SetBool "{data: true}"`` and ``ros2 service
call /excitation/start std_srvs/srv/Trigger``; the excitation writes nothing more once it has played
the schedule (a few minutes): disable the motors, then stop the launch."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node

PARAMETER_FILES = ["arm.yaml", "control.yaml", "graph.yaml", "identification.yaml", "rig.yaml",
                   "mocap.yaml"]
NODES = ["motor_driver", "mocap_bridge", "excitation", "recorder"]
REALTIME = {"motor_driver", "mocap_bridge"}


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES]
    task = {"graph.task": "identification"}
    start = {"excitation": {"wait_for_start": True}}
    return LaunchDescription(
        [Node(package="soft_arm", executable=name, name=name, output="screen",
              parameters=params + [task] + ([start[name]] if name in start else []),
              prefix="chrt -f 20" if name in REALTIME else None) for name in NODES])
