"""rosbag_writer: bags read back by independent readers (rosbags, mcap), metadata.yaml layout,
crash safety under SIGKILL, recovery of cut files, and error cases."""
import errno
import io
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped, Quaternion, Vector3
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from rclpy.serialization import serialize_message
from rosbags.interfaces import QosReliability
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA, Float64MultiArray, Header
from visualization_msgs.msg import Marker, MarkerArray

from soft_arm_drivers.recording import rosbag_writer
from soft_arm_drivers.recording.message_definitions import (UnknownMessageTypeError, message_definition,
                                                            type_description_hash)
from soft_arm_drivers.recording.rosbag_writer import (METADATA_FILE, BagError, QosProfile, RosbagWriter,
                                                      TopicSpec, UnknownTopicError, open_bag, recover)

JAZZY = get_typestore(Stores.ROS2_JAZZY)
T0 = 1_700_000_000_000_000_000  # ns
STEP = 10_000_000  # ns between messages

TOPICS = [
    TopicSpec("/arm/joint_states", "sensor_msgs/msg/JointState",
              QosProfile(reliability="best_effort", depth=5)),
    TopicSpec("/arm/backbone", "geometry_msgs/msg/PoseArray"),
    TopicSpec("/arm/tip_pose", "geometry_msgs/msg/PoseStamped"),
    TopicSpec("/arm/tendon_tension", "std_msgs/msg/Float64MultiArray"),
    TopicSpec("/arm/markers", "visualization_msgs/msg/MarkerArray",
              QosProfile(durability="transient_local", depth=1)),
    TopicSpec("/clock", "rosgraph_msgs/msg/Clock"),
    TopicSpec("/arm/never_written", "std_msgs/msg/Float64MultiArray"),
]
MESSAGES_PER_TOPIC = 4


def _header(i):
    return Header(stamp=Time(sec=1000 + i, nanosec=i), frame_id=f"base_{i}")


