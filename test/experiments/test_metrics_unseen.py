"""Task metrics of windows in which the mocap lost the task's markers: the frames that did not see
them are left out, never read as positions; a window with none seen is an error."""
import numpy as np
import pytest

from soft_arm_experiments.metrics import measured_speed, tracking_metrics, transition_metrics
from soft_arm_control.trajectories import Trajectory


def _window(n=400):
    t = np.linspace(0.0, 4.0, n)
    error = np.column_stack([0.02 * np.exp(-3 * t) + 0.001, np.zeros(n)])
    tip = np.column_stack([0.05 * (1 - np.exp(-3 * t)), np.zeros(n)])
    return t, error, tip, np.abs(0.15 * np.exp(-3 * t))


def test_unseen_frames_are_left_out_of_every_figure():
    t, error, tip, speed = _window()
    clean = transition_metrics("p", 1, t, error, tip, speed, 2.0, 4.0)
    holes = np.zeros(t.size, bool)
    holes[50:90] = holes[300:320] = True
    e2, tip2 = error.copy(), tip.copy()
    e2[holes, 0] = np.nan
    tip2[holes[::-1], 1] = np.nan                   # the tip lost at other times
    lossy = transition_metrics("p", 1, t, e2, tip2, speed, 2.0, 4.0)
    assert np.isfinite(lossy.rms_steady) and lossy.rms_steady == pytest.approx(clean.rms_steady, rel=0.05)
    assert lossy.time_mm == pytest.approx(clean.time_mm, abs=0.05) and lossy.window == 4.0
    assert np.isfinite(lossy.peak_speed) and lossy.displacement == pytest.approx(clean.displacement)


def test_a_window_no_frame_saw_is_an_error_not_a_figure():
    t, error, tip, speed = _window()
    with pytest.raises(ValueError, match="0 of 400 frames saw"):
        transition_metrics("p", 3, t, np.full_like(error, np.nan), tip, speed)


def test_tracking_figures_skip_the_unseen_frames():
    t = np.linspace(0.0, 6.0, 600)
    errors = np.column_stack([0.001 * np.ones(600), np.zeros(600)])
    errors[100:200] = np.nan
    out = tracking_metrics("circle", 1, Trajectory("circle", 0.01, 2.0), t, errors, 1.0)
    assert out.rms_error == pytest.approx(0.001) and out.max_error == pytest.approx(0.001)


def test_measured_speed_steps_over_unseen_samples():
    t = np.arange(100) * 0.005
    p = np.column_stack([0.1 * t, np.zeros(100), np.zeros(100)])
    p[40:45] = np.nan
    v = measured_speed(t, p)
    assert np.isnan(v[40:45]).all()
    np.testing.assert_allclose(v[3:40], 0.1, rtol=1e-9)
    np.testing.assert_allclose(v[45:], 0.1, rtol=1e-9)
