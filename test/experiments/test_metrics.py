"""The paper's task-space metrics on synthetic signals with known answers."""
import numpy as np
import pytest

from soft_arm_control.trajectories import Trajectory
from soft_arm_experiments.metrics import (format_table, format_tracking, measured_speed,
                                          settling_time, summarise, to_json, tracking_metrics,
                                          transition_metrics)


def _decay(t, amplitude, rate):
    """A two-coordinate error decaying exponentially, and a straight tip path of 0.2 m."""
    err = amplitude * np.exp(-rate * t)[:, None] * np.array([1.0, -0.5])
    tip = np.column_stack([0.2 * (1 - np.exp(-rate * t)), np.zeros_like(t), np.zeros_like(t)])
    return err, tip


def test_settling_time_is_the_last_entry_into_the_band():
    t = np.linspace(0, 5, 501)
    err, _ = _decay(t, 0.2, 2.0)
    # |e_1| = 0.2 exp(-2 t) < 0.03  <=>  t > ln(0.2 / 0.03) / 2
    assert settling_time(t, err, 0.03) == pytest.approx(np.log(0.2 / 0.03) / 2, abs=0.011)
    bounce = err.copy()
    bounce[300] = 0.05                                     # leaves the band again at t = 3 s
    assert settling_time(t, bounce, 0.03) == pytest.approx(3.01, abs=1e-9)
    assert settling_time(t, err + 0.05, 0.03) is None      # never inside at the end


def test_transition_metrics_and_summary():
    t = np.linspace(0, 5, 1201)
    err, tip = _decay(t, 0.2, 2.0)
    row = transition_metrics("p", 1, t, err, tip, np.full(t.size, 1.5), steady_time=1.0)
    assert row.displacement == pytest.approx(0.2 * (1 - np.exp(-10.0)))
    assert row.velocity_cm == pytest.approx(row.displacement / row.time_cm)
    assert row.time_mm == pytest.approx(np.log(0.2 / 0.01) / 2, abs=0.005)
    steady = t >= 4.0
    assert row.rms_steady == pytest.approx(np.sqrt(np.mean(np.sum(err[steady] ** 2, axis=1))))
    slow = transition_metrics("q", 2, t, err + 0.02, tip, np.full(t.size, 0.5), steady_time=1.0)
    assert slow.time_mm is None and slow.velocity_mm is None
    summary = summarise([row, slow])
    assert summary.velocity_mm == row.velocity_mm and summary.peak_speed == 1.5
    assert summary.reached_mm == 1 and summary.transitions == 2
    assert "Table 1 row" in format_table([row, slow], summary)
    assert to_json([row], summarise([row]))["summary"]["reached_cm"] == 1


def test_no_velocity_when_the_move_is_within_the_band():
    """A 2 cm move is inside the 3 cm band from the start: no cm-band velocity (it would be
    displacement / one sample), but a mm-band one."""
    t = np.linspace(0, 2, 481)
    err, tip = _decay(t, 0.02, 3.0)
    tip = tip * 0.1                                       # 2 cm of travel
    row = transition_metrics("p", 1, t, err, tip, np.ones(t.size))
    assert row.time_cm == 0.0 and row.velocity_cm is None
    assert row.velocity_mm == pytest.approx(row.displacement / row.time_mm)
    # a diagonal move of 3.8 cm, 2.7 cm on each of two coordinates: inside the 3 cm band at once
    diagonal = np.stack([err[:, 0], err[:, 0]], axis=1) * (0.027 / 0.02)
    row = transition_metrics("p", 1, t, diagonal, np.stack([tip[:, 0], tip[:, 0]], axis=1) * 1.35,
                             np.ones(t.size))
    assert row.displacement > 0.03 and row.time_cm == 0.0 and row.velocity_cm is None


def test_measured_speed_is_exact_on_uniform_motion_and_ignores_uneven_frame_spacing():
    """Uniform motion at 0.5 m/s sampled at uneven times (frames 0.1 ms apart among them), with
    0.2 mm of noise: the speed stays near 0.5 m/s, where frame-to-frame differences reach m/s."""
    rng = np.random.default_rng(0)
    t = np.sort(np.r_[np.arange(0.0, 1.0, 1 / 240), np.arange(0.0, 1.0, 1 / 240)[5::7] + 1e-4])
    velocity = np.array([0.3, 0.0, -0.4])
    exact = t[:, None] * velocity
    np.testing.assert_allclose(measured_speed(t, exact)[3:], 0.5, rtol=1e-9)
    assert measured_speed(t, exact)[0] == 0.0                     # nothing 10 ms before
    noisy = exact + rng.normal(0.0, 2e-4, exact.shape)
    frame_to_frame = np.linalg.norm(np.diff(noisy, axis=0), axis=1) / np.diff(t)
    assert frame_to_frame.max() > 2.0
    assert np.abs(measured_speed(t, noisy)[3:] - 0.5).max() < 0.12        # 4-5 sigma of one sample
    with pytest.raises(ValueError, match="baseline"):
        measured_speed(t, exact, baseline=0.0)


def test_tracking_figures_count_from_the_settling_time_and_give_the_last_period_apart():
    """A window of 10 s at 100 Hz whose error is 3 mm until 8 s and 1 mm after (a period of 2 s):
    the RMS from the settling time (2 s) mixes both, the last period's is the 1 mm; a window not a
    period longer than the settling time has no last period."""
    t = np.arange(0.0, 10.0, 0.01)
    errors = np.where(t[:, None] < 8.0, [0.003, 0.0], [0.0, 0.001])
    row = tracking_metrics("circle", 1, Trajectory("circle", 0.01, 2.0), t, errors, settle=2.0)
    assert row.rms_error == pytest.approx(np.sqrt((6 * 0.003 ** 2 + 2 * 0.001 ** 2) / 8), rel=1e-2)
    assert row.max_error == pytest.approx(0.003)
    assert row.last_period_rms_error == pytest.approx(0.001, rel=1e-2)
    short = tracking_metrics("circle", 1, Trajectory("circle", 0.01, 2.0), t[t < 3.5], errors[t < 3.5], 2.0)
    assert short.last_period_rms_error is None
    assert "1.00" in format_tracking([row]) and format_tracking([short]).rstrip().endswith("-")
