"""The live view's scene (soft_arm_experiments.live_view), decoded from its protobuf wire form as
the Foxglove app decodes it: the tube ends at the backbone's tip, unseen markers are not drawn, the
uncertainty ellipsoid has the covariance's axes, the server binds loopback unless told otherwise."""
import numpy as np
import pytest
from foxglove import messages

from foxglove_wire import cylinder_ends, decoder, rotate
from soft_arm_experiments.live_view import LiveView, check_bind, radii


SCHEMA = messages.SceneUpdate.get_schema()
DECODE = decoder(SCHEMA.name, SCHEMA.data)


def entity(scene, name):
    found = [e for e in scene.entities if e.id == name]
    assert len(found) == 1, [e.id for e in scene.entities]
    return found[0]


BACKBONE = np.array([[0.0, 0.0, 0.0], [0.0, 0.01, -0.1], [0.03, 0.02, -0.2], [0.08, 0.0, -0.28]])


def test_the_tube_runs_segment_by_segment_to_the_tip_and_tapers():
    view = LiveView(0.02, 0.01)
    view.take_backbone(1.0, BACKBONE)
    arm = entity(DECODE(view.scene().encode()), "arm")
    assert arm.frame_id == "arm_base" and len(arm.cylinders) == len(BACKBONE) - 1
    point_radii = radii(BACKBONE, 0.02, 0.01)
    for a, c in enumerate(arm.cylinders):
        bottom, top = cylinder_ends(c)
        np.testing.assert_allclose(bottom, BACKBONE[a], atol=1e-9)
        np.testing.assert_allclose(top, BACKBONE[a + 1], atol=1e-9)
        assert c.bottom_scale * c.size.x / 2 == pytest.approx(point_radii[a])
        assert c.top_scale * c.size.x / 2 == pytest.approx(point_radii[a + 1])
    assert point_radii[0] == 0.02 and point_radii[-1] == pytest.approx(0.01)


def test_unseen_markers_are_named_not_drawn_where_they_were():
    view = LiveView(0.02, 0.01)
    view.take_mocap(1.0, [[0.0, 0.0, -0.1], [0.0, 0.0, -0.2], [0.0, 0.0, -0.3]])
    view.take_mocap(1.1, [[0.0, 0.0, -0.1], [np.nan] * 3, [0.0, 0.0, -0.31]])
    mocap = entity(DECODE(view.scene().encode()), "mocap")
    drawn = [(s.pose.position.x, s.pose.position.y, s.pose.position.z) for s in mocap.spheres]
    assert drawn == [(0.0, 0.0, -0.1), (0.0, 0.0, -0.31)]
    assert {kv.key: kv.value for kv in mocap.metadata} == {"unseen": "2"}


def test_the_tip_ellipsoid_has_the_covariance_s_axes_and_one_sigma():
    rng = np.random.default_rng(0)
    basis, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    sigma = np.array([0.002, 0.005, 0.011])
    covariance = basis @ np.diag(sigma ** 2) @ basis.T
    view = LiveView(0.02, 0.01)
    view.take_estimate(1.0, [[0.0, 0.0, -0.1], [0.01, 0.0, -0.3]], covariance)
    spheres = entity(DECODE(view.scene().encode()), "estimate").spheres
    assert len(spheres) == 3                     # two markers and the tip's ellipsoid
    e = spheres[-1]
    np.testing.assert_allclose([e.pose.position.x, e.pose.position.y, e.pose.position.z], [0.01, 0.0, -0.3])
    for k, size in enumerate([e.size.x, e.size.y, e.size.z]):
        axis = rotate(e.pose.orientation, np.eye(3)[k])
        # each axis of the ellipsoid is an eigenvector, its diameter two standard deviations
        np.testing.assert_allclose(covariance @ axis, (size / 2) ** 2 * axis, atol=1e-12)
    assert sorted([e.size.x, e.size.y, e.size.z]) == pytest.approx(sorted(2 * sigma))


def test_the_target_sits_over_its_marker_and_the_trail_follows_the_tip():
    view = LiveView(0.02, 0.01, trail=0.25)
    view.take_mocap(0.0, [[0.0, 0.0, -0.1], [0.02, 0.03, -0.3]])
    view.take_target(["marker2.x", "marker2.z"], [0.05, -0.25])
    np.testing.assert_allclose(view.target_points(), [[0.05, 0.03, -0.25]])
    for k in range(5):
        view.take_backbone(0.1 * k, BACKBONE + [0.0, 0.0, 0.001 * k])
    scene = DECODE(view.scene().encode())
    trail = entity(scene, "trail").lines[0]
    assert [round(p.z, 6) for p in trail.points] == [-0.278, -0.277, -0.276]      # the last 0.25 s
    assert entity(scene, "target").spheres[0].pose.position.y == pytest.approx(0.03)


