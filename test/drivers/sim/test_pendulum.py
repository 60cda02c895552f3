"""The strike experiment's pendulum and its contact, alone: the free swing against closed forms,
energy, impacts on a held capsule chain (time, restitution, momentum), a miss's closest approach."""
import numpy as np
import pytest

from soft_arm_control.pendulum_geometry import GRAVITY, PendulumConfig
from soft_arm_drivers.sim.pendulum import ArmSurface, Pendulum, closest_capsule, hertz_stiffness

E = 1.5e5          # Pa, arm.yaml's Young's modulus


def config(angle_deg=80.0, restitution=0.5, **kw):
    values = dict(pivot=np.array([0.0, 0.1, 0.06]), length=0.305, mass=0.021, ball_radius=0.015,
                  release_angle=np.deg2rad(angle_deg), direction=np.array([1.0, 0.0, 0.0]),
                  restitution=restitution)
    values.update(kw)
    return PendulumConfig(**values)


def swing(pendulum, duration, dt=1e-3, surface=None):
    """Times, positions, velocities and contacts of ``duration`` [s] of swing."""
    t, p, v, contacts = [0.0], [pendulum.p.copy()], [pendulum.v.copy()], []
    for k in range(int(round(duration / dt))):
        contacts.append(pendulum.advance(dt, surface))
        t.append((k + 1) * dt)
        p.append(pendulum.p.copy())
        v.append(pendulum.v.copy())
    return np.array(t), np.array(p), np.array(v), contacts


def column(x, y, z_top=0.05, z_bottom=-0.40, radius=0.01, n=12):
    """A vertical capsule chain at (x, y), held still (an arm that does not move)."""
    z = np.linspace(z_top, z_bottom, n)
    points = np.column_stack([np.full(n, x), np.full(n, y), z])
    jac = np.zeros((n, 3, 3))
    jac[:, :, :] = np.eye(3)
    return ArmSurface(points, np.zeros((n, 3)), np.full(n, radius), jac)


def test_a_small_swing_has_the_small_angle_period_and_keeps_its_energy():
    c = config(angle_deg=3.0)
    pendulum = Pendulum(c, E)
    pendulum.release()
    t, p, v, _ = swing(pendulum, 3.0)
    x = p[:, 0] - c.pivot[0]
    crossings = t[1:][(x[:-1] > 0) & (x[1:] <= 0)]           # once per period, going the same way
    period = np.mean(np.diff(crossings))
    expected = 2 * np.pi * np.sqrt(c.length / np.linalg.norm(GRAVITY))
    assert period == pytest.approx(expected * (1 + np.deg2rad(3.0) ** 2 / 16), rel=2e-4)
    energy = 0.5 * c.mass * np.einsum("ij,ij->i", v, v) - c.mass * (p - c.pivot) @ GRAVITY
    assert np.ptp(energy) < 1e-9 * c.mass * np.linalg.norm(GRAVITY) * c.length
    np.testing.assert_allclose(np.linalg.norm(p - c.pivot, axis=1), c.length, atol=1e-12)


def test_a_large_swing_reaches_its_lowest_point_at_the_elliptic_quarter_period():
    c = config(angle_deg=80.0)
    pendulum = Pendulum(c, E)
    pendulum.release()
    t, p, v, _ = swing(pendulum, 0.6, dt=1e-4)
    lowest = np.argmin(p[:, 2])
    assert t[lowest] == pytest.approx(c.time_to_lowest(), abs=2e-4)
    assert c.time_to_lowest() > 1.1 * np.pi / 2 * np.sqrt(c.length / 9.81)     # not the small-angle one
    assert np.linalg.norm(v[lowest]) == pytest.approx(c.peak_speed(), rel=1e-5)
    np.testing.assert_allclose(p[lowest], c.lowest_point, atol=3e-4)
    # the energy error over the whole swing shrinks with the step at the integrator's order
    # (RK4 with the ball put back on the sphere: at least third order, 1e-10 of the energy at 20 ms)
    errors = []
    for dt in (2e-2, 1e-2):
        pendulum = Pendulum(c, E)
        pendulum.release()
        e0 = pendulum.energy()
        swing(pendulum, 0.6, dt=dt)
        errors.append(abs(pendulum.energy() - e0))
    assert errors[1] < errors[0] / 8 and errors[0] < 1e-8 * c.mass * 9.81 * c.length


def test_a_held_ball_does_not_move():
    pendulum = Pendulum(config(), E)
    contact = pendulum.advance(1e-3, column(0.5, 0.5))
    np.testing.assert_array_equal(pendulum.p, config().held_position)
    assert contact.overlap == 0.0 and contact.gap > 0.3


