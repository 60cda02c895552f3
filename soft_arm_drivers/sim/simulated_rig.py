"""The simulated rig, ROS-free: the plant with its motors, the encoders and the motion capture.

Shared by the closed-loop harness and the ROS ``simulator`` node, so that both see the same plant.
One call of :meth:`SimulatedRig.begin_step` and one of :meth:`SimulatedRig.end_step` advance the
plant by ``plant.timestep``; in between, the true sensor values of the current state are readable.
Mocap frames are exposed at ``mocap.rate`` (markers with Gaussian noise, seeded; the markers the
cameras do not see, :mod:`.occlusion`, are NaN) and delivered ``mocap.latency`` later; a frame
carries its mid-exposure time stamp. A task's pendulum
(:mod:`.pendulum`) swings with the arm, in contact with it, and its ball is in every frame.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from soft_arm_model import ImexStepper, build_model, solve_equilibrium

from .occlusion import Occlusions, arc_layout
from .pendulum import ArmSurface, Contact, Pendulum
from .plant_config import PlantConfig


class Plant:
    """The simulated arm with its motors: state (q, qd) stepped under the motor tensions (torque /
    pulley radius) [N], the rotors' reflected mass [kg] on every tendon.

    Each step is ``sense`` (evaluate the current state; the true sensor values come from that same
    evaluation) then ``step(u)``.
    """

    def __init__(self, model, timestep: float, rotor_mass: float = 0.0):
        self.model = model
        self.stepper = ImexStepper(model, timestep, rotor_mass=np.full(model.n_tendons, rotor_mass))
        self.q = np.zeros(model.n)
        self.qd = np.zeros(model.n)
        self._layout = None     # (order, radii) of the points and markers by arc length: surface()

    @classmethod
    def of(cls, arm, config: PlantConfig) -> "Plant":
        """The plant of ``config`` (plant.yaml) for the controller's ``arm``: its model error,
        time step and rotors."""
        return cls(build_model(config.plant_arm(arm)), config.timestep, config.rotor_mass)

    def settle(self, u):
        """Put the arm at rest at the static equilibrium of tensions u [N]."""
        self.q = solve_equilibrium(self.model, np.asarray(u, dtype=float)).q
        self.qd = np.zeros(self.model.n)

    def sense(self, markers: bool = False):
        """Evaluate the current state (markers too if asked) for the readings and the next step."""
        self.stepper.prepare(self.q, self.qd, markers)

    def step(self, u, payload: float = 0.0, force=None):
        """Advance the sensed state by one time step under tensions u [N], with a point mass
        ``payload`` [kg] hanging at the tip (its weight only; sense with markers=True first) and an
        external generalised force ``force`` (e.g. a contact's, :meth:`ArmSurface.generalised_force`)."""
        f_ext = None if force is None else np.asarray(force, dtype=float)
        if payload:
            d = self.stepper.data
            gravity_body = d.marker_R[-1].T @ self.model.gravity
            weight = payload * (d.marker_J[-1][3:].T @ gravity_body)
            f_ext = weight if f_ext is None else f_ext + weight
        self.q, self.qd = self.stepper.advance(u, f_ext)

    def surface(self) -> ArmSurface:
        """The arm's backbone at the state sensed with ``markers=True``, as a contact sees it: the
        model's points and the markers by arc length, their velocities, the cone's radius there and
        their linear Jacobians in arm_base (new arrays). The order and the radii depend on the
        model alone and are computed once; the rest in one compiled call (:func:`_surface`), as
        the pendulum's contact takes it at every plant step of a strike."""
        if self._layout is None:
            order, _, radii = arc_layout(self.model)
            self._layout = order, radii
        order, radii = self._layout
        d = self.stepper.data
        points, velocities, jacobians = _surface(order, d.p, d.marker_p, d.R, d.marker_R, d.J, d.marker_J,
                                                 np.ascontiguousarray(self.qd, dtype=float))
        return ArmSurface(points, velocities, radii.copy(), jacobians)

    def tendons(self) -> tuple[np.ndarray, np.ndarray]:
        """True shortenings L_c(0) - L_c(q) [m] and rates [m/s] of all tendons at the sensed state."""
        d = self.stepper.data
        return self.model.rest_tendon_lengths - d.Lc, -(d.A0.T @ self.qd)

    def markers(self) -> tuple[np.ndarray, float]:
        """True marker positions (n_markers, 3) [m] in arm_base and the tip speed [m/s] at the
        state sensed with ``markers=True``."""
        d = self.stepper.data
        v = d.marker_R[-1] @ (d.marker_J[-1][3:] @ self.qd)
        return d.marker_p.copy(), float(np.linalg.norm(v))


@njit(cache=True, nogil=True)
def _surface(order, p, marker_p, R, marker_R, J, marker_J, qd):
    """The backbone's points (N, 3) [m], velocities (N, 3) [m/s] and linear Jacobians (N, 3, n) in
    arm_base, in ``order`` (indices into the model's points then markers): jacobian = R J[3:] of
    each, velocity = jacobian qd (:meth:`Plant.surface`)."""
    n_points, N, n = p.shape[0], order.shape[0], qd.shape[0]
    points = np.empty((N, 3))
    velocities = np.empty((N, 3))
    jacobians = np.empty((N, 3, n))
    for i in range(N):
        k = order[i]
        if k < n_points:
            pos, rot, jac = p[k], R[k], J[k]
        else:
            pos, rot, jac = marker_p[k - n_points], marker_R[k - n_points], marker_J[k - n_points]
        for a in range(3):
            points[i, a] = pos[a]
            speed = 0.0
            for c in range(n):
                acc = rot[a, 0] * jac[3, c] + rot[a, 1] * jac[4, c] + rot[a, 2] * jac[5, c]
                jacobians[i, a, c] = acc
                speed += acc * qd[c]
            velocities[i, a] = speed
    return points, velocities, jacobians


class Encoders:
    """Motor encoders: shortening = pulley radius x angle, quantised to ``resolution`` [rad] (rate to
    ``velocity_resolution`` [rad/s]), zeroed at ``zero`` [m] (true shortening at start-up) and offset
    by ``offset`` [m] (the controller model's shortening of the start-up pose)."""

    def __init__(self, plant: PlantConfig, zero, offset):
        self.r, self.res, self.vres = plant.pulley_radius, plant.encoder_resolution, \
            plant.velocity_resolution
        self.zero, self.offset = np.array(zero, dtype=float), np.array(offset, dtype=float)

    def read(self, s_true, s_dot_true) -> tuple[np.ndarray, np.ndarray]:
        """Readings (shortenings [m], rates [m/s]) of the true shortenings and rates [m, m/s]."""
        return _read_encoders(np.ascontiguousarray(s_true, dtype=float),
                              np.ascontiguousarray(s_dot_true, dtype=float), self.zero, float(self.r),
                              float(self.res), float(self.vres), self.offset)


@njit(cache=True, nogil=True)
def _read_encoders(s_true, s_dot_true, zero, radius, resolution, velocity_resolution, offset):
    """:meth:`Encoders.read` in one compiled call (it runs at every inner-loop period and every
    estimate, where a dozen numpy calls on four numbers cost more than the reading): each angle
    and rate rounded half to even to its step (numpy's ``round``), none for a step of zero."""
    n = s_true.shape[0]
    s = np.empty(n)
    rate = np.empty(n)
    for k in range(n):
        angle = (s_true[k] - zero[k]) / radius
        if resolution != 0.0:
            angle = np.rint(angle / resolution) * resolution
        speed = s_dot_true[k] / radius
        if velocity_resolution != 0.0:
            speed = np.rint(speed / velocity_resolution) * velocity_resolution
        s[k] = angle * radius + offset[k]
        rate[k] = speed * radius
    return s, rate


@dataclass(frozen=True)
class MocapFrame:
    """One motion-capture frame: mid-exposure time [s], measured marker positions (n_markers, 3) [m]
    (noisy, in arm_base as the mocap's calibration has it; NaN rows for the markers the cameras did
    not see) and the true ones in arm_base, true tip speed [m/s], the frame number, the pendulum
    ball's measured centre [m] (None without one) and which markers were seen (n_markers,) bool."""
    stamp: float
    markers: np.ndarray
    true_markers: np.ndarray
    tip_speed: float
    number: int
    ball: np.ndarray | None = None
    visible: np.ndarray | None = None


class SimulatedRig:
    """Plant, encoders and mocap on one clock (``t`` [s], multiples of the plant time step).

    ``encoder_offset``: the controller's shortening of the start-up pose [m] (what zeroing the
    encoders on the hanging arm is taken to mean); ``pretension`` [N]: the tensions the arm hangs
    under at start-up.
    """

    def __init__(self, plant_model, plant: PlantConfig, encoder_offset, pretension,
                 payload=((), ()), pendulum=None):
        """``payload``: (masses [kg], attach times [s]): each mass hangs at the tip from its time
        on (an unmodelled load: the controller does not know it), as a weight at the tip (the
        plant's own ``tip_payload`` is part of ``plant_model``, with its inertia). ``pendulum``: the
        strike experiment's (:class:`~soft_arm_control.pendulum_geometry.PendulumConfig`), held
        until :meth:`release_pendulum`, swung with the arm and in contact with it; each step's
        contact is in :attr:`strike`."""
        self.config = plant
        self.pendulum = None if pendulum is None else Pendulum(pendulum,
                                                               plant_model.config.material.youngs_modulus)
        self.strike = StrikeRecord()
        self.payload_masses = np.array(payload[0], dtype=float)
        self.payload_times = np.array(payload[1], dtype=float)
        self.plant = Plant(plant_model, plant.timestep, plant.rotor_mass)
        self.plant.settle(pretension)
        self.plant.sense()
        zero, _ = self.plant.tendons()
        self.encoders = Encoders(plant, zero, encoder_offset)
        self.rng = np.random.default_rng(plant.mocap_seed)
        self.occlusions = Occlusions.for_plant(plant, plant_model.marker_X.size)
        self.step_index = 0
        self._frame_period = 1.0 / plant.mocap_rate
        self._next_frame = 0
        self._pending = deque()
        self._sensed = -1
        self._load = 0.0               # payload [kg] at the sensed state
        self.tension = np.array(pretension, dtype=float)

    @property
    def t(self) -> float:
        return self.step_index * self.config.timestep

    def begin_step(self) -> tuple[MocapFrame | None, list]:
        """Sense the current state; returns (the frame exposed now or None, frames delivered now).
        A second call before ``end_step`` senses nothing new and returns (None, [])."""
        if self._sensed == self.step_index:
            return None, []
        self._sensed = self.step_index
        exposure = self.t >= self._next_frame * self._frame_period - 1e-12
        self._load = self.payload()
        self.plant.sense(markers=exposure or self._load > 0 or self.pendulum is not None)
        frame = None
        if exposure:
            true, speed = self.plant.markers()
            noisy = self.config.as_mocap_reports(true) + self.rng.normal(0.0, self.config.mocap_noise,
                                                                         true.shape)
            visible = self.visible(true)
            noisy[~visible] = np.nan
            ball = None
            if self.pendulum is not None:
                ball = self.config.as_mocap_reports(self.pendulum.p[None, :])[0] + self.rng.normal(
                    0.0, self.config.mocap_noise, 3)
            frame = MocapFrame(self._next_frame * self._frame_period, noisy, true, speed,
                               self._next_frame, ball, visible)
            self._pending.append(frame)
            self._next_frame += 1
        delivered = []
        while self._pending and self._pending[0].stamp + self.config.mocap_latency <= self.t + 1e-12:
            delivered.append(self._pending.popleft())
        return frame, delivered

    def visible(self, true_markers) -> np.ndarray:
        """(n_markers,) bool: which of the plant's markers the cameras see in the frame exposed now,
        judged at the plant's workspace (the state just sensed with markers, ``true_markers`` (n, 3)
        [m, arm_base] being its markers); all without occlusions."""
        if self.occlusions is None:
            return np.ones(len(true_markers), bool)
        return self.occlusions.of_arm(self.plant.model, self.plant.stepper.data, self.t)

    def tendons(self) -> tuple[np.ndarray, np.ndarray]:
        """Encoder readings at the sensed state: shortenings [m] and rates [m/s]."""
        return self.encoders.read(*self.plant.tendons())

    def payload(self) -> float:
        """The tip payload [kg] at the current time."""
        if not self.payload_masses.size:
            return 0.0
        return float(self.payload_masses[self.payload_times <= self.t + 1e-12].sum())

    def release_pendulum(self):
        """Let the pendulum's ball go now (ValueError without a pendulum)."""
        if self.pendulum is None:
            raise ValueError("this rig has no pendulum (tasks.<task>.pendulum)")
        if not self.pendulum.released:
            self.pendulum.release()
            self.strike.release_time = self.t

    def end_step(self, u):
        """Apply tensions u [N] over one plant step (and the pendulum's contact, if any)."""
        self.tension = np.array(u, dtype=float)
        force = None
        if self.pendulum is not None:
            surface = self.plant.surface()
            contact = self.pendulum.advance(self.config.timestep, surface)
            self.strike.add(self.t, self.pendulum, contact, surface)
            if contact.overlap > 0:
                force = surface.generalised_force(contact.segment, contact.fraction, -contact.force)
        self.plant.step(self.tension, self._load, force)
        self.step_index += 1


@dataclass
class StrikeRecord:
    """What the pendulum did, one entry per plant step after the release: times [s] (the step's
    start), ball positions and velocities at the step's end [m, m/s], contact force on the ball [N],
    surface gap [m] (negative: overlap), and the arm's speed at the contact point [m/s]."""
    release_time: float | None = None
    t: list = field(default_factory=list)
    ball: list = field(default_factory=list)
    ball_velocity: list = field(default_factory=list)
    force: list = field(default_factory=list)
    gap: list = field(default_factory=list)
    arm_speed: list = field(default_factory=list)

    def add(self, t: float, pendulum: Pendulum, contact: Contact, surface: ArmSurface):
        if self.release_time is None:
            return
        i, s = contact.segment, contact.fraction
        self.t.append(t)
        self.ball.append(pendulum.p.copy())
        self.ball_velocity.append(pendulum.v.copy())
        self.force.append(contact.force.copy())
        self.gap.append(contact.gap)
        velocity = (1 - s) * surface.velocities[i] + s * surface.velocities[i + 1]
        self.arm_speed.append(float(np.linalg.norm(velocity)))