def _pose(i):
    return Pose(position=Point(x=0.1 * i, y=-0.2, z=0.3),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _message(topic, i):
    """The i-th message on a topic, built with the rclpy message classes."""
    if topic == "/arm/joint_states":
        return JointState(header=_header(i), name=["tendon_1", "tendon_2"],
                          position=[0.5 * i, -0.5 * i], velocity=[1.0, 2.0], effort=[])
    if topic == "/arm/backbone":
        return PoseArray(header=_header(i), poses=[_pose(i), _pose(i + 1), _pose(i + 2)])
    if topic == "/arm/tip_pose":
        return PoseStamped(header=_header(i), pose=_pose(i))
    if topic == "/arm/tendon_tension":
        return Float64MultiArray(data=[float(i), 2.5, 7.25])
    if topic == "/arm/markers":
        return MarkerArray(markers=[Marker(header=_header(i), ns="backbone", id=k,
                                           type=Marker.SPHERE, pose=_pose(k),
                                           scale=Vector3(x=0.01, y=0.01, z=0.01),
                                           color=ColorRGBA(r=1.0, g=0.5, b=0.0, a=1.0))
                                    for k in range(3)])
    return Clock(clock=Time(sec=42 + i, nanosec=7))


def _written():
    """(topic, timestamp ns, CDR bytes) of the standard bag, interleaved over the topics."""
    written = [spec.name for spec in TOPICS[:-1]]
    return [(topic, T0 + (i * len(written) + k) * STEP, serialize_message(_message(topic, i)))
            for i in range(MESSAGES_PER_TOPIC) for k, topic in enumerate(written)]


def _write_bag(directory, chunk_size=2048, **options):
    records = _written()
    with RosbagWriter(directory, TOPICS, chunk_size=chunk_size, **options) as writer:
        for topic, stamp, data in records:
            writer.write(topic, stamp, data)
    return records


def _decode(data, type_name):
    """Deserialize with rosbags. ``serialize_message`` (rmw_fastrtps) returns Fast DDS's
    *estimated* size, padded with uninitialised bytes, which rosbags rejects; messages taken by a
    raw subscription (the recorder's input) carry the exact length. Strip trailing bytes until
    rosbags accepts the message: the content itself must decode unchanged."""
    for end in range(len(data), 4, -1):
        try:
            return JAZZY.deserialize_cdr(data[:end], type_name)
        except SerdeError:
            continue
    raise AssertionError(f"rosbags cannot deserialize a {type_name}")


def _metadata(directory):
    return yaml.safe_load((Path(directory) / METADATA_FILE).read_text())[
        "rosbag2_bagfile_information"]


def _rosbags_messages(directory):
    with Reader(directory) as reader:
        return [(conn.topic, stamp, data) for conn, stamp, data in reader.messages()]


def _stream_messages(path):
    """Messages from the start of an MCAP file up to where it ends or is cut off."""
    messages = []
    with open(path, "rb") as file:
        try:
            for _, channel, message in NonSeekingReader(file, validate_crcs=True).iter_messages(
                    log_time_order=False):
                messages.append((channel.topic, message.log_time, message.data))
        except (McapError, struct.error):  # EndOfFile mostly; struct.error in a cut footer
            pass
    return messages


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    directory = tmp_path_factory.mktemp("bags") / "run"
    return directory, _write_bag(directory, custom_data={"rig": "soft_arm"})


def test_rosbags_reads_every_topic_type_count_and_message(bag):
    directory, records = bag
    with Reader(directory) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {s.name: s.type for s in TOPICS}
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts == {s.name: MESSAGES_PER_TOPIC for s in TOPICS[:-1]} | {
            "/arm/never_written": 0}
        for conn in reader.connections:
            assert conn.digest == JAZZY.hash_rihs01(conn.msgtype)  # hash computed by rosbags
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in reader.connections}
        assert qos["/arm/joint_states"].reliability == QosReliability.BEST_EFFORT
        assert qos["/arm/joint_states"].depth == 5
        assert qos["/clock"].reliability == QosReliability.RELIABLE
        assert reader.message_count == len(records)
        assert reader.ros_distro == "jazzy"
        read = [(c.topic, stamp, data) for c, stamp, data in reader.messages()]
    assert read == records


def test_rosbags_decodes_field_values(bag):
    directory, _ = bag
    decoded = {}
    with Reader(directory) as reader:
        for conn, _, data in reader.messages():
            decoded.setdefault(conn.topic, []).append(_decode(data, conn.msgtype))
    joints = decoded["/arm/joint_states"][3]
    assert joints.name == ["tendon_1", "tendon_2"]
    assert list(joints.position) == [1.5, -1.5]
    assert joints.header.frame_id == "base_3" and joints.header.stamp.sec == 1003
    assert decoded["/arm/backbone"][2].poses[1].position.x == pytest.approx(0.3)
    assert decoded["/arm/tip_pose"][1].pose.orientation.w == 1.0
    assert list(decoded["/arm/tendon_tension"][2].data) == [2.0, 2.5, 7.25]
    marker = decoded["/arm/markers"][0].markers[2]
    assert (marker.ns, marker.id, marker.type, marker.color.g) == ("backbone", 2, 2, 0.5)
    assert [m.clock.sec for m in decoded["/clock"]] == [42, 43, 44, 45]


