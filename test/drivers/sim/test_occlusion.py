"""The simulated mocap's occlusions: lines of sight against the arm's body, fields of view, random
dropouts and bursts, their configuration, and the frames of the simulated rig."""
import math
import time
from dataclasses import replace

import numpy as np
import pytest

from soft_arm_drivers.sim.occlusion import OcclusionConfig, Occlusions, body, cameras_seeing, segment_distance
from soft_arm_drivers.sim.plant_config import load_plant_config
from soft_arm_drivers.sim.simulated_rig import SimulatedRig
from soft_arm_model import ArmData, build_model, load_arm_config, marker_positions, solve_equilibrium
from soft_arm_model.config import with_basis
from soft_arm_model.parameters import ConfigError

# eight cameras 0.3 m around the z axis, 1 m above a horizontal rod along x at z = 0
RING = tuple((0.3 * math.cos(a), 0.3 * math.sin(a), 1.0) for a in np.arange(8) * math.pi / 4)
ROD = np.array([[x, 0.0, 0.0] for x in np.linspace(-0.2, 0.2, 9)])
ROD_RADII = np.full(9, 0.05)
ROD_ARCS = np.linspace(0.0, 0.4, 9)


def _config(**kw):
    kw.setdefault("cameras", RING)
    kw.setdefault("aim", (0.0, 0.0, 0.0))
    kw.setdefault("field_of_view", math.radians(120))
    return OcclusionConfig(**kw)


def test_segment_distance_matches_a_dense_sampling():
    rng = np.random.default_rng(3)
    p, d, a, e = (rng.normal(size=(200, 3)) for _ in range(4))
    e[:20] = 0.0                                        # degenerate segments: points
    d[20:40] = 2.5 * e[20:40]                           # parallel pairs
    s = np.linspace(0.0, 1.0, 401)
    brute = np.array([np.min(np.linalg.norm((p[i] + s[:, None] * d[i])[:, None, :]
                                            - (a[i] + s[:, None] * e[i])[None, :, :], axis=2))
                      for i in range(200)])
    exact = np.array([segment_distance(p[i], d[i], a[i], e[i]) for i in range(200)])
    assert np.all(exact <= brute + 1e-12)
    np.testing.assert_allclose(exact, brute, atol=0.02 * np.linalg.norm(d, axis=1).max())


def test_a_marker_behind_the_body_from_every_camera_is_occluded_and_one_in_plain_view_is_seen():
    config = _config()
    hidden, plain = np.array([0.0, 0.0, -0.1]), np.array([0.0, 0.5, -0.1])
    markers = np.array([hidden, plain])
    count = cameras_seeing(config, markers, np.array([2.0, 2.0]), ROD, ROD_RADII, ROD_ARCS)
    assert count.tolist() == [0, 8]
    # without the body, or with self-occlusion off, every camera sees both
    assert cameras_seeing(config, markers).tolist() == [8, 8]
    assert cameras_seeing(_config(self_occlusion=False), markers, np.array([2.0, 2.0]), ROD, ROD_RADII,
                          ROD_ARCS).tolist() == [8, 8]


def test_the_count_is_the_exact_test_on_every_capsule():
    """The count tests a capsule exactly only where a line of sight passes within its bounding
    sphere: on bent chains of long thin and short fat capsules, with markers scattered around
    them so that many lines of sight graze a capsule, it is the exact test's on every capsule."""
    rng = np.random.default_rng(11)
    config = _config(field_of_view=math.radians(170))
    compared = blocked = 0
    for trial in range(40):
        P = int(rng.integers(3, 12))
        steps = rng.normal(size=(P - 1, 3)) * rng.choice([0.02, 0.15])
        points = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
        radii = rng.uniform(0.005, 0.06, P)
        arcs = np.concatenate([[0.0], np.cumsum(np.linalg.norm(steps, axis=1))])
        markers = points[rng.integers(0, P, 30)] + rng.normal(size=(30, 3)) * 0.08
        count = cameras_seeing(config, markers, np.full(30, 100.0), points, radii, arcs)
        capsule_radii = np.maximum(radii[:-1], radii[1:])
        for m, marker in enumerate(markers):
            exact = 0
            for camera in np.array(RING):
                sight = marker - camera
                hits = [segment_distance(camera, sight, points[k], points[k + 1] - points[k])
                        < capsule_radii[k] for k in range(P - 1)]
                exact += not any(hits)
                blocked += any(hits)
            assert count[m] == exact, (trial, m)
            compared += 1
    assert compared == 1200 and blocked > 1000          # the lines of sight meet the body often


