"""The recorder node on real rclpy, in this process: its subscriptions adapt to the publishers' QoS
as rosbag2's do (a best-effort publisher on a topic the graph's table marks reliable is recorded; a
latched goal published before the recorder started is recorded; a publisher the subscription does
not match makes it subscribe again), the receive and source time stamps are recorded, and losses
(gaps in a publisher's sequence numbers) are counted and stored in the metadata."""
import json
import pathlib
import time

import pytest
import rclpy
import yaml
from mcap.reader import make_reader
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from soft_arm_interfaces.msg import ConfigurationReference, TaskGoal

from conftest import spin_until
from soft_arm_drivers.recording.adaptive_qos import LossCounter, adapt_to_offers, matches, resubscription
from soft_arm_drivers.recording.recorder_node import MATCH_TIME, RecorderNode
from soft_arm_drivers.recording.rosbag_writer import QosProfile

BEST_EFFORT = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


# -- the core ---------------------------------------------------------------------------------------
def test_the_subscription_is_as_strict_as_every_offer_allows():
    be, rel = QosProfile("best_effort", "volatile"), QosProfile("reliable", "volatile")
    latched = QosProfile("reliable", "transient_local")
    assert adapt_to_offers([]) is None
    assert adapt_to_offers([latched]) == QosProfile("reliable", "transient_local", "keep_last", 1000)
    assert adapt_to_offers([latched, rel]) == QosProfile("reliable", "volatile", "keep_last", 1000)
    assert adapt_to_offers([latched, be]).reliability.value == "best_effort"
    assert matches(adapt_to_offers([latched]), latched) and not matches(adapt_to_offers([latched]), be)
    assert not matches(adapt_to_offers([latched]), rel) and matches(adapt_to_offers([be]), latched)
    current = adapt_to_offers([latched])
    assert resubscription(current, [latched, latched]) is None              # still matches: kept
    assert resubscription(current, [latched, rel]) == QosProfile("reliable", "volatile", "keep_last", 1000)
    assert resubscription(current, [latched, be]) == QosProfile("best_effort", "volatile", "keep_last", 1000)
    assert resubscription(adapt_to_offers([be]), [latched]) is None         # never upward


def test_losses_are_sequence_gaps_of_a_single_publisher():
    losses = LossCounter()
    assert [losses.received("/a", s, 1) for s in (1, 2, 5, 6, 10)] == [0, 0, 2, 0, 3]
    assert losses.received("/a", 1, 1) == 0                          # the publisher restarted
    assert losses.received("/a", 3, 1) == 1
    assert losses.received("/b", 7, 2) == 0 and losses.received("/b", 20, 2) == 0   # two publishers
    assert losses.received("/c", None, 1) == 0
    assert losses.lost == {"/a": 6} and losses.total == 6


# -- the node (the ``context`` fixture: conftest) -----------------------------------------------------
def goal(value):
    return TaskGoal(mode=TaskGoal.MODE_CLIK, labels=["marker4.x"], target=[float(value)])


def reference(value):
    return ConfigurationReference(goal=int(value), q_d=[float(value)])


def recorder(context, bag, topics):
    return RecorderNode(context=context, parameter_overrides=[
        Parameter("output", value=str(bag)), Parameter("graph.recorder.topics", value=topics),
        Parameter("graph.recorder.flush_period", value=0.2)])


def read(bag):
    with open(pathlib.Path(bag) / f"{pathlib.Path(bag).name}_0.mcap", "rb") as fh:
        reader = make_reader(fh)
        return [(channel.topic, message) for _, channel, message in reader.iter_messages()]


def stream_and_recorder(context, bag):
    """A best-effort arm/configuration_reference publisher (its node and publisher) and a recorder of
    that topic into ``bag`` with an executor spinning only the recorder."""
    publisher_node = rclpy.create_node("stream_publisher", context=context)
    stream = publisher_node.create_publisher(ConfigurationReference, "arm/configuration_reference",
                                             BEST_EFFORT)
    node = recorder(context, bag, ["arm/configuration_reference"])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return publisher_node, stream, node, executor