def test_mcap_schemas_channels_and_summary(bag):
    directory, records = bag
    with open(directory / "run_0.mcap", "rb") as file:
        reader = make_reader(file)
        header = reader.get_header()
        summary = reader.get_summary()
        rosbag2_record = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    assert header.profile == "ros2" and "soft_arm" in header.library
    assert summary.statistics.message_count == len(records)
    assert summary.statistics.chunk_count > 1
    schemas = {s.name: s for s in summary.schemas.values()}
    assert set(schemas) == {s.type for s in TOPICS}
    for name, schema in schemas.items():
        assert schema.encoding == "ros2msg"
        assert schema.data.decode() == message_definition(name)
    joint_state = schemas["sensor_msgs/msg/JointState"].data.decode()
    assert "\nMSG: std_msgs/Header\n" in joint_state
    assert "\nMSG: builtin_interfaces/Time\n" in joint_state
    markers = schemas["visualization_msgs/msg/MarkerArray"].data.decode()
    for nested in ("visualization_msgs/Marker", "geometry_msgs/Pose", "std_msgs/ColorRGBA",
                   "builtin_interfaces/Duration", "sensor_msgs/CompressedImage"):
        assert f"\nMSG: {nested}\n" in markers
    for channel in summary.channels.values():
        spec = next(s for s in TOPICS if s.name == channel.topic)
        assert channel.message_encoding == "cdr"
        assert yaml.safe_load(channel.metadata["offered_qos_profiles"]) == [spec.qos.to_metadata()]
        assert channel.metadata["topic_type_hash"] == type_description_hash(spec.type)
    serialized = yaml.safe_load(rosbag2_record[0].metadata["serialized_metadata"])
    assert serialized == _metadata(directory)


def test_metadata_yaml_is_jazzy_version_9(bag):
    directory, records = bag
    info = _metadata(directory)
    assert list(info) == ["version", "storage_identifier", "duration", "starting_time",
                          "message_count", "topics_with_message_count", "compression_format",
                          "compression_mode", "relative_file_paths", "files", "custom_data",
                          "ros_distro"]
    stamps = [stamp for _, stamp, _ in records]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["ros_distro"] == "jazzy"
    assert info["message_count"] == len(records)
    assert info["starting_time"] == {"nanoseconds_since_epoch": min(stamps)}
    assert info["duration"] == {"nanoseconds": max(stamps) - min(stamps)}
    assert info["relative_file_paths"] == ["run_0.mcap"]
    assert info["files"] == [{"path": "run_0.mcap", "starting_time": info["starting_time"],
                              "duration": info["duration"], "message_count": len(records)}]
    assert (info["compression_format"], info["compression_mode"]) == ("", "")
    assert info["custom_data"] == {"rig": "soft_arm"}
    by_topic = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    joints = by_topic["/arm/joint_states"]
    assert joints["message_count"] == MESSAGES_PER_TOPIC
    assert list(joints["topic_metadata"]) == ["name", "type", "serialization_format",
                                              "offered_qos_profiles", "type_description_hash"]
    assert joints["topic_metadata"]["serialization_format"] == "cdr"
    assert joints["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
    profile = joints["topic_metadata"]["offered_qos_profiles"]
    assert profile == [{"history": "keep_last", "depth": 5, "reliability": "best_effort",
                        "durability": "volatile",
                        "deadline": {"sec": 9223372036, "nsec": 854775807},
                        "lifespan": {"sec": 9223372036, "nsec": 854775807},
                        "liveliness": "automatic",
                        "liveliness_lease_duration": {"sec": 9223372036, "nsec": 854775807},
                        "avoid_ros_namespace_conventions": False}]
    assert by_topic["/arm/never_written"]["message_count"] == 0
    assert sorted(p.name for p in directory.iterdir()) == ["metadata.yaml", "run_0.mcap"]


@pytest.mark.parametrize("type_name", sorted({s.type for s in TOPICS}))
def test_schema_text_defines_the_type_exactly(type_name):
    """rosbags parses the concatenated definition on its own; the type hash it computes from
    that text matches the hash rosidl generated, so every nested type is present and right."""
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(message_definition(type_name), type_name))
    assert store.hash_rihs01(type_name) == type_description_hash(type_name)
    assert type_description_hash(type_name) == JAZZY.hash_rihs01(type_name)


