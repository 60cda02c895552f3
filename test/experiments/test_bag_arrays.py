"""Topics of one message layout decoded as arrays: the values ``rosbags`` decodes message by
message, to the bit, whatever the alignment; a topic whose layout changes is left to it."""
import numpy as np
from rosbags.typesys import Stores, get_typestore

from soft_arm_drivers.recording.rosbag_writer import RosbagWriter, TopicSpec
from soft_arm_experiments.bag_arrays import joint_state_arrays, pose_array_positions, read_raw
from soft_arm_experiments.identify_cli import _read_by_message, read_recording

TYPES = get_typestore(Stores.ROS2_JAZZY)
T = TYPES.types
NAMES = ["tendon_1", "tendon_2", "tendon_3", "tendon_4"]


def _header(k, frame_id):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1700000000 + k // 7,
                                                                           nanosec=(k * 142857131) % 10 ** 9),
                                    frame_id=frame_id)


def _joint_states(count, names, frame_id="", velocity=False, seed=0):
    rng = np.random.default_rng(seed)
    raws = []
    for k in range(count):
        values = rng.standard_normal((3, len(names)))
        values[0, k % len(names)] = np.nan if k % 5 == 0 else values[0, k % len(names)]
        msg = T["sensor_msgs/msg/JointState"](
            header=_header(k, frame_id), name=list(names), position=values[0],
            velocity=values[1] if velocity else np.zeros(0), effort=values[2])
        raws.append(bytes(TYPES.serialize_cdr(msg, "sensor_msgs/msg/JointState")))
    return raws


def _by_message(raws, names, fields):
    msgs = [TYPES.deserialize_cdr(r, "sensor_msgs/msg/JointState") for r in raws]
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
    index = [list(msgs[0].name).index(n) for n in names]
    return t, {f: np.array([np.asarray(getattr(m, f))[index] for m in msgs], dtype=float) for f in fields}


def test_joint_states_are_the_message_by_message_values_for_every_alignment():
    """Frame ids of 0-8 characters and names of 1-9 characters shift every field's padding; an
    empty or a full velocity; names read in another order; NaN values kept."""
    order = ["tendon_3", "tendon_1", "tendon_4", "tendon_2"]
    for pad in range(9):
        names = [f"{n}{'x' * pad}" for n in NAMES]
        for velocity in (False, True):
            raws = _joint_states(40, names, frame_id="f" * pad, velocity=velocity, seed=pad)
            wanted = [f"{n}{'x' * pad}" for n in order]
            fields = ("position", "velocity", "effort") if velocity else ("position", "effort")
            got = joint_state_arrays(raws, wanted, fields)
            assert got is not None, (pad, velocity)
            t, values = _by_message(raws, wanted, fields)
            np.testing.assert_array_equal(got[0], t)
            for f in fields:
                np.testing.assert_array_equal(got[1][f], values[f])
            assert np.isnan(got[1]["position"]).any()


def test_a_topic_whose_layout_changes_or_lacks_a_name_is_left_to_the_message_decoder():
    raws = _joint_states(10, NAMES)
    assert joint_state_arrays(raws, NAMES) is not None
    assert joint_state_arrays(raws, NAMES + ["tendon_5"]) is None                   # a name it lacks
    assert joint_state_arrays(raws, NAMES, ("position", "velocity")) is None        # no velocities
    longer = _joint_states(1, ["tendon_1", "tendon_2", "tendon_3", "tendon_40"])
    assert joint_state_arrays(raws[:5] + longer + raws[5:], NAMES) is None          # another length
    renamed = _joint_states(1, ["tendon_1", "tendon_2", "tendon_3", "tendon_5"])
    assert len(renamed[0]) == len(raws[0])
    assert joint_state_arrays(raws[:5] + renamed + raws[5:], NAMES) is None         # same length, other name
    other_frame = _joint_states(1, NAMES, frame_id="a")
    other_frame_padded = _joint_states(1, NAMES, frame_id="b")
    assert joint_state_arrays(other_frame + other_frame_padded, NAMES) is None
    assert joint_state_arrays([], NAMES) is None


def _pose_arrays(count, poses, frame_id="mocap", seed=0):
    rng = np.random.default_rng(seed)
    Pose, Point = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"]
    Quat = T["geometry_msgs/msg/Quaternion"]
    raws = []
    for k in range(count):
        p = rng.standard_normal((poses, 3))
        if k % 4 == 1:
            p[k % poses] = np.nan                                   # an occluded marker
        msg = T["geometry_msgs/msg/PoseArray"](header=_header(k, frame_id), poses=[
            Pose(position=Point(x=a, y=b, z=c), orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0))
            for a, b, c in p])
        raws.append(bytes(TYPES.serialize_cdr(msg, "geometry_msgs/msg/PoseArray")))
    return raws


def test_marker_frames_are_the_message_by_message_positions_and_a_changed_count_is_left_alone():
    for pad in range(9):
        raws = _pose_arrays(30, 4, frame_id="m" * pad, seed=pad)
        t, positions = pose_array_positions(raws)
        msgs = [TYPES.deserialize_cdr(r, "geometry_msgs/msg/PoseArray") for r in raws]
        np.testing.assert_array_equal(t, [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
        want = [[[p.position.x, p.position.y, p.position.z] for p in m.poses] for m in msgs]
        np.testing.assert_array_equal(positions, want)
        assert np.isnan(positions).any()
    raws = _pose_arrays(6, 4)
    assert pose_array_positions(raws[:3] + _pose_arrays(1, 3) + raws[3:]) is None


def _bag(directory, states):
    """A bag of tendon states ``states``, commands and marker frames, 30 of each."""
    specs = [TopicSpec("/tendon/state", "sensor_msgs/msg/JointState"),
             TopicSpec("/tendon/command", "sensor_msgs/msg/JointState"),
             TopicSpec("/mocap/markers", "geometry_msgs/msg/PoseArray")]
    with RosbagWriter(directory, specs) as writer:
        for k, (state, command, frame) in enumerate(zip(states, _joint_states(30, NAMES, seed=1),
                                                        _pose_arrays(30, 4))):
            for topic, raw in (("/tendon/state", state), ("/tendon/command", command),
                               ("/mocap/markers", frame)):
                writer.write(topic, 1_000_000 * (k + 1), raw)
    return str(directory)


def test_a_bag_reads_the_same_recording_decoded_as_arrays_or_message_by_message(tmp_path):
    """One layout: the arrays' recording is the message decoder's. A state with a fifth joint
    among them: the whole bag goes to the message decoder, which reads it as before."""
    uniform = _bag(tmp_path / "uniform", _joint_states(30, NAMES, seed=2))
    mixed_states = _joint_states(30, NAMES, seed=2)
    mixed_states[7] = _joint_states(1, NAMES + ["tendon_5"], seed=3)[0]
    mixed = _bag(tmp_path / "mixed", mixed_states)
    for bag in (uniform, mixed):
        got, want = read_recording(bag, NAMES), _read_by_message(bag, NAMES)
        for field in ("t", "shortening", "tension", "t_command", "command", "t_markers", "markers"):
            a, b = getattr(got, field), getattr(want, field)
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    assert joint_state_arrays(read_raw(mixed, ["tendon/state"])["tendon/state"][1], NAMES) is None
