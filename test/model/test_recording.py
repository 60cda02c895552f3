"""Splitting a recorded identification experiment: plateaus from the commands alone, the samples
at their settled ends, the dynamic segments between them, the noise from the data."""
import numpy as np
import pytest

from soft_arm_model.identification import IdentificationError
from soft_arm_model.recording import Recording, dynamic_segments, noise_levels, plateaus, static_samples


def _recording(noise=0.0, seed=0):
    """Commands: 3 s at 0.1 N, a 1 s step to 1 N on tendon 1, 5 s at 0.1 N, 4 s at (1, 0.5) N; the
    arm settles (first-order, 0.2 s) to shortening = 0.01 m/N x tension, markers follow."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 13.0, 0.002)
    c = np.full((t.size, 2), 0.1)
    c[(t >= 3) & (t < 4), 0] = 1.0
    c[t >= 9] = [1.0, 0.5]
    s = np.zeros_like(c)
    for k in range(1, t.size):
        s[k] = s[k - 1] + (0.01 * c[k - 1] - s[k - 1]) * 0.002 / 0.2
    t_m = np.arange(0.0, 13.0, 1 / 240)
    base = np.array([[0.0, 0.0, -0.2], [0.0, 0.0, -0.38]])
    s_m = np.array([np.interp(t_m, t, s[:, j]) for j in range(2)]).T
    markers = base[None] + s_m[:, 0][:, None, None] * np.array([1.0, 0.0, 0.0])   # x follows tendon 1
    markers = markers + rng.normal(0.0, noise, markers.shape) if noise else markers
    return Recording(t, s + (rng.normal(0.0, noise, s.shape) if noise else 0.0), c.copy(), t, c, t_m, markers)


def test_plateaus_are_the_constant_commands_long_enough():
    held = plateaus(_recording(), min_hold=2.5)
    assert [(round(p.start, 3), round(p.end, 3)) for p in held] == [(0.0, 3.0), (4.0, 9.0), (9.0, 12.998)]
    assert np.allclose(held[2].command, [1.0, 0.5])


def test_samples_average_the_settled_end():
    rec = _recording()
    held = plateaus(rec, 2.5)
    samples = static_samples(rec, held, average=1.0)
    assert np.allclose(samples[2].shortening, [0.01, 0.005], atol=1e-6)
    assert np.allclose(samples[2].tension, [1.0, 0.5])
    assert np.allclose(samples[1].markers[:, 0], 0.001, atol=1e-6)


def test_a_plateau_without_frames_is_refused():
    rec = _recording()
    sel = rec.t_markers < 8.5
    cut = Recording(rec.t, rec.shortening, rec.tension, rec.t_command, rec.command, rec.t_markers[sel],
                    rec.markers[sel])
    with pytest.raises(IdentificationError, match="plateau 3 .* no mocap frames"):
        static_samples(cut, plateaus(cut, 2.5), 1.0)


def test_no_commands_is_refused():
    rec = _recording()
    empty = Recording(rec.t, rec.shortening, rec.tension, rec.t_command[:0], rec.command[:0], rec.t_markers,
                      rec.markers)
    with pytest.raises(IdentificationError, match="tendon/command"):
        plateaus(empty, 2.5)


def test_dynamic_segments_are_the_moves_between_plateaus():
    held = plateaus(_recording(), 2.5)
    assert [(round(d.start, 3), round(d.end, 3)) for d in dynamic_segments(held, 0.2, 2.0)] == [(2.8, 6.0)]
    assert len(dynamic_segments(held, 0.2, 2.0, moves_only=False)) == 2


def test_noise_levels_come_from_the_spread_of_the_readings():
    rec = _recording(noise=2e-4)
    held = plateaus(rec, 2.5)
    marker, shortening = noise_levels(rec, held, 1.0, per_reading=True)
    assert marker == pytest.approx(2e-4, rel=0.15) and shortening == pytest.approx(2e-4, rel=0.15)
    marker_avg, _ = noise_levels(rec, held, 1.0)
    assert marker_avg == pytest.approx(2e-4 / np.sqrt(240), rel=0.2)


def test_frames_with_an_unseen_marker_are_left_out_of_the_samples():
    """A frame with an occluded marker (NaN) is not averaged: the samples are those of the frames
    that saw every marker, and a plateau whose frames all lost one has no mocap frames."""
    rec = _recording()
    markers = rec.markers.copy()
    markers[::3, 1] = np.nan                        # a third of the frames lost the second marker
    late = rec.t_markers >= 7.5
    markers[late, 0] = np.nan                       # the end of plateau 2 onwards lost the first
    lossy = Recording(rec.t, rec.shortening, rec.tension, rec.t_command, rec.command, rec.t_markers, markers)
    held = plateaus(lossy, 2.5)
    clean = static_samples(rec, held[:1], 1.0)[0]
    sample = static_samples(lossy, held[:1], 1.0)[0]
    assert np.all(np.isfinite(sample.markers))
    np.testing.assert_allclose(sample.markers, clean.markers, atol=1e-9)
    with pytest.raises(IdentificationError, match="plateau 2 .* no mocap frames"):
        static_samples(lossy, held, 1.0)