@pytest.mark.parametrize("type_name, dependencies", [
    ("geometry_msgs/msg/PoseStamped",
     ["geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion", "std_msgs/Header",
      "builtin_interfaces/Time"]),
    ("visualization_msgs/msg/MarkerArray",
     ["visualization_msgs/Marker", "builtin_interfaces/Duration", "geometry_msgs/Point",
      "geometry_msgs/Pose", "geometry_msgs/Quaternion", "geometry_msgs/Vector3",
      "sensor_msgs/CompressedImage", "std_msgs/Header", "builtin_interfaces/Time",
      "std_msgs/ColorRGBA", "visualization_msgs/MeshFile", "visualization_msgs/UVCoordinate"]),
])
def test_message_definition_concatenates_like_rosbag2(type_name, dependencies):
    """The installed root text, then each dependency once: sorted by name, depth first."""
    share = Path(sys.prefix) / "share"

    def text(package, name):
        return (share / package / "msg" / f"{name}.msg").read_text()

    package, _, name = type_name.split("/")
    expected = text(package, name)
    for dependency in dependencies:
        expected += f"\n{'=' * 80}\nMSG: {dependency}\n{text(*dependency.split('/'))}"
    assert message_definition(type_name) == expected


def test_interfaces_are_found_through_ament_prefix_path(tmp_path, monkeypatch):
    msg_dir = tmp_path / "share" / "arm_msgs" / "msg"
    msg_dir.mkdir(parents=True)
    (msg_dir / "Tension.msg").write_text("std_msgs/Header header\nfloat64[<=6] newton\n")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    definition = message_definition("arm_msgs/msg/Tension")
    assert definition.startswith("std_msgs/Header header\nfloat64[<=6] newton\n\n=")
    assert "\nMSG: builtin_interfaces/Time\n" in definition  # from the wheels under sys.prefix
    assert type_description_hash("arm_msgs/msg/Tension") == ""  # no rosidl .json


def test_every_flush_leaves_a_bag_readable_without_help(tmp_path):
    """While the writer is open, the files on disk always form a complete bag holding exactly
    the flushed messages: the state a SIGKILL would leave."""
    directory = tmp_path / "live"
    records = _written()
    with RosbagWriter(directory, TOPICS, chunk_size=1500) as writer:
        flushes = 0
        for topic, stamp, data in records:
            before = writer.flushed_message_count
            writer.write(topic, stamp, data)
            if writer.flushed_message_count != before:
                flushes += 1
                assert _metadata(directory)["message_count"] == writer.flushed_message_count
                assert _rosbags_messages(directory) == records[:writer.flushed_message_count]
        assert flushes >= 3 and writer.message_count == len(records)
        assert writer.flushed_message_count < len(records)  # the open chunk is not on disk
    assert _rosbags_messages(directory) == records


# A writer that records JointStates until it is killed. argv: bag directory, file holding one
# CDR message, completed chunks to wait for, and "pause" (then stay inside the open chunk) or
# "run" (keep writing at full speed). Prints the flushed message count once the chunks are done.
CHILD = """
import sys, time
from soft_arm_drivers.recording.rosbag_writer import RosbagWriter, TopicSpec
directory, payload_file, chunks, mode = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
payload = open(payload_file, "rb").read()
writer = RosbagWriter(directory, [TopicSpec("/arm/joint_states", "sensor_msgs/msg/JointState")],
                      chunk_size=20 * len(payload))
stamp, flushes = 0, 0
def write():
    global stamp, flushes
    before = writer.flushed_message_count
    stamp += 1000
    writer.write("/arm/joint_states", stamp, payload)
    flushes += writer.flushed_message_count != before
while flushes < chunks:
    write()
for _ in range(3 if mode == "pause" else 0):
    write()
print(writer.flushed_message_count, writer.message_count, flush=True)
while mode == "run":
    write()
time.sleep(60)
"""