def test_the_markers_own_ring_does_not_hide_it():
    """A marker on the rod's axis at arc 0.2 m: the capsules within two radii of it are its ring."""
    config = _config()
    marker = np.array([[0.0, 0.0, 0.0]])
    assert cameras_seeing(config, marker, np.array([0.2]), ROD, ROD_RADII, ROD_ARCS).tolist() == [8]
    # the same point counted as the end of another body part (arc 2 m) is inside the rod: hidden
    assert cameras_seeing(config, marker, np.array([2.0]), ROD, ROD_RADII, ROD_ARCS).tolist() == [0]


def test_the_field_of_view_is_a_cone_of_the_given_full_angle():
    config = _config(cameras=((0.0, 0.0, 1.0),), aim=(0.0, 0.0, 0.0), field_of_view=math.radians(60))
    inside = np.array([[math.tan(math.radians(29)), 0.0, 0.0]])
    outside = np.array([[math.tan(math.radians(31)), 0.0, 0.0]])
    assert cameras_seeing(config, inside).tolist() == [1] and cameras_seeing(config, outside).tolist() == [0]


def test_the_hanging_arm_is_seen_by_most_of_the_default_ring():
    arm = load_arm_config()
    plant = load_plant_config(arm)
    model = build_model(arm)
    data = ArmData(model)
    marker_positions(model, solve_equilibrium(model, np.full(4, 0.5)).q, data)
    points, radii, arcs = body(model, data)
    assert np.all(np.diff(arcs) >= 0) and points.shape == (arcs.size, 3)
    seen = cameras_seeing(plant.occlusion, data.marker_p, model.marker_X, points, radii, arcs)
    assert np.all(seen >= 6), seen