def test_the_closest_capsule_is_the_chains_nearest_the_first_of_equals_and_needs_two_points():
    """Against every segment's closest point (the projection clipped to the segment), on random
    chains; of two capsules as close the first; a chain of one point refused."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        points, radii, centre = rng.normal(size=(9, 3)), rng.uniform(0.01, 0.05, 9), rng.normal(size=3)
        d = points[1:] - points[:-1]
        s = np.clip(np.einsum("ij,ij->i", centre - points[:-1], d) / np.einsum("ij,ij->i", d, d), 0, 1)
        q = points[:-1] + s[:, None] * d
        gaps = np.linalg.norm(centre - q, axis=1) - (radii[:-1] + s * np.diff(radii))
        i, fraction, point, gap = closest_capsule(points, radii, centre)
        assert i == np.argmin(gaps) and fraction == pytest.approx(s[i], abs=1e-12)
        np.testing.assert_allclose(point, q[i], atol=1e-12)
        assert gap == pytest.approx(gaps.min(), abs=1e-12)
    corner = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    i, fraction, point, gap = closest_capsule(corner, np.full(3, 0.1), np.array([0.0, 1.0, 0.0]))
    assert (i, fraction, gap) == (0, 1.0, pytest.approx(0.9)) and np.all(point == 0.0)
    with pytest.raises(ValueError, match="at least|P >= 2"):
        closest_capsule(corner[:1], np.full(1, 0.1), np.zeros(3))


def test_an_arm_surface_that_is_no_number_turns_the_ball_to_no_number_not_to_a_miss():
    """A NaN in the arm's points is said by the contact and the ball, never taken for an arm out of
    reach."""
    c = config()
    surface = column(c.lowest_point[0], c.lowest_point[1])
    surface.points[4, 2] = np.nan
    pendulum = Pendulum(c, E)
    pendulum.release()
    contact = pendulum.advance(1e-3, surface)
    assert np.isnan(contact.gap) and np.isnan(contact.force).any() and np.isnan(pendulum.p).any()


def test_each_step_leaves_new_float_arrays():
    """A reader keeping the ball's position has the one it took; a state given as integers is
    stepped as numbers, not truncated."""
    pendulum = Pendulum(config(), E)
    pendulum.release()
    before = pendulum.p
    kept = before.copy()
    pendulum.v = np.zeros(3, dtype=int)
    pendulum.advance(1e-3)
    assert pendulum.p is not before and np.array_equal(before, kept)
    assert pendulum.v.dtype == float and np.linalg.norm(pendulum.v) > 1e-3


def test_a_still_arm_in_the_path_is_struck_when_the_surfaces_meet_and_the_ball_rebounds():
    c = config(restitution=0.9)
    arm_radius = 0.01
    surface = column(c.lowest_point[0], c.lowest_point[1], radius=arm_radius)
    # the free swing says when the ball's surface first meets the column's
    free = Pendulum(c, E)
    free.release()
    t, p, v, _ = swing(free, 0.5, dt=1e-4)
    horizontal = np.linalg.norm(p[:, :2] - c.lowest_point[:2], axis=1)
    touch = t[np.argmax(horizontal <= arm_radius + c.ball_radius)]
    incoming = v[np.argmax(horizontal <= arm_radius + c.ball_radius)]

    struck = Pendulum(c, E)
    struck.release()
    t, p, v, contacts = swing(struck, 0.5, dt=1e-4, surface=surface)
    touching = np.array([k.overlap > 0 for k in contacts])
    first = np.argmax(touching)
    assert touching.any() and abs(t[first + 1] - touch) <= 2e-4
    last = first + np.argmin(touching[first:])
    assert 0 < (last - first) * 1e-4 < 0.02                     # a short, compliant contact
    outgoing = v[last + 1]
    # the ball comes back along x at about e times the incoming speed (Lankarani-Nikravesh for e near 1)
    assert outgoing[0] * incoming[0] < 0
    assert abs(outgoing[0] / incoming[0]) == pytest.approx(c.restitution, abs=0.05)
    # the column took the impulse the ball got (momentum along the normal)
    impulse = sum(k.force for k in contacts[first:last + 1]) * 1e-4
    assert impulse[0] == pytest.approx(c.mass * (outgoing[0] - incoming[0]), rel=0.02)
    assert max(k.overlap for k in contacts) < 0.01


def test_a_still_arm_beside_the_path_is_missed_by_its_closest_approach():
    c = config()
    arm_radius, offset = 0.01, 0.05
    surface = column(c.lowest_point[0], c.lowest_point[1] + offset, radius=arm_radius)
    pendulum = Pendulum(c, E)
    pendulum.release()
    *_, contacts = swing(pendulum, 0.5, dt=1e-4, surface=surface)
    assert all(k.overlap == 0.0 for k in contacts)
    closest = min(k.gap for k in contacts)
    assert closest == pytest.approx(offset - arm_radius - c.ball_radius, abs=1e-6)


def test_hertz_stiffness_grows_with_the_modulus_and_the_radii():
    k = hertz_stiffness(E, 0.01, 0.015)
    assert k == pytest.approx(4 / 3 * E / 0.75 * np.sqrt(0.006))
    assert hertz_stiffness(2 * E, 0.01, 0.015) == pytest.approx(2 * k)
    assert hertz_stiffness(E, 0.02, 0.015) > k


# -- the pendulum on the simulated rig ------------------------------------------------------------

def _rig(pendulum):
    """The simulated rig of plant.yaml with ``pendulum``, its arm hanging under the pretension."""
    from soft_arm_experiments.harness import load_setup
    from soft_arm_drivers.sim.simulated_rig import SimulatedRig
    from soft_arm_model import build_model
    setup = load_setup("pendulum")
    pretension = np.full(len(setup.arm.tendons), setup.control.tension_min)
    model = build_model(setup.plant.plant_arm(setup.arm))
    rig = SimulatedRig(model, setup.plant, np.zeros(len(pretension)), pretension, pendulum=pendulum)
    return rig, pretension


def _hanging_tip(rig):
    rig.begin_step()
    surface = rig.plant.surface()
    return surface.points[-1], surface.radii[-1]


def test_the_surfaces_jacobians_are_the_derivatives_of_its_points():
    """The contact's point velocities (and so the generalised forces) against finite differences of
    the backbone points along a random rate."""
    rig, _ = _rig(None)
    plant = rig.plant
    rng = np.random.default_rng(3)
    q, qd = 0.3 * rng.normal(size=plant.model.n), rng.normal(size=plant.model.n)
    h = 1e-6
    points = []
    for sign in (1, -1):
        plant.q, plant.qd = q + sign * h * qd, qd
        plant.sense(markers=True)
        points.append(plant.surface().points)
    plant.q, plant.qd = q, qd
    plant.sense(markers=True)
    surface = plant.surface()
    np.testing.assert_allclose(surface.velocities, (points[0] - points[1]) / (2 * h), atol=1e-6)
    force = np.array([0.3, -0.2, 0.5])
    generalised = surface.generalised_force(4, 0.25, force)
    point_velocity = 0.75 * surface.velocities[4] + 0.25 * surface.velocities[5]
    assert generalised @ qd == pytest.approx(force @ point_velocity)


@pytest.mark.parametrize("offset", [0.0, 0.05])
def test_a_held_arm_is_struck_in_the_balls_path_and_missed_beside_it(offset):
    """The ball's lowest point at the hanging arm's tip: the impact comes when the free swing says
    the surfaces meet, and the arm moves; 5 cm beside it (along y, across the swing): no contact,
    and the closest approach is the free swing's distance to the still arm."""
    probe, pretension = _rig(None)
    tip, radius = _hanging_tip(probe)
    c = config(pivot=tip + np.array([0.0, offset, 0.305]))
    # the free swing against the still arm: when the surfaces first meet, and how close they come
    free = Pendulum(c, E)
    free.release()
    surface = probe.plant.surface()
    gaps = []
    for _ in range(500):
        gaps.append(surface.closest(free.p)[3] - c.ball_radius)
        free.advance(1e-3)
    gaps = np.array(gaps)

    rig, pretension = _rig(c)
    rig.release_pendulum()
    q0 = rig.plant.q.copy()
    for _ in range(500):
        rig.begin_step()
        rig.end_step(pretension)
    force = np.linalg.norm(np.array(rig.strike.force), axis=1)
    if offset == 0.0:
        predicted = np.argmax(gaps <= 0) * 1e-3
        impact = np.argmax(force > 0) * 1e-3
        assert force.max() > 0 and abs(impact - predicted) <= 2e-3
        assert np.abs(rig.plant.q - q0).max() > 1e-3                 # the blow moved the arm
    else:
        assert force.max() == 0
        assert min(rig.strike.gap) == pytest.approx(gaps.min(), abs=2e-4)
        assert gaps.min() == pytest.approx(offset - radius - c.ball_radius, abs=2e-3)