@pytest.mark.parametrize("host, remote, refused", [
    ("127.0.0.1", False, False), ("localhost", False, False), ("::1", False, False),
    ("0.0.0.0", False, True), ("192.168.1.20", False, True), ("0.0.0.0", True, False)])
def test_a_server_beyond_loopback_must_be_asked_for(host, remote, refused):
    if refused:
        with pytest.raises(ValueError, match="view.remote"):
            check_bind(host, remote)
    else:
        check_bind(host, remote)


def test_the_layout_shows_only_what_the_live_view_serves():
    """config/foxglove_layout.json: every panel of its tree is configured, the 3D panel draws the
    scene in arm_base, and every plotted path is a field of a series the node logs."""
    import json
    import re

    from soft_arm_model.parameters import default_config_dir
    with open(f"{default_config_dir()}/foxglove_layout.json", encoding="utf-8") as fh:
        layout = json.load(fh)

    def panels(node):
        return [node] if isinstance(node, str) else panels(node["first"]) + panels(node["second"])

    configs = layout["configById"]
    assert set(panels(layout["layout"])) == set(configs)
    three_d = configs["3D!arm"]
    assert three_d["followTf"] == "arm_base" and set(three_d["topics"]) == {"/view/scene"}
    fields = {"/view/tendons": {"tension", "shortening", "reference", "rate"},
              "/view/task": {"error", "target", "measured"}}
    for name, config in configs.items():
        for path in config.get("paths", []):
            topic, field = re.match(r"^(/view/\w+)\.(\w+)\[\d\]$", path["value"]).groups()
            assert field in fields[topic], (name, path)


def test_the_task_series_is_the_target_less_what_the_mocap_measured():
    view = LiveView(0.02, 0.01)
    assert view.task() is None
    view.take_target(["marker2.x", "marker1.z"], [0.05, -0.1])
    view.take_mocap(1.0, [[0.0, 0.0, -0.12], [np.nan] * 3])
    task = view.task()
    assert task["labels"] == ["marker2.x", "marker1.z"] and task["target"] == [0.05, -0.1]
    assert np.isnan(task["measured"][0]) and task["error"][1] == pytest.approx(-0.02)


def test_the_launcher_waits_for_its_live_view_and_names_what_it_waited_for():
    """``live_view``'s wait (:func:`~.live_launch._served`): the address the process writes once set
    up; a process that ends first, one that never reports, and a stop asked for meanwhile each end
    the wait with a RuntimeError naming the address it waited on."""
    import os
    import subprocess
    import sys

    from soft_arm_experiments.live_launch import _served

    def waiting(code: str, timeout: float = 10.0, stopped=lambda: False):
        read, write = os.pipe()
        process = subprocess.Popen([sys.executable, "-c", code.format(fd=write)], pass_fds=(write,))
        os.close(write)
        try:
            return _served(process, read, "127.0.0.1:9", timeout, stopped)
        finally:
            os.close(read)
            process.kill()
            process.wait()

    import_os = "import os, time; "
    assert waiting(import_os + "os.write({fd}, b'ws://127.0.0.1:'); time.sleep(0.2); "
                   "os.write({fd}, b'4242\\n'); time.sleep(30)") == "ws://127.0.0.1:4242"
    with pytest.raises(RuntimeError, match=r"127.0.0.1:9 ended before it was set up \(exit status 3"):
        waiting("raise SystemExit(3)")
    with pytest.raises(RuntimeError, match=r"127.0.0.1:9 was not set up within 0.5 s"):
        waiting(import_os + "time.sleep(30)", timeout=0.5)
    with pytest.raises(RuntimeError, match="stopped while waiting for the live view on 127.0.0.1:9"):
        waiting(import_os + "time.sleep(30)", stopped=lambda: True)


def test_the_live_view_reports_its_address_only_to_a_launcher_that_waits():
    import os

    from soft_arm_experiments.live_launch import READY_FD, report_ready

    assert report_ready("ws://127.0.0.1:1", {}) is False          # the rig's ros2 run: no one waits
    read, write = os.pipe()
    environ = {READY_FD: str(write)}
    try:
        assert report_ready("ws://127.0.0.1:4242", environ) is True
        assert os.read(read, 100) == b"ws://127.0.0.1:4242\n" and READY_FD not in environ
        assert os.read(read, 100) == b""                          # and the pipe closed: EOF
        for bad in ("x", str(write)):                             # not a number; closed already
            with pytest.raises(ValueError, match=f"{READY_FD}='{bad}' names no pipe"):
                report_ready("ws://127.0.0.1:4242", {READY_FD: bad})
    finally:
        os.close(read)
