"""ament_python package ``soft_arm`` (also installable with pip: ``pip install -e ".[test]"``)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "soft_arm"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["soft_arm_model", "soft_arm_model.*", "soft_arm_ros", "soft_arm_ros.*",
                                    "soft_arm_control", "soft_arm_control.*", "soft_arm_drivers",
                                    "soft_arm_drivers.*", "soft_arm_experiments",
                                    "soft_arm_experiments.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + ["config/foxglove_layout.json"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.26,<3",
        "scipy>=1.11",
        "numba>=0.60",
        "PyYAML>=6",
        "matplotlib>=3.8",
        "python-can>=4.3",
        "mcap==1.6.0",
        # the live view (live_view node): a Foxglove WebSocket server from Python
        "foxglove-sdk==0.30.3",
        # soft-arm-campaign: runs on Dask distributed; bokeh serves its dashboard
        "dask[distributed]>=2024.8",
        "bokeh>=3.1",
        # Real ROS 2 Jazzy rclpy from PyPI; without the RMW implementation rclpy cannot start.
        "ros-jazzy-rclpy==7.1.6",
        "ros-jazzy-common-interfaces==5.3.6",
        "ros-jazzy-rmw-fastrtps-cpp==8.4.3",
    ],
    extras_require={
        # PyElastica: the model bench's comparison, whose timing a test checks; websockets and
        # protobuf: the live view's test client, which decodes the scene as the Foxglove app does;
        # threadpoolctl: a test repeats a campaign worker's run with the worker's one BLAS thread
        "test": ["pytest>=8", "pytest-xdist>=3.5", "hypothesis>=6", "rosbags==0.11.9", "flake8>=7",
                 "sphinx>=8", "myst-parser>=4", "furo>=2024.8.6", "pyelastica==1.0.0", "websockets>=13",
                 "protobuf>=5", "threadpoolctl>=3"],
    },
    zip_safe=True,
    maintainer="soft_arm maintainers",
    maintainer_email="soft-arm@example.org",
    description="ROS 2 control stack for a soft tendon-driven continuum arm",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "soft-arm-model = soft_arm_model.cli:main",
            "soft-arm-harness = soft_arm_experiments.harness_cli:main",
            "soft-arm-targets = soft_arm_control.targets_cli:main",
            "soft-arm-experiment = soft_arm_experiments.experiment:main",
            "soft-arm-identify = soft_arm_experiments.identify_cli:main",
            "soft-arm-warmup = soft_arm_experiments.warmup:main",
            "soft-arm-campaign = soft_arm_experiments.campaigns.cli:main",
            "simulator = soft_arm_drivers.sim.simulator_node:main",
            "recorder = soft_arm_drivers.recording.recorder_node:main",
            "inner_loop = soft_arm_control.inner_loop_node:main",
            "clik = soft_arm_control.clik_node:main",
            "shape_estimator = soft_arm_control.shape_estimator_node:main",
            "task_runner = soft_arm_experiments.task_runner_node:main",
            "excitation = soft_arm_experiments.excitation_node:main",
            "live_view = soft_arm_experiments.live_view_node:main",
            "mocap_bridge = soft_arm_drivers.mocap.mocap_bridge_node:main",
            "emulated_rig = soft_arm_drivers.sim.emulated_rig:main",
            "motor_driver = soft_arm_drivers.can.motor_driver_node:main",
        ],
        # python-can plugins: can.Bus(interface="soft_arm_loopback", channel="LOCAL:PEER")
        "can.interface": [
            "soft_arm_loopback = soft_arm_drivers.can.loopback_bus:LoopbackBus",
        ],
    },
)