def test_the_compiled_surface_is_the_workspace_in_arc_length_order():
    """Plant.surface against its definition in numpy: the model's points and markers sorted by arc
    length (stable), their linear Jacobians rotated into arm_base (R J[3:]), their velocities
    (those Jacobians times qd) and the cone's radius at each, on random states; new arrays each
    call (a contact keeps what it was given)."""
    rig, _ = _rig(None)
    plant, model = rig.plant, rig.plant.model
    rng = np.random.default_rng(5)
    X = np.concatenate([model.X, model.marker_X])
    order = np.argsort(X, kind="stable")
    g = model.config.geometry
    for _ in range(5):
        plant.q, plant.qd = 0.1 * rng.normal(size=model.n), rng.normal(size=model.n)
        plant.sense(markers=True)
        d = plant.stepper.data
        R = np.concatenate([d.R, d.marker_R])[order]
        jacobians = np.einsum("pij,pjk->pik", R, np.concatenate([d.J, d.marker_J])[order][:, 3:])
        surface = plant.surface()
        np.testing.assert_array_equal(surface.points, np.concatenate([d.p, d.marker_p])[order])
        np.testing.assert_allclose(surface.jacobians, jacobians, rtol=0, atol=1e-14)
        np.testing.assert_allclose(surface.velocities, jacobians @ plant.qd, rtol=0, atol=1e-13)
        np.testing.assert_allclose(surface.radii, g.base_radius + (g.tip_radius - g.base_radius)
                                   * X[order] / g.length, rtol=0, atol=1e-15)
        again = plant.surface()
        assert not any(np.shares_memory(a, b) for a, b in zip(
            (surface.points, surface.velocities, surface.radii, surface.jacobians),
            (again.points, again.velocities, again.radii, again.jacobians)))