def _killed_bag(tmp_path, mode, chunks=5):
    """Run CHILD until it reports, SIGKILL it. Returns the bag, the payload, the counts."""
    payload = serialize_message(_message("/arm/joint_states", 1))
    (tmp_path / "payload.cdr").write_bytes(payload)
    directory = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(directory),
                              str(tmp_path / "payload.cdr"), str(chunks), mode],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = child.stdout.readline()
        child.send_signal(signal.SIGKILL)
        assert child.wait(timeout=10) == -signal.SIGKILL, child.stderr.read()
    finally:
        child.kill()
        child.stdout.close()
        child.stderr.close()
    flushed, written = map(int, line.split())
    return directory, payload, flushed, written


def test_sigkill_inside_an_open_chunk_keeps_every_flushed_message(tmp_path):
    directory, payload, flushed, written = _killed_bag(tmp_path, "pause")
    assert 0 < flushed < written
    expected = [("/arm/joint_states", 1000 * (i + 1), payload) for i in range(flushed)]
    assert _stream_messages(directory / "killed_0.mcap") == expected
    assert _rosbags_messages(directory) == expected  # no recovery needed
    assert _metadata(directory)["message_count"] == flushed
    assert recover(directory) == flushed


def test_sigkill_while_writing_keeps_every_completed_chunk(tmp_path):
    directory, payload, flushed, _ = _killed_bag(tmp_path, "run")
    streamed = _stream_messages(directory / "killed_0.mcap")
    assert len(streamed) >= flushed
    assert streamed == [("/arm/joint_states", 1000 * (i + 1), payload)
                        for i in range(len(streamed))]
    assert _metadata(directory)["message_count"] >= flushed
    recovered = recover(directory)
    assert recovered == len(streamed)
    assert _rosbags_messages(directory) == streamed
    assert _metadata(directory)["message_count"] == recovered


@pytest.fixture(scope="module")
def flush_states(tmp_path_factory):
    """The bag after 5 flushed messages (state 1) and after 10 (state 2), the writer alive."""
    directory = tmp_path_factory.mktemp("states") / "cut"
    data = serialize_message(_message("/arm/tendon_tension", 1))
    writer = RosbagWriter(directory, [TOPICS[3]], chunk_size=10**9)
    states = []
    for block in range(2):
        for i in range(5):
            writer.write("/arm/tendon_tension", T0 + (5 * block + i) * STEP, data)
        writer.flush()
        states.append((writer.mcap_path.read_bytes(), (directory / METADATA_FILE).read_text()))
    writer.close()
    return states


TAIL = 13 + 29 + 8  # DataEnd record, Footer record, magic


def test_a_flush_only_appends_to_the_file(flush_states):
    """What a cut write leaves is a prefix of the next state: there is no stale byte to skip."""
    (first, _), (second, _) = flush_states
    assert second.startswith(first[:-TAIL]) and first[-TAIL:] == second[-TAIL:]


@pytest.mark.parametrize("cut", [0, 1, 9, TAIL, 200, -TAIL - 1, -TAIL, -1])
def test_recover_a_bag_cut_during_a_flush(flush_states, tmp_path, cut):
    """SIGKILL during the second flush leaves the first state's data plus part of the second
    flush's bytes; `cut` says how much (negative: all but that many bytes)."""
    (first, metadata), (second, _) = flush_states
    start = len(first) - TAIL
    length = cut if cut >= 0 else len(second) - start + cut
    directory = tmp_path / "cut"
    directory.mkdir()
    (directory / "cut_0.mcap").write_bytes(second[:start + length])
    (directory / METADATA_FILE).write_text(metadata)
    opcode, chunk_length = struct.unpack_from("<BQ", second, start)
    assert opcode == 0x06  # the flush wrote a Chunk record first
    expected = 10 if length >= 9 + chunk_length else 5
    assert len(_stream_messages(directory / "cut_0.mcap")) == expected
    with pytest.raises(ReaderError, match="magic"):
        _rosbags_messages(directory)
    assert recover(directory) == expected
    assert len(_rosbags_messages(directory)) == expected
    assert _metadata(directory)["message_count"] == expected
    assert recover(directory) == expected  # idempotent


