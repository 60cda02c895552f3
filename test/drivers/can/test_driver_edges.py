"""The motor driver's edges: commands stamped on any clock (or none) never hold the watchdog off,
no tension pushes a tendon, a velocity read on the wrong firmware scale is caught."""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_rig import R, Rig, driver_config
from soft_arm_drivers.can.driver_config import Motor
from soft_arm_drivers.can.mit_protocol import MOTOR_PRESETS, decode_command
from soft_arm_drivers.can.motor_driver import tension_frame
from soft_arm_drivers.can.velocity_scale import VelocityScaleCheck, fitting_preset

TIMEOUT = 0.021             # s, the watchdog of these tests: 10.5 cycles at 500 Hz


def hold_commands(rig, stamp, seconds=0.3):
    """Enable, command 3 N stamped ``stamp`` once, then nothing for ``seconds``: the cycles' results."""
    rig.driver.enable()
    rig.step(5, [3.0] * 4)
    try:
        rig.driver.command([3.0] * 4, stamp)
    except ValueError:
        pass
    return [rig.step(1) for _ in range(round(seconds / rig.period))]


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf])
def test_a_command_without_a_finite_stamp_is_refused_and_the_watchdog_trips(make_rig, stamp):
    rig = make_rig(overrides={"watchdog_timeout": TIMEOUT})
    results = hold_commands(rig, stamp)
    assert results[-1].diagnostics.rejected_commands == 1
    assert results[-1].diagnostics.mode == "fault" and "stale command" in results[-1].diagnostics.fault
    enabled = sum(r.diagnostics.mode == "enabled" for r in results)
    assert enabled * rig.period <= TIMEOUT                   # tripped on time, counted from the last good one
    np.testing.assert_array_equal(results[-1].state.command, 0.0)


@pytest.mark.parametrize("offset", [1000.0, -1000.0, 1e9])
def test_a_command_stamped_on_another_clock_does_not_hold_the_watchdog_off(make_rig, offset):
    rig = make_rig(overrides={"watchdog_timeout": TIMEOUT})
    results = hold_commands(rig, rig.t + offset)
    assert results[-1].diagnostics.rejected_commands == 0         # accepted: its age counts from receipt
    assert results[-1].diagnostics.mode == "fault" and "stale command" in results[-1].diagnostics.fault
    assert sum(r.diagnostics.mode == "enabled" for r in results) * rig.period <= TIMEOUT + rig.period
    assert results[-1].diagnostics.command_age < 1.0               # on the driver's clock, not the stamp's


STAMPS = st.one_of(st.just(math.nan), st.just(math.inf), st.just(-math.inf), st.just(None),
                   st.floats(-1e12, 1e12), st.sampled_from([0.0, 1e9, -5.0]))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(events=st.lists(st.tuples(st.integers(0, 14), STAMPS), min_size=1, max_size=40))
def test_the_watchdog_trips_within_its_timeout_of_the_last_good_command_whatever_the_stamps(make_rig, events):
    """Commands after random gaps (cycles) with random stamps: the driver is enabled exactly while
    the last accepted command is at most ``watchdog_timeout`` old on its clock, and stays in fault
    once it tripped."""
    rig = make_rig(overrides={"watchdog_timeout": TIMEOUT})
    rig.driver.enable()
    last_good, tripped, rejected = rig.t, False, 0
    for gap, stamp in events + [(30, None)]:
        for _ in range(gap):
            result = rig.step(1)
            age = rig.t - rig.period - last_good
            tripped = tripped or age > TIMEOUT
            assert (result.diagnostics.mode == "fault") == tripped, (age, result.diagnostics)
        if gap < 30:
            try:
                rig.driver.command([1.0] * 4, stamp)
                last_good = rig.t
            except ValueError:
                rejected += 1
    assert tripped and rig.driver.rejected_commands == rejected
    assert rejected == sum(s is not None and not math.isfinite(s) for _, s in events)


# -- a tendon can only be pulled -----------------------------------------------------------------

TENSIONS = st.one_of(st.floats(allow_nan=False, allow_infinity=False),
                     st.floats(-1e6, 1e6), st.sampled_from([0.0, -0.0, 5e-324, -5e-324]))


@settings(max_examples=400, deadline=None)
@given(model=st.sampled_from(sorted(MOTOR_PRESETS)), direction=st.sampled_from([1, -1]),
       torque_range=st.sampled_from([0.0, 0.5, 3.0]), radius=st.floats(1e-3, 0.5), tension=TENSIONS)
def test_no_tension_gives_a_pushing_torque(model, direction, torque_range, radius, tension):
    motor = Motor(1, direction, model, torque_range)
    lim = motor.limits
    torque = decode_command(lim, tension_frame(motor, radius, tension)).torque
    step = (lim.t_max - lim.t_min) / 4095
    assert direction * torque >= 0.0
    assert direction * torque <= max(0.0, radius * tension) + step + 1e-12      # at most one step above


@pytest.mark.parametrize("tension", [math.nan, math.inf, -math.inf])
def test_a_tension_that_is_no_number_raises_value_error(tension):
    with pytest.raises(ValueError, match="finite"):
        tension_frame(Motor(1, 1, "AK10-9"), R, tension)