def metadata(bag):
    return yaml.safe_load((pathlib.Path(bag) / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def test_latched_and_best_effort_publishers_are_recorded(context, tmp_path):
    """task/goal is reliable + transient local in the graph's table. A latched goal published before
    the recorder starts reaches it; then a best-effort publisher appears on the same topic: the
    recorder subscribes again, best effort, and records its messages too."""
    publisher_node = rclpy.create_node("goal_publisher", context=context)
    latched = publisher_node.create_publisher(TaskGoal, "task/goal", LATCHED)
    before = time.time_ns()
    latched.publish(goal(1.0))                                  # nobody listens yet
    published = time.time_ns()
    bag = tmp_path / "bag"
    node = recorder(context, bag, ["task/goal"])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(publisher_node)
    try:
        spin_until(executor, lambda: node.count >= 1)
        assert node.topics["/task/goal"].profile.durability.value == "transient_local"
        streaming = publisher_node.create_publisher(TaskGoal, "task/goal", BEST_EFFORT)
        spin_until(executor, lambda: node.topics["/task/goal"].profile.reliability.value == "best_effort")
        spin_until(executor, lambda: streaming.get_subscription_count() > 0)
        for k in range(2, 40):
            streaming.publish(goal(k))
            executor.spin_once(timeout_sec=0.002)
        spin_until(executor, lambda: node.count >= 20)
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()
    after = time.time_ns()
    messages = read(bag)
    assert len(messages) == node.count >= 20
    values = [deserialize_message(m.data, TaskGoal).target[0] for _, m in messages]
    assert values[0] == 1.0 and set(values[1:]) <= set(range(2, 40)) and len(values) >= 20
    for _, m in messages:
        # the source time (publisher's) before the receive time, both inside the test's window
        assert before <= m.publish_time <= m.log_time <= after
    # the latched goal: stamped with when it was published, and when the recorder received it
    assert before <= messages[0][1].publish_time <= published < messages[0][1].log_time
    assert json.loads(metadata(bag)["custom_data"]["soft_arm.lost_messages"]) == {}


def test_messages_the_recorder_could_not_keep_up_with_are_counted(context, tmp_path):
    """3000 best-effort messages published while the recorder does not spin: its history (1000)
    overflows; what it missed is counted from the publisher's sequence numbers, so that recorded +
    lost covers every message, and the count is in the bag's metadata."""
    bag = tmp_path / "bag"
    publisher_node, stream, node, executor = stream_and_recorder(context, bag)
    try:
        spin_until(executor, lambda: stream.get_subscription_count() > 0)
        stream.publish(reference(0))
        spin_until(executor, lambda: node.count == 1)
        for k in range(1, 3000):
            stream.publish(reference(k))
        count = -1
        while count != node.count:                               # until nothing more arrives
            count = node.count
            for _ in range(50):
                executor.spin_once(timeout_sec=0.01)
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()
    lost = node.losses.lost.get("/arm/configuration_reference", 0)
    assert lost >= 1000 and node.count + lost == 3000
    stored = json.loads(metadata(bag)["custom_data"]["soft_arm.lost_messages"])
    assert stored == {"/arm/configuration_reference": lost}
    values = [deserialize_message(m.data, ConfigurationReference).q_d[0] for _, m in read(bag)]
    assert values == sorted(values) and values[-1] == 2999.0


def test_messages_are_taken_in_batches_and_written_in_the_order_they_were_received(context, tmp_path):
    """Two streams published alternately while the executor spins: no message goes through a
    callback (the executor is kept off the subscriptions, the node takes what waits every
    take_period), and the bag holds every message, each stream in order, log times never
    decreasing across the two."""
    publisher_node = rclpy.create_node("streams", context=context)
    references = publisher_node.create_publisher(ConfigurationReference, "arm/configuration_reference",
                                                 BEST_EFFORT)
    goals = publisher_node.create_publisher(TaskGoal, "task/goal", BEST_EFFORT)
    bag = tmp_path / "bag"
    node = recorder(context, bag, ["arm/configuration_reference", "task/goal"])
    assert node.get_parameter("graph.recorder.take_period").value == pytest.approx(0.02)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        spin_until(executor, lambda: min(references.get_subscription_count(),
                                         goals.get_subscription_count()) > 0)
        assert not any(executor.can_execute(t.subscription) for t in node.topics.values())
        for k in range(300):
            references.publish(reference(k))
            goals.publish(goal(k))
            executor.spin_once(timeout_sec=0.0005)
        spin_until(executor, lambda: node.count == 600)
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()
    messages = read(bag)
    assert len(messages) == 600 and node.losses.total == 0
    log_times = [m.log_time for _, m in messages]
    assert log_times == sorted(log_times)
    by_topic = {}
    for topic, m in messages:
        by_topic.setdefault(topic, []).append(m)
    assert [deserialize_message(m.data, ConfigurationReference).goal
            for m in by_topic["/arm/configuration_reference"]] == list(range(300))
    goal_values = [deserialize_message(m.data, TaskGoal).target[0] for m in by_topic["/task/goal"]]
    assert goal_values == list(range(300))


def test_messages_waiting_when_the_bag_closes_are_written(context, tmp_path):
    """Messages received but not taken yet (nothing spun since) are written when the bag closes,
    as a SIGINT or SIGTERM closes it."""
    bag = tmp_path / "bag"
    publisher_node, stream, node, executor = stream_and_recorder(context, bag)
    try:
        spin_until(executor, lambda: stream.get_subscription_count() > 0)
        for k in range(50):
            stream.publish(reference(k))
        time.sleep(0.2)                                   # delivered into the history, not taken
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()
    values = [deserialize_message(m.data, ConfigurationReference).goal for _, m in read(bag)]
    assert values == list(range(50)) and node.count == 50


def test_log_times_never_decrease_and_a_failed_take_still_closes_the_bag(context, tmp_path, monkeypatch):
    """Held messages are written in the order received; a log time earlier than the last written
    (a simulator's clock slower than the wall's between takes) is written as the last. A take that
    fails at close still leaves a closed, readable bag."""
    bag = tmp_path / "bag"
    node = recorder(context, bag, ["arm/configuration_reference"])
    topic = node.topics["/arm/configuration_reference"]
    data = bytes(serialize_message(reference(1)))
    for received, log_time in ((100, 5000), (200, 4000), (300, 6000)):
        node._hold(topic, data, {"received_timestamp": received}, log_time)
    node.take(everything=True)
    node.writer.flush()                                   # readable as it is written
    with open(bag / "bag_0.mcap", "rb") as fh:
        in_file_order = [m.log_time for _, _, m in make_reader(fh).iter_messages(log_time_order=False)]
    assert in_file_order == [5000, 5000, 6000]
    node._hold(topic, data, {"received_timestamp": 400}, 7000)
    monkeypatch.setattr(node, "take", lambda everything=False: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        node.close()
    assert node.writer.closed and len(read(bag)) == 3
    node.destroy_node()


def test_a_publisher_the_recorder_cannot_match_is_warned_of_once(context, tmp_path, monkeypatch):
    """A subscription that matches fewer publishers than there are, whose QoS already matches every
    offer (another type, say): looked up again at each discovery, warned of once, not resubscribed."""
    node = recorder(context, tmp_path / "bag", ["task/goal"])
    publisher_node = rclpy.create_node("goal_publisher", context=context)
    topic = node.topics["/task/goal"]
    warnings = []
    try:
        publisher_node.create_publisher(TaskGoal, "task/goal", BEST_EFFORT)
        deadline = time.monotonic() + 10.0
        while topic.subscription is None and time.monotonic() < deadline:
            node.discover()
            time.sleep(0.01)
        subscription = topic.subscription
        monkeypatch.setattr(subscription, "get_publisher_count", lambda: 0)
        monkeypatch.setattr(node.get_logger(), "warning", lambda text, **_: warnings.append(text))
        time.sleep(MATCH_TIME)
        for _ in range(3):
            node.discover()
        assert topic.subscription is subscription
        assert len(warnings) == 1 and "1 of 1 publishers do not match" in warnings[0]
    finally:
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()


def test_publishers_are_looked_up_only_when_their_number_changes(context, tmp_path, monkeypatch):
    """The discovery timer counts each topic's publishers and looks up their offers (the costly
    call) only when the count changed: none while nobody publishes, one when a publisher appears
    (and the topic is subscribed), none after that."""
    node = recorder(context, tmp_path / "bag", ["task/goal"])
    lookups = []
    lookup = node.get_publishers_info_by_topic
    monkeypatch.setattr(node, "get_publishers_info_by_topic",
                        lambda name: lookups.append(name) or lookup(name))
    publisher_node = rclpy.create_node("goal_publisher", context=context)
    try:
        for _ in range(5):
            node.discover()
        assert lookups == [] and node.topics["/task/goal"].subscription is None
        publisher_node.create_publisher(TaskGoal, "task/goal", LATCHED)
        deadline = time.monotonic() + 10.0
        while node.count_publishers("/task/goal") == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        for _ in range(5):
            node.discover()
        assert lookups == ["/task/goal"] and node.topics["/task/goal"].subscription is not None
        assert node.topics["/task/goal"].publishers == 1
    finally:
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()


def test_lost_messages_are_warned_of_at_most_once_a_second(context, tmp_path, monkeypatch):
    """Every second message missing from a publisher's sequence (100 gaps in a burst): every gap
    is counted, but one warning is logged, not one per gap (rclpy's own throttle inspects the
    caller's frame on every call)."""
    node = recorder(context, tmp_path / "bag", ["arm/configuration_reference"])
    warnings = []
    monkeypatch.setattr(node.get_logger(), "warning", lambda text, **_: warnings.append(text))
    topic = node.topics["/arm/configuration_reference"]
    topic.publishers = 1
    try:
        start = time.monotonic()
        for k in range(1, 201, 2):
            node._count_losses(topic, k)
        elapsed = time.monotonic() - start
    finally:
        node.close()
        node.destroy_node()
    assert node.losses.lost == {"/arm/configuration_reference": 99}
    gaps = [text for text in warnings if "sequence gap" in text]
    assert 1 <= len(gaps) <= 1 + int(elapsed / 1.0)
    assert "99 messages were not received" in warnings[-1]         # and the sum when the bag closes


def test_a_publisher_replaced_by_an_unmatched_one_is_looked_up_again(context, tmp_path):
    """A latched publisher replaced by a best-effort one, the number of publishers the same at
    every discovery: the subscription matches none of them, so the next discovery (MATCH_TIME after
    the subscription was made) looks the offers up again, and the recorder subscribes again, best
    effort (the discovery timer is held off: discovery runs when the test calls it)."""
    node = RecorderNode(context=context, parameter_overrides=[
        Parameter("output", value=str(tmp_path / "bag")),
        Parameter("graph.recorder.topics", value=["task/goal"]),
        Parameter("graph.recorder.discovery_period", value=10.0)])
    publisher_node = rclpy.create_node("goal_publisher", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    topic = node.topics["/task/goal"]
    try:
        latched = publisher_node.create_publisher(TaskGoal, "task/goal", LATCHED)
        spin_until(executor, lambda: node.count_publishers("/task/goal") == 1)
        node.discover()
        assert topic.profile.reliability.value == "reliable" and topic.publishers == 1
        streaming = publisher_node.create_publisher(TaskGoal, "task/goal", BEST_EFFORT)
        publisher_node.destroy_publisher(latched)
        spin_until(executor, lambda: node.count_publishers("/task/goal") == 1
                   and topic.subscription.get_publisher_count() == 0)     # unmatched
        time.sleep(max(0.0, topic.subscribed_at + MATCH_TIME - time.monotonic()))
        node.discover()
        assert topic.profile.reliability.value == "best_effort" and topic.publishers == 1
        spin_until(executor, lambda: streaming.get_subscription_count() > 0)
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        publisher_node.destroy_node()