class _FillingDisk(io.FileIO):
    """A file on a disk that fills up once ``room`` more bytes are written."""

    room = None

    def write(self, data):
        if self.room is not None and len(data) > self.room:
            super().write(bytes(data[:self.room]))
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        if self.room is not None:
            self.room -= len(data)
        return super().write(data)


def test_a_flush_cut_after_one_byte_is_recovered(tmp_path, monkeypatch):
    """The writer drops the provisional tail before writing, so even a write that stops after
    its first byte leaves no stale tail bytes behind it."""
    disks = []

    def open_on_filling_disk(path, mode):
        disks.append(_FillingDisk(path, mode.replace("b", "")))
        return io.BufferedWriter(disks[-1])

    monkeypatch.setattr(rosbag_writer, "open", open_on_filling_disk, raising=False)
    directory = tmp_path / "full"
    data = serialize_message(_message("/arm/tendon_tension", 1))
    writer = RosbagWriter(directory, [TOPICS[3]], chunk_size=10**9)
    for i in range(5):
        writer.write("/arm/tendon_tension", T0 + i, data)
    writer.flush()
    disks[0].room = 1
    for i in range(5, 10):
        writer.write("/arm/tendon_tension", T0 + i, data)
    with pytest.raises(OSError, match="No space"):
        writer.flush()
    assert disks[0].closed  # the writer gave up
    disks[0].room = None  # space again: closing now must not write over the cut
    writer.close()
    with pytest.raises(ValueError, match="closed"):
        writer.write("/arm/tendon_tension", T0 + 10, data)
    monkeypatch.undo()
    assert recover(directory) == 5
    assert [stamp for _, stamp, _ in _rosbags_messages(directory)] == [T0 + i for i in range(5)]


def test_recover_leaves_a_closed_bag_unchanged(bag, tmp_path):
    directory = tmp_path / "run"
    shutil.copytree(bag[0], directory)
    before = {p.name: p.read_bytes() for p in directory.iterdir()}
    assert recover(directory) == len(bag[1])
    assert {p.name: p.read_bytes() for p in directory.iterdir()} == before


def test_a_closed_bag_opens_without_being_recovered(bag, tmp_path, monkeypatch):
    """open_bag trusts a closed bag whose metadata.yaml counts what its summary does: nothing is
    rewritten (every reader of a run's bag calls it)."""
    directory = tmp_path / "run"
    shutil.copytree(bag[0], directory)
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in directory.iterdir()}

    def recover(_):
        raise AssertionError("a closed bag was recovered")
    monkeypatch.setattr(rosbag_writer, "recover", recover)
    assert open_bag(directory) == len(bag[1])
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in directory.iterdir()} == before


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_compressed_chunks(tmp_path, compression):
    records = _write_bag(tmp_path / "packed", compression=compression)
    assert _rosbags_messages(tmp_path / "packed") == records
    with open(tmp_path / "packed" / "packed_0.mcap", "rb") as file:
        reader = make_reader(file)
        assert {c.compression for c in reader.get_summary().chunk_indexes} == {compression}


def test_empty_bag(tmp_path):
    RosbagWriter(tmp_path / "empty", TOPICS[:2]).close()
    info = _metadata(tmp_path / "empty")
    assert info["message_count"] == 0 and info["duration"] == {"nanoseconds": 0}
    with Reader(tmp_path / "empty") as reader:
        assert [c.topic for c in reader.connections] == [TOPICS[0].name, TOPICS[1].name]
        assert list(reader.messages()) == []


