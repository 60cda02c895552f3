"""The harmonic learner of a periodic path (soft_arm_control/track_learning.py): its correction's
derivatives, its convergence on a plant it does not know (whole and uneven periods, frames
missing), and its backing off where the plant does not follow."""
import numpy as np
import pytest

from soft_arm_control.track_learning import BACK_OFF, HALVINGS, HarmonicLearner
from soft_arm_control.trajectories import Trajectory

PERIOD = 0.5        # s: a 2 Hz path
FRAMES = 120        # per period (the default frame step: PERIOD / FRAMES)
START = np.array([0.0192, -0.3041])      # m: absolute coordinates, as the mocap gives them


def desired_at(tau, shape="circle", period=PERIOD):
    return Trajectory(shape, 0.01, period).at(START, tau)[0]


OSCILLATOR_HZ = np.array([1.2, 1.5])     # the oscillator's natural frequencies, per coordinate
OSCILLATOR_DAMPING = 0.3


def oscillator_response(frequency):
    """The oscillator's frequency response from reference to position at ``frequency`` [Hz], per
    coordinate: G(i omega) = w^2 / (w^2 - omega^2 + 2 i zeta w omega)."""
    w, omega = 2 * np.pi * OSCILLATOR_HZ, 2 * np.pi * frequency
    return w ** 2 / (w ** 2 - omega ** 2 + 2j * OSCILLATOR_DAMPING * w * omega)


class Oscillator:
    """A plant above whose modes the path runs: per coordinate x'' + 2 zeta w (x') + w^2 (x - r -
    offset) = 0 (w: 1.2 and 1.5 Hz, zeta 0.3), from rest at the start; at 2 Hz it answers with
    0.49 and 0.90 of the amplitude, 151 and 134 degrees late (:func:`oscillator_response`), and
    ``offset`` [m] away (a model error)."""

    def __init__(self, offset=(0.0, 0.002)):
        self.w = 2 * np.pi * OSCILLATOR_HZ
        self.offset = np.array(offset)
        self.x, self.v = START.copy(), np.zeros(2)

    def __call__(self, reference, dt, substeps=20):
        h = dt / substeps
        for _ in range(substeps):       # semi-implicit Euler
            a = -2 * OSCILLATOR_DAMPING * self.w * self.v - self.w ** 2 * (self.x - reference - self.offset)
            self.v = self.v + h * a
            self.x = self.x + h * self.v
        return self.x.copy()