def test_of_arm_is_visible_on_the_arms_body_frame_for_frame():
    """of_arm (the model's layout kept between frames) gives what visible gives on body()'s points,
    frame for frame with the same random losses, through bent poses (markers hidden by the arm),
    for a second model and inside a blackout."""
    arm = load_arm_config()
    config = load_plant_config(arm).occlusion
    config = OcclusionConfig(**{**config.__dict__, "dropout": 0.1, "burst_fraction": (0.1, 0.2, 0.1, 0.3),
                                "blackout": (0.5, 0.6)})
    d = arm.discretisation
    other = with_basis(replace(arm, geometry=replace(arm.geometry, tip_radius=0.5 * arm.geometry.tip_radius)),
                       d.legendre_order, tuple(g + 2 for g in d.gauss_points))
    models = [build_model(arm), build_model(other)]
    assert models[1].X.size != models[0].X.size
    fast, plain = (Occlusions(config, 4, 1 / 240, 7) for _ in range(2))
    rng = np.random.default_rng(2)
    hidden = 0
    for frame in range(120):
        model = models[frame // 60]
        data = ArmData(model)
        u = rng.uniform(0.0, 4.0, 4)
        marker_positions(model, solve_equilibrium(model, u).q, data)
        t = frame / 100
        seen = fast.of_arm(model, data, t)
        points, radii, arcs = body(model, data)
        assert np.array_equal(seen, plain.visible(data.marker_p, model.marker_X, points, radii, arcs, t))
        hidden += int((cameras_seeing(config, data.marker_p, model.marker_X, points, radii, arcs)
                       < config.min_cameras).sum())
    assert hidden > 0          # some poses hide a marker from the cameras, not only the random losses


def test_dropouts_and_bursts_have_the_configured_rate_and_length():
    period = 1 / 240
    drop = Occlusions(_config(dropout=0.1), 1, period, seed=1)
    seen = np.array([drop.visible(np.zeros((1, 3)))[0] for _ in range(20000)])
    assert abs((~seen).mean() - 0.1) < 4 * math.sqrt(0.1 * 0.9 / 20000)
    bursts = Occlusions(_config(burst_fraction=(0.3,), burst_duration=0.5), 1, period, seed=2)
    lost = np.array([not bursts.visible(np.zeros((1, 3)))[0] for _ in range(240 * 400)])
    edges = np.flatnonzero(np.diff(lost.astype(int)))
    runs = np.diff(edges)[::2] if lost[edges[0] + 1] else np.diff(edges)[1::2]
    assert abs(lost.mean() - 0.3) < 0.04
    assert runs.mean() * period == pytest.approx(0.5, rel=0.15)


def test_the_same_seed_draws_the_same_losses():
    def draw(seed):
        occ = Occlusions(_config(dropout=0.05, burst_fraction=(0.1, 0.2), burst_duration=0.2), 2, 0.01, seed)
        return np.array([occ.visible(np.zeros((2, 3))) for _ in range(500)])
    assert np.array_equal(draw([1, 1]), draw([1, 1])) and not np.array_equal(draw([1, 1]), draw([2, 1]))


@pytest.mark.parametrize("overrides, message", [
    ({"mocap.occlusion.min_cameras": 9}, "plant.mocap.occlusion.min_cameras = 9"),
    ({"mocap.occlusion.cameras.positions": "[0.0, 0.0, -0.2]"}, "at least 0.1 m from the aim point"),
    ({"mocap.occlusion.cameras.positions": "[1.0, 0.0]"}, "plant.mocap.occlusion.cameras.positions"),
    ({"mocap.occlusion.bursts.fraction": "[0.1, 0.1]"}, "one per marker"),
    ({"mocap.occlusion.dropout": 0.9}, r"plant.mocap.occlusion.dropout.*\[0, 0.5\]"),
    ({"mocap.occlusion.cameras.field_of_view_deg": 180.0}, "field_of_view_deg"),
])
def test_bad_occlusion_values_name_the_key(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_plant_config(load_arm_config(), overrides=overrides)


def _rig(overrides):
    arm = load_arm_config()
    plant = load_plant_config(arm, overrides=overrides)
    u = np.full(4, 0.5)
    return SimulatedRig(build_model(plant.plant_arm(arm)), plant, np.zeros(4), u), u


def _frames(rig, u, count):
    out = []
    while len(out) < count:
        frame, _ = rig.begin_step()
        if frame is not None:
            out.append(frame)
        rig.end_step(u)
    return out


def test_the_rigs_frames_carry_nan_for_the_markers_not_seen_and_the_same_noise_on_the_others():
    lossy, u = _rig({"mocap.occlusion.dropout": 0.3})
    clean, _ = _rig({"mocap.occlusion.enabled": False})
    a, b = _frames(lossy, u, 60), _frames(clean, u, 60)
    unseen = np.array([~f.visible for f in a])
    assert 0.15 < unseen.mean() < 0.45 and all(f.visible.all() for f in b)
    for fa, fb in zip(a, b):
        assert np.isnan(fa.markers[~fa.visible]).all()
        np.testing.assert_array_equal(fa.markers[fa.visible], fb.markers[fa.visible])


def test_the_emulated_motive_server_applies_the_blackout_from_its_start():
    """plant.mocap.occlusion.blackout on the emulated rig: seconds since the Motive server started;
    inside it every marker is NaN (flagged occluded), after it the markers come back."""
    from soft_arm_drivers.can.driver_config import load_driver_config
    from soft_arm_drivers.can.loopback_bus import free_udp_ports
    from soft_arm_drivers.mocap.bridge_config import load_mocap_config
    from soft_arm_drivers.sim.emulated_hardware import HardwareSpec
    from soft_arm_drivers.sim.configuration_history import ConfigurationHistory
    from soft_arm_drivers.sim.emulated_motive import start_motive
    from soft_arm_drivers.sim.emulated_rig import load_emulator_config, read_emulated_motors
    arm = load_arm_config()
    plant = load_plant_config(arm, overrides={"mocap.occlusion.blackout": [0.0, 30.0],
                                              "mocap.occlusion.dropout": 0.0})
    model = build_model(plant.plant_arm(arm))
    q = solve_equilibrium(model, np.full(4, 0.5)).q
    spec = HardwareSpec(load_driver_config(overrides=read_emulated_motors()), arm, plant,
                        load_emulator_config(),
                        load_mocap_config(overrides={"mocap.command_port": free_udp_ports(1)[0],
                                                     "mocap.data_port": 0}))
    history = ConfigurationHistory(model.n, 2, 1e-3)
    history.append(time.time(), q)                  # the arm holding q from now on
    emulator = start_motive(spec, model, history)
    try:
        markers = emulator._markers                  # what the server streams at an exposure time
        now = time.time()
        assert np.isnan(markers(now)).all()
        assert np.isfinite(markers(now + 31.0)).all()
    finally:
        emulator.close()