def test_close_after_an_error_keeps_the_messages_and_is_idempotent(tmp_path):
    data = serialize_message(_message("/clock", 0))
    with pytest.raises(RuntimeError, match="controller fault"):
        with RosbagWriter(tmp_path / "fault", [TOPICS[5]]) as writer:
            writer.write("/clock", T0, data)
            raise RuntimeError("controller fault")
    writer.close()
    assert _rosbags_messages(tmp_path / "fault") == [("/clock", T0, data)]
    with open(writer.mcap_path, "rb") as file:
        assert make_reader(file).get_summary().statistics.message_count == 1
    with pytest.raises(ValueError, match="closed"):
        writer.write("/clock", T0, data)
    with pytest.raises(ValueError, match="closed"):
        writer.flush()


def test_errors_leave_nothing_behind(tmp_path):
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(FileExistsError, match="already exists"):
        RosbagWriter(existing, TOPICS)
    with pytest.raises(UnknownMessageTypeError, match="no_msgs/msg/Nothing.msg"):
        RosbagWriter(tmp_path / "a", [TopicSpec("/x", "no_msgs/msg/Nothing")])
    with pytest.raises(UnknownMessageTypeError, match="package/msg/Type"):
        RosbagWriter(tmp_path / "b", [TopicSpec("/x", "sensor_msgs/JointState")])
    with pytest.raises(ValueError, match="more than once"):
        RosbagWriter(tmp_path / "c", [TOPICS[0], TOPICS[0]])
    with pytest.raises(ValueError, match="chunk_size"):
        RosbagWriter(tmp_path / "d", TOPICS, chunk_size=0)
    with pytest.raises(ValueError, match="compression"):
        RosbagWriter(tmp_path / "e", TOPICS, compression="bz2")
    with pytest.raises(ValueError, match="custom_data"):
        RosbagWriter(tmp_path / "f", TOPICS, custom_data={"run": 3})
    assert [p.name for p in tmp_path.iterdir()] == ["existing"]


def test_invalid_specs():
    with pytest.raises(ValueError, match="fully qualified"):
        TopicSpec("joint_states", "sensor_msgs/msg/JointState")
    with pytest.raises(ValueError):
        QosProfile(reliability="sometimes")
    with pytest.raises(ValueError, match="depth"):
        QosProfile(depth=-1)


def test_invalid_writes_are_rejected_and_the_writer_stays_usable(tmp_path):
    data = serialize_message(_message("/clock", 0))
    with RosbagWriter(tmp_path / "w", [TOPICS[5]]) as writer:
        with pytest.raises(UnknownTopicError, match="/clok"):
            writer.write("/clok", T0, data)
        with pytest.raises(ValueError, match="nanoseconds"):
            writer.write("/clock", -1, data)
        with pytest.raises(TypeError):
            writer.write("/clock", 1.5e18, data)
        with pytest.raises(TypeError, match="CDR bytes"):
            writer.write("/clock", T0, "not bytes")
        writer.write("/clock", T0, bytearray(data), publish_time_ns=T0 - 5)
    with open(tmp_path / "w" / "w_0.mcap", "rb") as file:
        [(_, _, message)] = make_reader(file).iter_messages()
    assert (message.log_time, message.publish_time, message.data) == (T0, T0 - 5, data)
    assert message.sequence == 1


# --- a bag cut off at any moment opens --------------------------------------------------------------