def run(learner, plant, periods, shape="circle", followed=lambda j, c: True, clipped=lambda j: False,
        dt=PERIOD / FRAMES, seen=lambda tau: True, period=PERIOD):
    """Drive the learner (None: the path unlearned) and ``plant(reference, desired, correction,
    dt)`` along the path of ``period`` [s] with frames every dt [s] for ``periods`` periods;
    ``seen(tau)``: the learner gets that frame. The RMS error of each period [m]."""
    errors = [[] for _ in range(periods)]
    for n in range(int(round(periods * period / dt))):
        tau = n * dt
        j = min(int(tau // period), periods - 1)
        desired = desired_at(tau, shape, period)
        c = np.zeros(2) if learner is None else learner.correction(tau)[0]
        measured = plant(desired + c, desired, c, dt)
        errors[j].append(np.linalg.norm(desired - measured))
        if learner is not None and seen(tau):
            learner.add(tau, desired, desired + c, measured, followed(j, c), clipped(j))
    return [float(np.sqrt(np.mean(np.square(e)))) for e in errors]


def linear(oscillator):
    return lambda reference, desired, c, dt: oscillator(reference, dt)


def test_the_correction_its_velocity_and_acceleration_are_continuous_through_a_blend():
    learner = HarmonicLearner(PERIOD, 2, harmonics=2, gain=0.5)
    learner.current = np.array([[0.001, -0.002], [0.003 + 0.002j, -0.001j], [0.0005, 0.001 + 0.001j]])
    learner.blend_from = 1.0
    h = 1e-5
    for tau in (1.05, 1.2, 1.37, 1.49, 1.6):
        c, dc, ddc = learner.correction(tau)
        plus, minus = learner.correction(tau + h), learner.correction(tau - h)
        assert np.allclose(dc, (plus[0] - minus[0]) / (2 * h), rtol=1e-5, atol=1e-9)
        assert np.allclose(ddc, (plus[1] - minus[1]) / (2 * h), rtol=1e-4, atol=1e-7)
    # no step at either end: value, velocity and acceleration (the dynamic reference's feedforward)
    settled = HarmonicLearner(PERIOD, 2, harmonics=2)
    settled.current = learner.current
    assert np.allclose(learner.correction(1.0 + 1e-9), 0.0, atol=1e-7)
    assert np.allclose(learner.correction(1.5 - 1e-9), settled.correction(1.5), atol=1e-7)
    # a blend cut short by the next one starts it from where it was
    before = learner.correction(1.3)[0]
    learner._blend(1.3, np.zeros_like(learner.current))
    assert np.allclose(learner.correction(1.3)[0], before)


def test_a_plant_above_its_modes_and_off_by_an_offset_is_learned_to_a_twentieth_of_its_error():
    unlearned = run(None, linear(Oscillator()), 20)
    learner = HarmonicLearner(PERIOD, 2, harmonics=3, gain=0.5)
    learned = run(learner, linear(Oscillator()), 20)
    assert unlearned[-1] > 0.008                       # half the circle's amplitude, late, offset
    assert learned[-1] < unlearned[-1] / 20
    assert learner.updates == 19 and learner.backed_off == 0
    # the learned gains are the plant's frequency response at the path's frequency, as the frames
    # see it: each frame's reference is held over the frame (dt / 2 late) and its measurement is the
    # state at the frame's end (dt early), a lead of omega dt / 2 (1.5 degrees); what is left, 0.2 %,
    # is the semi-implicit Euler's error at its step of dt / 20 (of order w h)
    dt = PERIOD / FRAMES
    expected = oscillator_response(1 / PERIOD) * np.exp(1j * np.pi / PERIOD * dt)
    g = learner.gains[1]
    assert np.all(np.abs(g - expected) < 0.005 * np.abs(expected)), (g, expected)


def test_uneven_frames_and_missing_ones_are_learned_from_alike():
    """Frames at 240 Hz (a period of 0.5 s is 120 of them, of 0.4712 s 113.1), a tenth of every
    other period's frames missing at its end, and a frame with no measurement: the least-squares
    harmonics do not mistake the absolute coordinates (0.3 m) for the path (1 cm)."""
    def seen(tau):
        u = tau / PERIOD
        return not (int(u) % 2 and u % 1 > 0.9)

    def plant_with_a_hole(reference, desired, c, dt, oscillator=Oscillator(), frames=[0]):
        frames[0] += 1
        x = oscillator(reference, dt)
        return np.array([np.nan, x[1]]) if frames[0] == 1000 else x
    unlearned = run(None, linear(Oscillator()), 24, dt=1 / 240)
    learner = HarmonicLearner(PERIOD, 2, harmonics=3, gain=0.5)
    learned = run(learner, plant_with_a_hole, 24, dt=1 / 240, seen=seen)
    assert learned[-1] < unlearned[-1] / 20 and np.all(np.isfinite(learner.current))
    learner = HarmonicLearner(0.4712, 2, harmonics=3, gain=0.5)
    learned = run(learner, linear(Oscillator()), 24, dt=1 / 240, period=0.4712)
    assert learned[-1] < 1e-3 and learner.backed_off == 0


def test_a_period_with_a_gap_of_a_third_is_not_learned_from():
    learner = HarmonicLearner(PERIOD, 2, harmonics=3, gain=0.5)
    run(learner, linear(Oscillator()), 6, seen=lambda tau: not (2 * PERIOD < tau < 2.4 * PERIOD))
    assert learner.updates == 4                 # periods 0, 1, 3 and 4; not 2; 5 is never closed


def test_the_figure_eight_s_second_harmonic_is_learned_too():
    unlearned = run(None, linear(Oscillator()), 24, "figure8")
    learner = HarmonicLearner(PERIOD, 2, harmonics=3, gain=0.5)
    learned = run(learner, linear(Oscillator()), 24, "figure8")
    assert learned[-1] < unlearned[-1] / 10
    assert np.any(np.abs(learner.current[2]) > 1e-4)      # the second harmonic holds a correction
    assert np.allclose(learner.current[3], 0.0)           # the third, absent from the path, does not


def test_a_period_the_clik_could_not_follow_halves_the_correction_and_the_gain():
    learner = HarmonicLearner(PERIOD, 2, harmonics=1, gain=0.5)
    run(learner, linear(Oscillator()), 6, followed=lambda j, c: j != 5)     # the last period blocked
    before = learner.current.copy()
    assert learner.updates == 5
    learner.add(6 * PERIOD, desired_at(0.0), desired_at(0.0), desired_at(0.0))   # closes it
    assert learner.backed_off == 1 and learner.updates == 5 and learner.gain == 0.25
    assert np.allclose(learner.current, BACK_OFF * before)


def test_a_path_beyond_the_limits_is_not_learned_up_against_them_again_and_again():
    """The CLIK cannot follow a correction larger than 8 mm (the tendons' limit, here), and the
    plant needs one of about 14 mm: each blocked period halves the correction and the gain, so the
    learner creeps back up ever slower and stops after a few tries instead of cycling."""
    learner = HarmonicLearner(PERIOD, 2, harmonics=1, gain=0.5)
    run(learner, linear(Oscillator()), 40, followed=lambda j, c: np.linalg.norm(c) < 0.008)
    assert 1 <= learner.backed_off <= HALVINGS and learner.stopped
    assert np.all(np.abs(learner.current) < 0.008)


def test_a_period_whose_dynamic_reference_was_clipped_keeps_the_correction_without_learning():
    learner = HarmonicLearner(PERIOD, 2, harmonics=1, gain=0.5)
    run(learner, linear(Oscillator()), 6, clipped=lambda j: j == 5)      # the last period clipped
    before = learner.current.copy()
    learner.add(6 * PERIOD, desired_at(0.0), desired_at(0.0), desired_at(0.0))   # closes it
    assert learner.frozen == 1 and learner.updates == 5 and learner.backed_off == 0
    assert np.array_equal(learner.current, before)


def test_a_plant_that_answers_the_correction_backwards_is_not_made_worse_than_unlearned():
    """A plant the learner's estimate gets wrong: it follows the path like the oscillator but
    moves against whatever is added to it. Each step makes the error grow; the learner goes back
    to its best correction (none) with half the gain, until it stops: a wrong step costs the
    periods that try it and undo it, and the error ends where the unlearned one is."""
    def backwards(oscillator):
        return lambda reference, desired, c, dt: oscillator(desired - 3 * c, dt)
    unlearned = run(None, backwards(Oscillator()), 40)
    learner = HarmonicLearner(PERIOD, 2, harmonics=1, gain=0.5)
    learned = run(learner, backwards(Oscillator()), 40)
    assert learner.stopped and learner.backed_off >= 1 and np.allclose(learner.current, 0.0)
    assert max(learned) < 2.5 * max(unlearned)
    assert np.mean(learned[-10:]) == pytest.approx(np.mean(unlearned[-10:]), rel=0.02)


def test_the_periods_within_the_settling_time_are_watched_not_learned_from():
    learner = HarmonicLearner(PERIOD, 2, harmonics=1, gain=0.5, settle=1.2)
    run(learner, linear(Oscillator()), 5)   # periods 0-2 start before 1.2 s; 3 closes when 4 starts
    assert learner.updates == 1 and len(learner.errors) == 1


def test_a_learner_refuses_what_it_cannot_do():
    for args in ((0.0, 2), (1.0, 2, 0), (1.0, 2, 3, 0.0), (1.0, 2, 3, 1.5), (1.0, 2, 3, 0.5, -1.0)):
        with pytest.raises(ValueError, match="harmonic learner needs"):
            HarmonicLearner(*args)
