"""The graph's QoS table against the subscriptions it must serve: a viewer's default (reliable)
subscription receives the shape; every topic the recorder may meet is receivable by the profile it
adapts to; streams stay best effort (a reliable stream would make a late sample block the next)."""
from rclpy.qos import QoSCompatibility, QoSProfile, qos_check_compatible

from soft_arm_drivers.recording.adaptive_qos import adapt_to_offers
from soft_arm_drivers.recording.recorder_node import to_profile, to_rclpy
from soft_arm_ros.contract import QOS

RVIZ_DEFAULT = QoSProfile(depth=10)          # rclpy / RViz default: reliable, volatile, keep last


def compatible(publisher, subscription) -> bool:
    """Not incompatible (rclpy warns where a policy is the system default, e.g. liveliness)."""
    return qos_check_compatible(publisher, subscription)[0] != QoSCompatibility.ERROR


def test_a_viewer_with_default_qos_receives_the_shape():
    assert compatible(QOS["arm/shape"], RVIZ_DEFAULT)
    assert not compatible(QOS["mocap/markers"], RVIZ_DEFAULT)     # why the shape is not a stream


def test_the_recorder_receives_every_topic_of_the_table():
    for topic, profile in QOS.items():
        recording = to_rclpy(adapt_to_offers([to_profile(profile)]))
        assert compatible(profile, recording), topic


def test_streams_are_best_effort_state_is_latched():
    for topic in ("tendon/command", "tendon/state", "mocap/markers", "mocap/tip", "/clock"):
        assert QOS[topic].reliability.name == "BEST_EFFORT", topic
    for topic in ("tendon/reference", "task/goal", "arm/configuration_reference", "pendulum/release"):
        assert QOS[topic].durability.name == "TRANSIENT_LOCAL", topic