@pytest.fixture(scope="module")
def history(tmp_path_factory):
    """A bag written in many chunks, then closed: its final file, and metadata.yaml as it stood when
    the bag was created and after each flush (the states a kill can leave beside the file)."""
    directory = tmp_path_factory.mktemp("history") / "cut"
    records = _written()
    metadata = []
    with RosbagWriter(directory, TOPICS, chunk_size=700) as writer:
        metadata.append((directory / METADATA_FILE).read_text())
        for topic, stamp, data in records:
            flushed = writer.flushed_message_count
            writer.write(topic, stamp, data)
            if writer.flushed_message_count != flushed:
                metadata.append((directory / METADATA_FILE).read_text())
    return (directory / "cut_0.mcap").read_bytes(), metadata, records


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_bag_cut_at_any_byte_opens_with_the_projects_tools_and_rosbags(history, tmp_path, data):
    """The MCAP file cut at any byte (a kill while it was created, between or during flushes, while
    it was closed), beside any metadata.yaml the writer left, or none: open_bag recovers it, and
    rosbags then reads every message of every chunk that was complete."""
    final, metadata, records = history
    cut = data.draw(st.integers(0, len(final)))
    directory = Path(tempfile.mkdtemp(dir=tmp_path))
    (directory / f"{directory.name}_0.mcap").write_bytes(final[:cut])
    stale = data.draw(st.sampled_from([None] + metadata))
    if stale is not None:
        renamed = stale.replace("cut_0.mcap", f"{directory.name}_0.mcap")
        (directory / METADATA_FILE).write_text(renamed)
    expected = _stream_messages(directory / f"{directory.name}_0.mcap") if cut >= 8 else []
    assert open_bag(directory) == len(expected)
    assert _rosbags_messages(directory) == expected == records[:len(expected)]
    assert open_bag(directory) == len(expected)                          # nothing left to mend


# A writer that writes until it is killed, and says after each flush how many messages it has
# flushed (a full pipe holds it after a flush, which changes nothing of what it said)
KILLED_WRITER = """
import sys
from soft_arm_drivers.recording.rosbag_writer import RosbagWriter, TopicSpec
payload = open(sys.argv[2], "rb").read()
print("started", flush=True)
with RosbagWriter(sys.argv[1], [TopicSpec("/arm/joint_states", "sensor_msgs/msg/JointState")],
                  chunk_size=7 * len(payload)) as writer:
    stamp, flushed = 0, 0
    while True:
        stamp += 1000
        writer.write("/arm/joint_states", stamp, payload)
        if writer.flushed_message_count != flushed:
            flushed = writer.flushed_message_count
            print(f"flushed {flushed}", flush=True)
"""


@pytest.mark.parametrize("delay", [0.0, 0.002, 0.01, 0.03, 0.07, 0.15])
def test_a_writer_killed_at_any_moment_leaves_a_bag_that_opens(tmp_path, delay):
    """SIGKILL at moments from the bag's creation on: the project's tools open what is left, and
    rosbags reads it: a prefix of what was written, holding at least every message the writer had
    flushed (said) before the kill. Killed before its first flush, there may be no bag at all."""
    payload = serialize_message(_message("/arm/joint_states", 1))
    (tmp_path / "payload.cdr").write_bytes(payload)
    directory = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(directory),
                              str(tmp_path / "payload.cdr")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline() == "started\n"
        time.sleep(delay)
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        said = [int(line.split()[1]) for line in child.stdout.read().splitlines()
                if line.startswith("flushed ")]
    finally:
        child.kill()
        child.stdout.close()
        child.stderr.close()
    if delay >= 0.03:
        assert said, "the writer never flushed in 30 ms"
    if not said:
        if not directory.exists():
            return                                        # killed before it made anything
        try:
            open_bag(directory)
        except BagError:
            assert not any(directory.glob("*.mcap"))      # killed before the file existed
            return
    count = open_bag(directory)
    messages = _rosbags_messages(directory)
    assert len(messages) == count >= max(said, default=0)
    assert messages == [("/arm/joint_states", 1000 * (i + 1), payload) for i in range(count)]


def test_what_is_not_a_bag_is_refused_by_name(tmp_path):
    with pytest.raises(BagError, match="is not a bag directory"):
        open_bag(tmp_path / "nothing")
    (tmp_path / "file").write_text("x")
    with pytest.raises(BagError, match="is not a bag directory"):
        open_bag(tmp_path / "file")
    with pytest.raises(BagError, match="holds no rosbag2 bag"):
        open_bag(tmp_path)
