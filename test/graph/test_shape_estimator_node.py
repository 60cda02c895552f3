"""The shape_estimator node on real rclpy: it answers tendon states with the estimate, the fused
markers (the mocap's where seen), the tip with its covariance and its diagnostics, at its rate;
states it cannot use are counted, never a crash."""
import math
import time

import numpy as np
import pytest

from soft_arm_model import build_model, marker_positions, solve_equilibrium, tendon_lengths


def test_the_node_publishes_estimate_fused_tip_and_diagnostics():
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_ros.contract import QOS
    from soft_arm_ros.conversions import joint_state, markers_of, pose_array

    model = build_model()
    u = np.array([0.5, 2.0, 1.5, 0.3])
    q = solve_equilibrium(model, u).q
    s = model.rest_tendon_lengths - tendon_lengths(model, q)
    true = marker_positions(model, q)
    rclpy.init()
    try:
        node = ShapeEstimatorNode()
        peer = rclpy.create_node("peer")
        state = peer.create_publisher(JointState, "tendon/state", QOS["tendon/state"])
        frames = peer.create_publisher(PoseArray, "mocap/markers", QOS["mocap/markers"])
        got = {"estimate": [], "fused": [], "tip": [], "diagnostics": []}
        peer.create_subscription(PoseArray, "estimate/markers", got["estimate"].append,
                                 QOS["estimate/markers"])
        peer.create_subscription(PoseArray, "fused/markers", got["fused"].append, QOS["fused/markers"])
        peer.create_subscription(PoseWithCovarianceStamped, "estimate/tip", got["tip"].append,
                                 QOS["estimate/tip"])
        peer.create_subscription(DiagnosticArray, "/diagnostics", got["diagnostics"].append, 10)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(peer)
        names = model.tendon_names
        deadline = time.monotonic() + 10.0
        while not all(peer.count_subscribers(t) for t in ("tendon/state", "mocap/markers")) \
                or not peer.count_publishers("fused/markers"):
            executor.spin_once(timeout_sec=0.01)
            assert time.monotonic() < deadline
        seen = true + np.array([5e-4, 0.0, 0.0])           # the mocap's own calibration error
        seen[-1] = np.nan                                   # the tip occluded
        for k in range(200):                                # 0.4 s of states at 500 Hz
            if k % 2 == 0:
                frames.publish(pose_array(seen, k * 0.002))
            state.publish(joint_state(names, k * 0.002, position=s, velocity=np.zeros(4), effort=u))
            if k == 100:
                state.publish(joint_state(names, k * 0.002, position=s + np.array([math.nan, 0, 0, 0]),
                                          velocity=np.zeros(4), effort=u))
                # the topic keeps only its latest state (best effort, depth 1): the next one would
                # replace this one if the node had not taken it yet, as a loaded machine lets happen
                taken = time.monotonic() + 5.0
                while node.rejected == 0 and time.monotonic() < taken:
                    executor.spin_once(timeout_sec=0.002)
                assert node.rejected == 1, "the state with a NaN shortening was not counted within 5 s"
            for _ in range(3):
                executor.spin_once(timeout_sec=0.002)

        def updates():
            status = [st for m in got["diagnostics"] for st in m.status if st.name == "shape_estimator"]
            return int({kv.key: kv.value for kv in status[-1].values}["updates"]) if status else 0

        end = time.monotonic() + 3.0                        # the next report, once a second
        while updates() < 90 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        # one update per 4 ms of state time: about half the states
        assert 60 <= len(got["estimate"]) <= 110 and len(got["fused"]) == len(got["estimate"])
        estimate, fused = markers_of(got["estimate"][-1]), markers_of(got["fused"][-1])
        assert np.all(np.isfinite(estimate)) and np.all(np.isfinite(fused))
        np.testing.assert_allclose(estimate, true, atol=1e-3)
        # fused, update by update: the frame's markers where the mocap saw them (the estimate's
        # when no frame came since the last update), the estimate's tip where it did not
        with_frame = 0
        for e, f in zip(got["estimate"], got["fused"]):
            e, f = markers_of(e), markers_of(f)
            np.testing.assert_array_equal(f[-1], e[-1])
            with_frame += np.array_equal(f[:-1], seen[:-1])
            assert np.array_equal(f[:-1], seen[:-1]) or np.array_equal(f[:-1], e[:-1])
        assert with_frame >= len(got["fused"]) // 2 and not np.array_equal(estimate[:-1], seen[:-1])
        tip = got["tip"][-1]
        cov = np.array(tip.pose.covariance).reshape(6, 6)[:3, :3]
        assert np.all(np.linalg.eigvalsh(cov) > 0) and np.sqrt(np.trace(cov)) < 0.05
        assert node.rejected == 1
        status = [st for m in got["diagnostics"] for st in m.status if st.name == "shape_estimator"]
        values = {kv.key: kv.value for kv in status[-1].values}
        assert int(values["updates"]) > 50 and float(values["stiffness_scale"]) == pytest.approx(1.0, abs=0.1)
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize("jump", [1000.0, -5.0])
def test_a_stepped_state_clock_is_counted_and_neither_stops_the_updates_nor_inflates_the_estimate(jump):
    """The states' stamps jump by ``jump`` [s] halfway (NTP, another clock): the estimate goes on
    at its rate, the step is counted, and the tip's uncertainty stays what it was (a 1000 s gap taken
    as elapsed time would let the random walk grow by 1000 s)."""
    import rclpy

    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_ros.conversions import joint_state

    model = build_model()
    u = np.array([0.5, 2.0, 1.5, 0.3])
    s = model.rest_tendon_lengths - tendon_lengths(model, solve_equilibrium(model, u).q)
    rclpy.init()
    try:
        node = ShapeEstimatorNode()
        sigma = []
        for k in range(400):                                # 0.8 s of states at 500 Hz
            stamp = k * 0.002 + (jump if k >= 200 else 0.0)
            node.on_state(joint_state(model.tendon_names, stamp, position=s, velocity=np.zeros(4), effort=u))
            if k in (199, 201, 399):
                sigma.append(float(node.core.estimate().marker_sigma[-1]))
        assert node.clock.steps == 1 and node.rejected == 0
        assert 195 <= node.core.counts["updates"] <= 205         # one per 4 ms of state time
        assert sigma[1] < 1.1 * sigma[0] and sigma[2] < 1.1 * sigma[0], sigma
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.fixture
def reporting_node():
    """A shape_estimator node on real rclpy whose diagnostics are kept in a list, and a function
    that gives it the states of samples k0..k1 (500 Hz) at the tensions ``u`` [N] with the
    shortenings of the model's equilibrium under [0.5, 2, 1.5, 0.3] N."""
    import rclpy

    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_ros.conversions import joint_state

    model = build_model()
    held = np.array([0.5, 2.0, 1.5, 0.3])
    s = model.rest_tendon_lengths - tendon_lengths(model, solve_equilibrium(model, held).q)
    rclpy.init()
    try:
        node = ShapeEstimatorNode()
        published = []
        node.diagnostics_pub.publish = published.append

        def states(k0, k1, u=held):
            for k in range(k0, k1):
                node.on_state(joint_state(model.tendon_names, k * 0.002, position=s, velocity=np.zeros(4),
                                          effort=u))
        yield node, published, states
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def _status(published):
    """The last diagnostics' status and its values."""
    status = published[-1].status[0]
    return status, {v.key: v.value for v in status.values}