def test_a_negative_tension_is_the_smallest_pull_on_the_largest_motor():
    motor = Motor(1, 1, "AK10-9")
    torque = decode_command(motor.limits, tension_frame(motor, R, -1e6)).torque
    assert 0.0 <= torque <= 130.0 / 4095                # not -14,393 N of pushing: the field's zero pull
    assert decode_command(motor.limits, tension_frame(motor, R, 1e12)).torque == pytest.approx(65.0)


# -- the velocity scale ----------------------------------------------------------------------------

def moving(rig, seconds, amplitude=0.005, frequency=1.0):
    """Drive the (plant-less) tendons along a sine of ``amplitude`` [m] for ``seconds``; the results."""
    out = []
    for _ in range(round(seconds / rig.period)):
        w = 2 * math.pi * frequency
        phase = w * rig.t + np.arange(4)
        rig.emulator.set_tendons(amplitude * np.sin(phase), amplitude * w * np.cos(phase))
        out.append(rig.step(1))
    return out


@pytest.mark.parametrize("preset, firmware, ratio", [("AK80-9", "AK80-9-fw1.1", 0.45),
                                                     ("AK80-9", "AK80-9-fw2", 0.5128),
                                                     ("AK80-9-fw1.1", "AK80-9", 2.222)])
def test_a_motor_flashed_with_another_firmware_faults_naming_the_preset_that_fits(preset, firmware, ratio):
    rig = Rig(driver_config(models=[preset] * 4), firmware=firmware)
    try:
        results = moving(rig, 1.0)
        faults = [r.diagnostics.fault for r in results if r.diagnostics.fault]
        assert faults, "no mismatch found in 1 s of motion"
        assert f"the preset {preset}" in faults[0] and f"the preset {firmware} would fit" in faults[0]
        first = next(k for k, r in enumerate(results) if r.diagnostics.fault)
        assert first * rig.period < 0.5                          # before control relies on it for long
        measured = [m.velocity_ratio for m in results[-1].diagnostics.motors]
        np.testing.assert_allclose(measured, ratio, rtol=0.03)
    finally:
        rig.close()


def test_the_right_firmware_moves_without_a_fault_and_reports_a_ratio_of_one(make_rig):
    rig = make_rig()
    assert np.isnan([m.velocity_ratio for m in rig.step(5).diagnostics.motors]).all()    # not moved
    results = moving(rig, 2.0)
    assert all(r.diagnostics.fault is None for r in results)
    np.testing.assert_allclose([m.velocity_ratio for m in results[-1].diagnostics.motors], 1.0, atol=0.03)


def test_the_check_takes_the_median_block_ratio_and_restarts_after_a_gap():
    limits = MOTOR_PRESETS["AK80-9"]
    check = VelocityScaleCheck(["AK80-9"], [limits], block=0.02, min_step=10, blocks=8, confirm=2)
    dt, verdicts = 0.002, []
    for k in range(400):                      # position at 1 rad/s, velocity read as 2 rad/s: ratio 0.5
        gap = 1.0 if k >= 100 else 0.0       # a second without replies: not integrated over
        velocity = 2.0 if k % 50 else 40.0   # and a spike every 0.1 s: the median ignores it
        verdicts.append(check.add(0, k * dt + gap, 1.0 * k * dt, velocity))
    assert check.ratios()[0] == pytest.approx(0.5, rel=1e-9)
    found = [v for v in verdicts if v is not None]
    assert len(found) == 1 and "0.5 times" in found[0] and "+-25 rad/s" in found[0]
    assert "the preset AK80-9-fw2 would fit" in found[0]


def test_a_motor_that_barely_moves_gives_no_verdict():
    """Quantisation and noise on a motor at rest, or creeping below ten position steps per block,
    say nothing of the scale."""
    limits = MOTOR_PRESETS["AK80-9"]
    check = VelocityScaleCheck(["AK80-9"], [limits])
    rng = np.random.default_rng(5)
    lsb = 25.0 / 65535
    for k in range(5000):                     # 10 s: +-2 LSB of jitter, 0.05 rad/s of velocity noise
        assert check.add(0, k * 0.002, lsb * rng.integers(-2, 3) + 2e-3 * k * 0.002,
                         rng.normal(0.0, 0.05)) is None
    assert np.isnan(check.ratios()[0])


def test_fitting_presets():
    ak = MOTOR_PRESETS["AK80-9"]
    assert fitting_preset("AK80-9", ak, 0.45) == "AK80-9-fw1.1"
    assert fitting_preset("AK80-9", ak, 22.5 / 50 * 1.03) == "AK80-9-fw1.1"     # 3 % off: still it
    assert fitting_preset("AK80-9", ak, 1.52) == "AK80-6"                        # +-76 rad/s
    assert fitting_preset("AK80-9", ak, 0.05) is None
    assert fitting_preset("AK80-9", ak, -1.0) is None and fitting_preset("AK80-9", ak, math.nan) is None
