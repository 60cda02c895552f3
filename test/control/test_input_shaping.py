"""Input shaping of reference steps: zero residual vibration at the design mode, the model's modes
against a simulated free vibration, shaped steps in the outer loop."""
import numpy as np
import pytest

from soft_arm_control.clik import Clik, ClikGains
from soft_arm_control.collocated import build_collocated
from soft_arm_control.input_shaping import (Mode, ShapedStep, StepShaper, dominant_mode, impulses,
                                            step_modes)
from soft_arm_control.outer_loop import OuterLoop
from soft_arm_control.task_space import TaskSpace
from soft_arm_model import simulate, solve_equilibrium
from soft_arm_model.dynamics import mass_matrix

TRIANGLE = TaskSpace((3, 3, 3, 2), (0, 1, 2, 1))
KP, KD = np.full(4, 1500.0), np.full(4, 120.0)


def oscillator_response(t, times, fractions, f, zeta):
    """Exact response of x'' + 2 zeta w x' + w^2 x = w^2 r(t) from rest to the staircase r."""
    w = 2 * np.pi * f
    wd = w * np.sqrt(1 - zeta ** 2)
    x = np.zeros_like(t)
    for ti, a in zip(times, fractions):
        s = np.clip(t - ti, 0.0, None)
        step = 1 - np.exp(-zeta * w * s) * (np.cos(wd * s) + zeta / np.sqrt(1 - zeta ** 2) * np.sin(wd * s))
        x += a * np.where(t >= ti, step, 0.0)
    return x


def residual(shaper, f_design, f_true, zeta=0.1):
    """Largest |x - 1| of the oscillator after the shaper's last impulse."""
    times, fractions = impulses(shaper, f_design, zeta)
    t = np.linspace(times[-1], times[-1] + 3.0, 3001)
    return np.abs(oscillator_response(t, times, fractions, f_true, zeta) - 1).max()


@pytest.mark.parametrize("shaper", ["zv", "zvd"])
def test_a_shaped_step_leaves_its_design_mode_at_rest(shaper):
    times, fractions = impulses(shaper, 1.4, 0.1)
    assert times[0] == 0 and np.all(np.diff(times) > 0) and np.isclose(fractions.sum(), 1)
    assert np.all(fractions > 0)
    assert residual(shaper, 1.4, 1.4) < 1e-12
    assert residual("none", 1.4, 1.4) > 0.5               # the plain step rings at ~70 %


def test_zvd_tolerates_a_frequency_error_zv_does_not():
    for error in (0.8, 1.2):
        zv, zvd = residual("zv", 1.4, 1.4 * error), residual("zvd", 1.4, 1.4 * error)
        assert zvd < 0.1 and zv > 2 * zvd
    assert residual("zv", 1.4, 1.4 * 1.1) < 0.25 * residual("none", 1.4, 1.4 * 1.1)


def test_impulses_refuse_what_they_cannot_shape():
    with pytest.raises(ValueError, match="one of"):
        impulses("zvdd", 1.0, 0.1)
    with pytest.raises(ValueError, match="frequency > 0"):
        impulses("zv", 0.0, 0.1)
    times, fractions = impulses("zv", 1.0, 1.5)            # overdamped: nothing to cancel
    assert times.tolist() == [0.0] and fractions.tolist() == [1.0]


@pytest.fixture(scope="module")
def triangle(paper_model):
    cm = build_collocated(paper_model, (0, 1, 2, 3))
    clik = Clik(cm, TRIANGLE, ClikGains(2.0, 5.0), (0.05, 5.0))
    a = clik.reference(solve_equilibrium(paper_model, [0.1, 0.5, 1.1, 0.3]).q)
    b = clik.reference(solve_equilibrium(paper_model, [0.9, 0.1, 0.7, 1.1]).q)
    return cm, clik, a, b


def test_the_slowest_mode_is_the_free_vibration_of_the_simulated_arm(paper_model, triangle):
    """Tensions fixed (no inner loop): released from its equilibrium displaced along the lowest
    mode, the simulated arm vibrates at the mode's frequency and decays at its damping ratio."""
    cm, clik, a, b = triangle
    zero = np.zeros(4)
    modes = step_modes(cm, TRIANGLE, zero, zero, a, b)
    lowest = modes[0]
    assert all(m.frequency >= lowest.frequency for m in modes)
    # the mode shape, from the same eigenproblem the module solves
    import scipy.linalg
    from soft_arm_control.collocated import held_stiffness
    k = held_stiffness(cm, b.q, b.u_ff, zero)
    m = mass_matrix(paper_model, b.q)
    w2, shapes = scipy.linalg.eigh(0.5 * (k + k.T), m)
    assert np.isclose(np.sqrt(w2[0]) / (2 * np.pi), lowest.frequency)
    phi = shapes[:, 0]
    u = np.asarray(b.u_ff)
    traj = simulate(paper_model, b.q + 0.02 * phi / np.abs(phi).max(), np.zeros_like(b.q), lambda t: u,
                    4.0, dt=1e-3)
    y = (traj.q - b.q) @ m @ phi                         # the mode's coordinate
    up = np.flatnonzero((y[:-1] < 0) & (y[1:] >= 0))
    period = np.diff(traj.t[up]).mean()
    assert abs(1 / period - lowest.frequency) < 0.05 * lowest.frequency
    peaks = [np.abs(y[i:j]).max() for i, j in zip(up[:-1], up[1:])]
    decrement = np.log(peaks[0] / peaks[-1]) / (len(peaks) - 1)
    zeta = decrement / (2 * np.pi)
    assert abs(zeta - lowest.damping) < 0.25 * lowest.damping


