"""Declared parameters on real rclpy, through the parameter services as ``ros2 param`` uses them:
every value the inner loop reads is declared with a description and, for scalars, the range its
schema states; values fixed after start are read-only and a set is refused; a live gain out of its
range is refused with the key and the allowed range; a valid change applies from the next step."""
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from soft_arm_control.inner_loop_node import LIVE, InnerLoopNode


@pytest.fixture
def inner_loop(context):
    node = InnerLoopNode(context=context, parameter_overrides=[
        Parameter("control.inner_loop.integral_saturation", value=1)])     # an int for a float
    user = rclpy.create_node("ros2_param", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(user)
    client = AsyncParameterClient(user, "inner_loop")

    def wait(future, timeout=10.0):
        deadline = time.monotonic() + timeout
        while not future.done():
            assert time.monotonic() < deadline, "the parameter service did not answer"
            executor.spin_once(timeout_sec=0.01)
        return future.result()

    assert client.wait_for_services(timeout_sec=10.0)
    try:
        yield node, client, wait
    finally:
        executor.shutdown()
        node.destroy_node()
        user.destroy_node()


def test_every_value_read_is_declared_with_a_description_and_range(inner_loop):
    node, client, wait = inner_loop
    names = wait(client.list_parameters()).result.names
    for name in ("control.inner_loop.proportional", "control.tension_max", "arm.material.youngs_modulus",
                 "graph.task", "tasks.triangle.tendons", "control.clik.min_frequency"):
        assert name in names
    described = {d.name: d for d in wait(client.describe_parameters(list(names))).descriptors}
    own = [n for n in names if n.split(".")[0] in ("arm", "control", "tasks", "graph")]
    assert len(own) > 100 and all(described[n].description.startswith("expected ") for n in own)
    modulus = described["arm.material.youngs_modulus"]
    assert modulus.read_only and modulus.description == "expected a modulus in (0, 1e12] Pa"
    interval = modulus.floating_point_range[0]
    assert (interval.from_value, interval.to_value) == (0.0, 1e12)
    assert {n for n in own if not described[n].read_only} == set(LIVE)
    # the override's int became the float the schema asks for
    assert node.get_parameter("control.inner_loop.integral_saturation").value == 1.0


def test_read_only_and_out_of_range_values_are_refused(inner_loop):
    node, client, wait = inner_loop
    before = node.core.gains

    def refused(name, value):
        results = wait(client.set_parameters([Parameter(name, value=value)])).results
        assert not results[0].successful
        return results[0].reason
    assert "read-only" in refused("arm.material.youngs_modulus", 2e5)
    assert "read-only" in refused("control.clik.task_gain", 5.0)
    assert "out of range" in refused("control.tension_max", 500.0)                  # rclpy's range
    assert refused("control.tension_max", 0.0) == \
        "control.tension_max = 0.0 is not valid: expected a tension in (0, 100] N"  # the open end
    assert "gains >= 0 N/m, one per tendon" in refused("control.inner_loop.proportional",
                                                       [1500.0, -1.0, 0.0, 0.0])
    assert "derivative and integral need one gain per tendon" in refused("control.inner_loop.derivative",
                                                                         [1.0, 2.0])
    assert "tension_min < tension_max" in refused("control.tension_min", 50.0)
    assert node.core.gains == before and node.get_parameter("control.tension_max").value == before.tension_max


def test_a_valid_gain_change_applies_from_the_next_step(inner_loop):
    node, client, wait = inner_loop
    core = node.core
    n = len(node.names)
    s_ref = np.full(n, 0.004)
    core.set_reference(s_ref, np.full(n, 1.0))
    s, rate = np.full(n, 0.0039), np.zeros(n)
    u_before = core.update(1.0, s, rate)
    kp = np.array(node.get_parameter("control.inner_loop.proportional").value)
    doubled = Parameter("control.inner_loop.proportional", value=list(2 * kp))
    results = wait(client.set_parameters([doubled])).results
    assert results[0].successful, results[0].reason
    assert list(node.get_parameter("control.inner_loop.proportional").value) == list(2 * kp)
    u_after = core.update(1.0, s, rate)                     # the same instant: no integral change
    active = node.core.active
    # u = kp e + u_ff on the regulated tendons (e = thetabar_a(s_ref) - thetabar_a(s) > 0, unsaturated)
    np.testing.assert_allclose(u_after[active] - 1.0, 2 * (u_before[active] - 1.0), rtol=1e-9)
    assert np.all(u_before[active] > 1.0)
