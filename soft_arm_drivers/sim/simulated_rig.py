"""The simulated rig, ROS-free: the plant with its motors, the encoders and the motion capture.

Shared by the closed-loop harness and the ROS ``simulator`` node, so that both see the same plant.
One call of :meth:`SimulatedRig.begin_step` and one of :meth:`SimulatedRig.end_step` advance the
plant by ``plant.timestep``; in between, the true sensor values of the current state are readable.
Mocap frames are exposed at ``mocap.rate`` (markers with Gaussian noise, seeded) and delivered
``mocap.latency`` later; a frame carries its mid-exposure time stamp.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from soft_arm_model import ImexStepper, build_model, solve_equilibrium

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

    def step(self, u, payload: float = 0.0):
        """Advance the sensed state by one time step under tensions u [N], with a point mass
        ``payload`` [kg] hanging at the tip (its weight only; sense with markers=True first)."""
        f_ext = None
        if payload:
            d = self.stepper.data
            gravity_body = d.marker_R[-1].T @ self.model.gravity
            f_ext = payload * (d.marker_J[-1][3:].T @ gravity_body)
        self.q, self.qd = self.stepper.advance(u, f_ext)

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


class Encoders:
    """Motor encoders: shortening = pulley radius x angle, quantised to ``resolution`` [rad] (rate to
    ``velocity_resolution`` [rad/s]), zeroed at ``zero`` [m] (true shortening at start-up) and offset
    by ``offset`` [m] (the controller model's shortening of the start-up pose)."""

    def __init__(self, plant: PlantConfig, zero, offset):
        self.r, self.res, self.vres = plant.pulley_radius, plant.encoder_resolution, \
            plant.velocity_resolution
        self.zero, self.offset = np.array(zero, dtype=float), np.array(offset, dtype=float)

    @staticmethod
    def _quantise(v, step):
        return v if step == 0 else np.round(v / step) * step

    def read(self, s_true, s_dot_true) -> tuple[np.ndarray, np.ndarray]:
        angle = self._quantise((np.asarray(s_true) - self.zero) / self.r, self.res)
        rate = self._quantise(np.asarray(s_dot_true) / self.r, self.vres)
        return angle * self.r + self.offset, rate * self.r


@dataclass(frozen=True)
class MocapFrame:
    """One motion-capture frame: mid-exposure time [s], measured marker positions (n_markers, 3) [m]
    (noisy, in arm_base as the mocap's calibration has it) and the true ones in arm_base, true tip
    speed [m/s] and the frame number."""
    stamp: float
    markers: np.ndarray
    true_markers: np.ndarray
    tip_speed: float
    number: int


class SimulatedRig:
    """Plant, encoders and mocap on one clock (``t`` [s], multiples of the plant time step).

    ``encoder_offset``: the controller's shortening of the start-up pose [m] (what zeroing the
    encoders on the hanging arm is taken to mean); ``pretension`` [N]: the tensions the arm hangs
    under at start-up.
    """

    def __init__(self, plant_model, plant: PlantConfig, encoder_offset, pretension,
                 payload=((), ())):
        """``payload``: (masses [kg], attach times [s]): each mass hangs at the tip from its time
        on (an unmodelled load: the controller does not know it), as a weight at the tip (the
        plant's own ``tip_payload`` is part of ``plant_model``, with its inertia)."""
        self.config = plant
        self.payload_masses = np.array(payload[0], dtype=float)
        self.payload_times = np.array(payload[1], dtype=float)
        self.plant = Plant(plant_model, plant.timestep, plant.rotor_mass)
        self.plant.settle(pretension)
        self.plant.sense()
        zero, _ = self.plant.tendons()
        self.encoders = Encoders(plant, zero, encoder_offset)
        self.rng = np.random.default_rng(plant.mocap_seed)
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
        self.plant.sense(markers=exposure or self._load > 0)
        frame = None
        if exposure:
            true, speed = self.plant.markers()
            noisy = self.config.as_mocap_reports(true) + self.rng.normal(0.0, self.config.mocap_noise,
                                                                         true.shape)
            frame = MocapFrame(self._next_frame * self._frame_period, noisy, true, speed,
                               self._next_frame)
            self._pending.append(frame)
            self._next_frame += 1
        delivered = []
        while self._pending and self._pending[0].stamp + self.config.mocap_latency <= self.t + 1e-12:
            delivered.append(self._pending.popleft())
        return frame, delivered

    def tendons(self) -> tuple[np.ndarray, np.ndarray]:
        """Encoder readings at the sensed state: shortenings [m] and rates [m/s]."""
        return self.encoders.read(*self.plant.tendons())

    def payload(self) -> float:
        """The tip payload [kg] at the current time."""
        if not self.payload_masses.size:
            return 0.0
        return float(self.payload_masses[self.payload_times <= self.t + 1e-12].sum())

    def end_step(self, u):
        """Apply tensions u [N] over one plant step."""
        self.tension = np.array(u, dtype=float)
        self.plant.step(self.tension, self._load)
        self.step_index += 1