def test_the_amplitudes_are_the_steps_projection_on_the_modes(paper_model, triangle):
    cm, clik, a, b = triangle
    modes = step_modes(cm, TRIANGLE, KP, KD, a, b)
    assert len(modes) == paper_model.n and all(m.damping > 0 for m in modes)
    assert all(m.amplitude == 0 for m in step_modes(cm, TRIANGLE, KP, KD, b, b))
    half = clik.reference(0.5 * (a.q + b.q))
    halved = step_modes(cm, TRIANGLE, KP, KD, half, b)
    for m, h in zip(modes, halved):
        assert np.isclose(h.amplitude, 0.5 * m.amplitude, rtol=1e-9, atol=1e-15)
    # the inner loop's stiffness raises every frequency of the free arm
    free = step_modes(cm, TRIANGLE, np.zeros(4), np.zeros(4), a, b)
    assert modes[0].frequency > free[0].frequency


def test_the_dominant_mode_is_the_one_that_stays_longest_above_the_level():
    slow_small = Mode(1.0, 0.05, 0.002)        # ln 2 / 0.314 = 2.2 s
    fast_large = Mode(3.0, 0.4, 0.05)          # ln 50 / 7.5 = 0.52 s
    below = Mode(1.0, 0.01, 0.0009)
    assert dominant_mode([fast_large, slow_small, below], 1e-3) is slow_small
    assert dominant_mode([fast_large, slow_small, below], 0.01) is fast_large
    assert dominant_mode([below], 1e-3) is None
    assert np.isclose(slow_small.decay_time(1e-3), np.log(2) / (0.05 * 2 * np.pi))


def test_a_step_is_shaped_only_when_its_vibration_would_outlast_the_shaper(triangle):
    cm, clik, a, b = triangle
    shaped = StepShaper(cm, TRIANGLE, "zv", KP, KD, level=0.01).shape(2.0, a, b)
    assert shaped.mode is not None and len(shaped.times) == 2
    assert shaped.mode.decay_time(0.01) > shaped.times[-1]
    assert StepShaper(cm, TRIANGLE, "zv", KP, KD, level=1.0).shape(2.0, a, b).mode is None
    assert StepShaper(cm, TRIANGLE, "none", KP, KD, level=0.01).shape(2.0, a, b).times.tolist() == [0.0]
    with pytest.raises(ValueError, match="level"):
        StepShaper(cm, TRIANGLE, "zv", KP, KD, level=0.0)


def test_a_shaped_step_moves_every_reference_by_the_given_fractions(triangle):
    cm, clik, a, b = triangle
    step = ShapedStep(a, b, 1.0, np.array([0.0, 0.3]), np.array([0.6, 0.4]))
    assert step.end_time == 1.3 and step.fraction(0.99) == 0.0 and step.fraction(1.0) == 0.6
    mid = step.at(1.2)
    for u, v, w in ((a.q, b.q, mid.q), (a.shortening, b.shortening, mid.shortening),
                    (a.u_ff, b.u_ff, mid.u_ff)):
        assert np.allclose(w, u + 0.6 * (v - u))
    assert step.at(1.3) is b and step.at(5.0) is b


def test_the_outer_loop_gives_a_shaped_replay_in_fractions_and_refines_after_it(triangle):
    cm, clik, a, b = triangle
    shaper = StepShaper(cm, TRIANGLE, "zv", KP, KD, level=0.001)
    outer = OuterLoop(clik, a, switch_delay=0.1, rate=240.0, shaper=shaper, shaped_modes=("replay",))
    outer.goal(0.0, b.x, "clik", b)                   # clik goals are not shaped here: a step
    assert outer.reference is b and outer.reports[-1].shaped_mode is None
    outer.goal(5.0, a.x, "clik", a)
    first = outer.goal(10.0, b.x, "replay")
    report = outer.reports[-1]
    assert report.shaped_mode is not None
    f, zeta = report.shaped_mode
    times, fractions = impulses("zv", f, zeta)
    assert np.allclose(first.shortening, a.shortening + fractions[0] * (b.shortening - a.shortening))
    frames = np.arange(10.0, 11.0, 1 / 240)[1:]
    changes = [(t, outer.frame(t, b.x)) for t in frames]
    changes = [(t, ref) for t, ref in changes if ref is not None]
    assert len(changes) == 1                          # one more fraction, at the first frame after the delay
    t_change, ref = changes[0]
    assert 10.0 + times[1] <= t_change < 10.0 + times[1] + 1 / 240
    assert ref is b and outer.reference is b and report.online_steps == 0     # replay: no CLIK
    # a clik goal shaped: online refinement waits for the last fraction, even past switch_delay
    outer = OuterLoop(clik, a, switch_delay=0.0, rate=240.0, shaper=shaper, shaped_modes=("clik",))
    outer.goal(0.0, b.x, "clik", b)
    end = 0.5 / (outer.reports[-1].shaped_mode[0] * np.sqrt(1 - outer.reports[-1].shaped_mode[1] ** 2))
    for t in frames - 10.0:
        outer.frame(t, b.x)
        if t < end:
            assert outer.reports[-1].online_steps == 0
    assert outer.reports[-1].online_steps > 0
    # a goal that interrupts a shaped clik step stores that step's end for the target
    outer.goal(2.0, a.x, "clik", a)
    outer.goal(2.01, b.x, "replay")
    assert outer.stored[outer.key(a.x)] is a