def test_states_at_tensions_without_an_equilibrium_are_said_on_diagnostics_not_a_crash(reporting_node):
    """Tensions the model holds no equilibrium for (1e5 N on one tendon, a torque reading gone
    wrong) before the first start: the node goes on (its start's error ended the process), publishes
    no marker it stands by, and its diagnostics warn with the samples that could not start; states
    at sane tensions then start the estimate."""
    from diagnostic_msgs.msg import DiagnosticStatus
    node, published, states = reporting_node
    states(0, 20, [1e5, 0.0, 0.0, 0.0])
    assert not node.core.started and node.core.counts["start_failures"] >= 5
    assert node.undefended >= 5 and "no start" in node.distrust, node.distrust
    node.publish_diagnostics(0.04, node.core.estimate())
    status, values = _status(published)
    assert status.level == DiagnosticStatus.WARN and int(values["start_failures"]) >= 5
    assert "with no start" in status.message, status.message
    states(20, 40)
    assert node.core.started and node.core.distrust is None


def test_tendon_states_that_stop_coming_are_said_on_diagnostics(reporting_node):
    """The states stop (the inner loop or the driver gone): the heartbeat's diagnostics warn that
    the estimate is that of the last update, and how long ago, where they said OK."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from soft_arm_control.shape_estimator_node import REPORT_PERIOD
    node, published, states = reporting_node
    states(0, 10)
    node.publish_diagnostics(*node._last)
    assert _status(published)[0].level == DiagnosticStatus.OK
    node._updated_at -= 3 * REPORT_PERIOD                  # three report periods without a state
    node._reported_at -= REPORT_PERIOD
    node._heartbeat()
    status, values = _status(published)
    assert status.level == DiagnosticStatus.WARN and float(values["since_update_s"]) >= 3 * REPORT_PERIOD
    assert status.message.startswith("no update for 3"), status.message


def test_a_frame_stamped_far_from_the_state_is_left_out_and_counted_not_fused_as_measured():
    """A frame stamped 0.3 s before the state it would be weighed with (queued behind a stall of
    the mocap bridge), or 0.3 s after it (a clock that disagrees): the estimate does not take its
    markers, fused/markers carries the estimate's and fused/tip the estimate's covariance, the frame
    is counted and /diagnostics warns; a frame 4 ms old is fused as measured."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus

    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_ros.conversions import joint_state, markers_of, pose_array

    model = build_model()
    u = np.array([0.5, 2.0, 1.5, 0.3])
    q = solve_equilibrium(model, u).q
    s = model.rest_tendon_lengths - tendon_lengths(model, q)
    elsewhere = marker_positions(model, q) + np.array([0.0, 0.0, 1e-3])     # 1 mm from the estimate
    rclpy.init()
    try:
        node = ShapeEstimatorNode()
        fused, tips, diagnostics = [], [], []
        node.fused_pub.publish, node.fused_tip_pub.publish = fused.append, tips.append
        node.diagnostics_pub.publish = diagnostics.append
        t = 10.0
        for k in range(50):
            node.on_state(joint_state(model.tendon_names, t + k * 0.004, position=s,
                                      velocity=np.zeros(4), effort=u))
        used = node.core.counts["markers_used"]
        for offset, stale in ((-0.3, True), (0.3, True), (-0.004, False)):
            t += 0.2
            node.on_markers(pose_array(elsewhere, t + offset))
            node.on_state(joint_state(model.tendon_names, t, position=s, velocity=np.zeros(4), effort=u))
            tip_variance = np.array(tips[-1].pose.covariance).reshape(6, 6)[:3, :3]
            taken = not np.allclose(markers_of(fused[-1]), elsewhere, atol=1e-9)
            assert taken == stale and (np.all(tip_variance == 0.0) != stale), offset
            assert (node.core.counts["markers_used"] > used) != stale
            used = node.core.counts["markers_used"]
        assert node.stale_frames == 2
        node._reported_at = -math.inf
        node._heartbeat()
        status = diagnostics[-1].status[0]
        values = {kv.key: kv.value for kv in status.values}
        assert status.level == DiagnosticStatus.WARN and values["stale_frames"] == "2"
        assert "2 mocap frames left out" in status.message
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_configured_dynamic_the_node_runs_the_dynamic_estimate_with_the_controllers_rotors():
    """``estimator.process_model: dynamic`` on the node: the dynamic filter, the rotors' reflected
    mass from ``control.rotor_mass``; at rest on the tendons alone the tip it publishes is within
    the covariance it publishes (chi-square, 3 degrees of freedom, 0.1 %), and its diagnostics say
    how long the rest must last before the tendons teach the stiffness and friction."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from soft_arm_control.dynamic_estimation import DynamicShapeEstimator
    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_ros.contract import QOS
    from soft_arm_ros.conversions import joint_state

    model = build_model()
    u = np.array([0.5, 2.0, 1.5, 0.3])
    q = solve_equilibrium(model, u).q
    s = model.rest_tendon_lengths - tendon_lengths(model, q)
    rclpy.init()
    try:
        node = ShapeEstimatorNode(parameter_overrides=[Parameter("estimator.process_model", value="dynamic"),
                                                       Parameter("control.rotor_mass", value=0.4)])
        assert isinstance(node.core, DynamicShapeEstimator) and np.all(node.core.rotor == 0.4)
        peer = rclpy.create_node("peer")
        state = peer.create_publisher(JointState, "tendon/state", QOS["tendon/state"])
        tips = []
        peer.create_subscription(PoseWithCovarianceStamped, "estimate/tip", tips.append, QOS["estimate/tip"])
        settling = []

        def report(msg):
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                if status.name == "shape_estimator" and int(values["updates"]) > 0:
                    settling.append(float(values["rest_settling_time_s"]))
        peer.create_subscription(DiagnosticArray, "/diagnostics", report, QOS["/diagnostics"])
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(peer)
        deadline = time.monotonic() + 10.0
        while not peer.count_subscribers("tendon/state") or not peer.count_publishers("estimate/tip"):
            executor.spin_once(timeout_sec=0.01)
            assert time.monotonic() < deadline
        for k in range(200):                                # 0.4 s of states at 500 Hz
            state.publish(joint_state(model.tendon_names, k * 0.002, position=s, velocity=np.zeros(4),
                                      effort=u))
            for _ in range(3):
                executor.spin_once(timeout_sec=0.002)
        end = time.monotonic() + 3.0
        while len(tips) < 90 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        assert len(tips) >= 60
        p = tips[-1].pose.pose.position
        error = np.array([p.x, p.y, p.z]) - marker_positions(model, q)[-1]
        covariance = np.array(tips[-1].pose.covariance).reshape(6, 6)[:3, :3]
        assert error @ np.linalg.solve(covariance, error) <= 16.27, (error, np.diag(covariance))
        end = time.monotonic() + 3.0                        # the next report, once a second
        while not settling and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        assert settling and 1.0 < settling[-1] < 10.0, settling
    finally:
        rclpy.try_shutdown()


def test_an_identified_arm_file_after_estimator_yaml_gives_the_node_its_priors(tmp_path):
    """The rig's way to an identified arm: ``--params-file`` the file soft-arm-identify wrote; the
    node's estimator takes the priors it carries, the arm it describes."""
    import rclpy

    from soft_arm_control.shape_estimator_node import ShapeEstimatorNode
    from soft_arm_experiments.identify_cli import write_identified_arm
    from soft_arm_model import load_arm_config

    arm = load_arm_config(overrides={"material.youngs_modulus": 1.8e5})
    path = str(tmp_path / "arm_identified.yaml")
    priors = {"prior.stiffness": 0.004, "prior.friction": 0.01, "prior.tendon_offset": 0.013,
              "prior.tendon_angle": 0.014, "prior.payload": 1e-5}
    write_identified_arm(path, arm, (np.eye(3), np.zeros(3)), priors=priors)
    rclpy.init()
    try:
        node = ShapeEstimatorNode(cli_args=["--ros-args", "--params-file", path])
        c = node.config
        assert (c.prior_stiffness, c.prior_friction, c.prior_tendon_offset, c.prior_tendon_angle,
                c.prior_payload) == tuple(priors.values())
        assert node.model.config.material.youngs_modulus == 1.8e5
        assert node.get_parameter("estimator.prior.tendon_angle").value == 0.014
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
