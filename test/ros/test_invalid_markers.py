"""The encoding of an unseen marker on ``mocap/markers``: NaN position and a zero quaternion, read
back as a NaN row, so that no reader takes it for a position."""
import math

import numpy as np

from geometry_msgs.msg import Pose, PoseArray
from soft_arm_ros.conversions import markers_of, pose_array


def test_an_unseen_marker_goes_out_invalid_and_comes_back_nan():
    markers = np.array([[0.0, 0.0, -0.1], [np.nan, np.nan, np.nan], [0.01, 0.02, -0.3]])
    msg = pose_array(markers, 1.5)
    assert [p.orientation.w for p in msg.poses] == [1.0, 0.0, 1.0]
    assert math.isnan(msg.poses[1].position.x)
    back = markers_of(msg)
    assert np.isnan(back[1]).all()
    np.testing.assert_array_equal(back[[0, 2]], markers[[0, 2]])


def test_a_zero_quaternion_marks_a_marker_invalid_whatever_its_position():
    """A publisher that zeroes the position of an occluded marker (as Motive does) but sets the
    quaternion to zero is read as unseen, not as a marker at the origin."""
    msg = PoseArray()
    for w in (1.0, 0.0):
        pose = Pose()
        pose.orientation.w = w
        msg.poses.append(pose)
    back = markers_of(msg)
    assert np.array_equal(back[0], np.zeros(3)) and np.isnan(back[1]).all()
    assert markers_of(PoseArray()).shape == (0, 3)
