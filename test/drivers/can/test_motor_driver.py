"""CAN motor driver core against the motor emulator on an in-process python-can ``virtual`` bus, in
lockstep with explicit time: conversions, zeroing, reply matching, every safety case, determinism;
the emulator's protocol behaviour; the ``rig.motors`` configuration."""
import contextlib
import math
import os
import subprocess
import sys

import can
import numpy as np
import pytest

from soft_arm_drivers.can.driver_config import Motor, load_driver_config
from soft_arm_drivers.can.mit_protocol import MOTOR_PRESETS, decode_command, encode_command, encode_reply
from soft_arm_drivers.can.motor_driver import PERIOD_WINDOW, MotorDriver, tension_frame
from soft_arm_drivers.can.order_statistics import percentile
from soft_arm_drivers.sim.can_emulator import CanMotorEmulator, EmulatorThread, arm_plant
from soft_arm_model.parameters import ConfigError

from can_rig import P_STEP, R, T_STEP, V_STEP, Rig, driver_config as config, pull


# -- conversions -------------------------------------------------------------------------------------

@pytest.mark.parametrize("model", sorted(MOTOR_PRESETS))
@pytest.mark.parametrize("direction", [1, -1])
def test_tension_frame_rounds_to_nearest_and_never_pushes(model, direction):
    motor = Motor(1, direction, model)
    lim = motor.limits
    step = (lim.t_max - lim.t_min) / 4095
    for tension in np.concatenate([[0.0, 1e-9, 1e-3], np.linspace(0.0, lim.t_max / R, 997)]):
        cmd = decode_command(lim, tension_frame(motor, R, tension))
        assert direction * cmd.torque >= 0.0, (tension, cmd.torque)
        error = abs(cmd.torque - direction * R * tension)
        assert error <= (step if R * tension < step else step / 2) + 1e-12, (tension, error)
        assert cmd.kp == 0.0 and cmd.kd == 0.0


def test_tension_to_torque_to_tension_round_trip(make_rig):
    rig = make_rig(overrides={"directions": [1, -1, 1, -1]})
    command = np.array([0.5, 1.7, 3.0, 5.0])
    rig.driver.enable()
    result = rig.step(8, command)                      # rate limit: 1 N per cycle
    assert result.diagnostics.mode == "enabled"
    np.testing.assert_array_equal(result.state.command, command)
    # the motors apply d r T to within half a torque step, always pulling
    np.testing.assert_allclose(rig.emulator.tensions, command, atol=T_STEP / 2 / R + 1e-9)
    assert np.all(pull(rig.emulator) > 0) and np.sign([rig.emulator.torque(i) for i in range(4)]).tolist() \
        == [1, -1, 1, -1]
    # measured: the reply torque (truncated to 12 bits) back to tension
    np.testing.assert_allclose(result.state.tension, command, atol=1.5 * T_STEP / R)


@pytest.mark.parametrize("directions", [[1, 1, 1, 1], [-1, 1, -1, 1]])
def test_encoder_angle_to_shortening_relative_to_the_zero(make_rig, directions):
    rig = make_rig(overrides={"directions": directions}, zero_spread=2.0, seed=3)
    rest = np.array([0.010, 0.004, 0.007, 0.012])
    rig.emulator.set_tendons(rest)
    before = rig.step(2).state.shortening
    # before zeroing: relative to the motors' stored zeros (seeded, up to 2 rad = 2 cm of tendon)
    expected = [d * R * (d * s / R - m.zero) for d, s, m in zip(directions, rest, rig.emulator.motors)]
    np.testing.assert_allclose(before, expected, atol=R * P_STEP)
    rig.driver.zero()
    rig.step(2)
    moved, rate = rest + [0.021, -0.003, 0.0, 0.0005], np.array([0.05, -0.02, 0.0, 0.1])
    rig.emulator.set_tendons(moved, rate)
    state = rig.step(2).state
    np.testing.assert_allclose(state.shortening, moved - rest, atol=R * P_STEP)
    np.testing.assert_allclose(state.rate, rate, atol=R * V_STEP)


def test_shortening_follows_the_arm_plant_under_tension(make_rig):
    rig = make_rig(arm_plant())
    rig.step(2)
    rig.driver.zero()
    rig.step(2)
    s0, _ = rig.emulator.tendons()
    rig.driver.enable()
    for _ in range(100):                                  # 0.2 s at 2.5 N on tendon 1
        rig.driver.command([2.5, 0.0, 0.0, 0.0])
        true_s, true_rate = rig.emulator.tendons()       # what the replies to this cycle will carry
        state = rig.step(1).state
    state = rig.step(1, [2.5, 0.0, 0.0, 0.0]).state
    assert state.complete and state.shortening[0] > 5e-3          # the pulled tendon shortens
    np.testing.assert_allclose(state.shortening, true_s - s0, atol=2 * R * P_STEP)
    np.testing.assert_allclose(state.rate, true_rate, atol=R * V_STEP)
    assert rig.emulator.tensions[0] == pytest.approx(2.5, abs=T_STEP / 2 / R)


def test_zeroing_is_explicit_and_refused_while_enabled(make_rig):
    rig = make_rig(zero_spread=1.0, seed=7)
    state = rig.step(50).state
    assert all(m.zero_count == 0 for m in rig.emulator.motors)       # nothing zeroes at start-up
    assert np.max(np.abs(state.shortening)) > 1e-3
    rig.driver.enable()
    with pytest.raises(RuntimeError, match="slack"):
        rig.driver.zero()
    assert all(m.zero_count == 0 for m in rig.emulator.motors)
    rig.driver.disable()
    assert not rig.step(2).diagnostics.zeroed
    rig.driver.zero()
    result = rig.step(2)
    assert all(m.zero_count == 1 for m in rig.emulator.motors)
    assert result.diagnostics.zeroed
    np.testing.assert_allclose(result.state.shortening, 0.0, atol=R * P_STEP)


# -- reply matching ----------------------------------------------------------------------------------

def test_replies_are_matched_by_the_motor_id_in_the_payload():
    cfg = config(ids=[3, 1, 7, 2])
    other = can.Bus(interface="virtual", channel=cfg.channel, preserve_timestamps=True)
    bus = can.Bus(interface="virtual", channel=cfg.channel)
    try:
        driver = MotorDriver(cfg, bus, clock=lambda: 0.0)
        lim = MOTOR_PRESETS["AK80-9"]
        angles = {3: 0.1, 1: -0.2, 7: 0.3, 2: -0.4}

        def reply(motor_id, angle, extra=(40, 0)):
            return can.Message(arbitration_id=0, is_extended_id=False, timestamp=1.0 + motor_id,
                               data=encode_reply(lim, motor_id, angle, 0.0, 0.0, *extra))
        for motor_id in (2, 7, 3, 1):                                   # not in tendon order
            extra = (40 + motor_id, 0) if motor_id != 1 else (None, None)       # motor 1: 6 bytes
            other.send(reply(motor_id, angles[motor_id], extra))
        other.send(reply(9, 1.0))                                       # not one of ours
        other.send(can.Message(arbitration_id=0, data=bytes(5), is_extended_id=False))  # bad length
        other.send(can.Message(arbitration_id=0, is_error_frame=True, is_extended_id=False))
        # a command to motor 3 from another host: not a reply (arbitration id), whatever its byte 0
        other.send(can.Message(arbitration_id=3, is_extended_id=False, data=bytes([3]) + bytes(7)))
        other.send(can.Message(arbitration_id=0, is_extended_id=True,               # extended id
                               data=encode_reply(lim, 3, 2.0, 0.0, 0.0)))
        result = driver.cycle()
        state, diag = result.state, result.diagnostics
        np.testing.assert_allclose(state.shortening, [R * angles[i] for i in (3, 1, 7, 2)], atol=R * P_STEP)
        np.testing.assert_array_equal(state.stamps, [4.0, 2.0, 8.0, 3.0])
        assert state.complete and state.stamp == 2.0
        assert [m.temperature for m in diag.motors] == [43, None, 47, 42]
        assert [m.can_id for m in diag.motors] == [3, 1, 7, 2]
        assert diag.foreign_frames == 4 and diag.error_frames == 1
        driver.close()
    finally:
        bus.shutdown()
        other.shutdown()


def test_frames_that_do_not_leave_on_a_stop_are_returned_though_the_fault_names_the_stop():
    """The bus down (every send raises): e-stop, disable and close latch e-stop as the fault's
    reason, the first, and return each frame that did not leave, so that a caller that reports the
    stop can say the motors may not have it (it answered success before)."""
    cfg = config(ids=[1, 2, 3, 4])
    bus = can.Bus(interface="virtual", channel=cfg.channel)
    try:
        driver = MotorDriver(cfg, bus, clock=lambda: 0.0)

        def down(*args, **kwargs):
            raise can.CanError("Network is down")
        bus.send = down
        unsent = driver.estop()
        assert driver.fault == "e-stop"
        assert unsent == [f"motor {i}: Network is down" for i in (1, 2, 3, 4)] * 2   # zero, exit
        assert len(driver.disable()) == 8 and len(driver.close()) == 8 and driver.close() == []
    finally:
        bus.shutdown()


def test_a_zero_whose_frames_do_not_leave_is_returned_and_leaves_the_driver_unzeroed():
    """The bus down for one motor's frame: zero returns that frame and the driver is not zeroed
    (the fault it latched, which the next enable clears, cannot be the only trace); once every frame
    leaves, zeroed."""
    cfg = config(ids=[1, 2, 3, 4])
    bus = can.Bus(interface="virtual", channel=cfg.channel)
    try:
        driver = MotorDriver(cfg, bus, clock=lambda: 0.0)
        send = bus.send

        def down_for_motor_3(message, *args, **kwargs):
            if message.arbitration_id == 3:
                raise can.CanError("No buffer space available")
            return send(message, *args, **kwargs)
        bus.send = down_for_motor_3
        assert driver.zero() == ["motor 3: No buffer space available"] and not driver.zeroed
        assert "motor 3" in driver.fault
        bus.send = send
        assert driver.zero() == [] and driver.zeroed
    finally:
        bus.shutdown()


@contextlib.contextmanager
def _driver_and_motors(clock=lambda: 0.0):
    """A driver for motors 1-4 on a virtual channel (the driver's ``clock``), and a second bus on
    the channel to send their replies from; ``reply(motor_id, angle, stamp)``: one motor's reply
    at ``angle`` [rad] received at ``stamp`` [s]. The driver and both buses are closed after."""
    cfg = config(ids=[1, 2, 3, 4])
    motors = can.Bus(interface="virtual", channel=cfg.channel, preserve_timestamps=True)
    bus = can.Bus(interface="virtual", channel=cfg.channel)
    driver = None
    lim = MOTOR_PRESETS["AK80-9"]

    def reply(motor_id, angle=0.1, stamp=1.0):
        motors.send(can.Message(arbitration_id=0, is_extended_id=False, timestamp=stamp,
                                data=encode_reply(lim, motor_id, angle, 0.0, 0.0, 40, 0)))
    try:
        driver = MotorDriver(cfg, bus, clock=clock)
        yield cfg, driver, reply
    finally:
        if driver is not None:
            driver.close()
        bus.shutdown()
        motors.shutdown()


@pytest.mark.parametrize("angles, fault", [
    ((0.2, 12.5), "at the end of its field"),            # saturated: a tendon run off its spool
    ((-0.3, -12.5), "at the end of its field"),
    ((12.3, -12.3), "wrapped at the end of its field"),  # firmware that does not clamp
    ((12.3, 12.4), None), ((-4.0, 4.0), None)])          # far from the ends, and a fast turn
def test_an_angle_at_the_end_of_the_reply_field_or_wrapped_is_no_measurement(angles, fault):
    """A motor's angle at the end of the 16-bit field (+-12.5 rad: +-125 mm of tendon on a 1 cm
    pulley) saturates, or wraps in firmware that does not clamp: the shortening would read a tendon
    held still while the motor spins free. Either latches a fault naming the motor; angles within
    the field, however far apart, do not."""
    with _driver_and_motors() as (_, driver, reply):
        for angle in angles:
            for motor_id in (1, 2, 3, 4):
                reply(motor_id, angle if motor_id == 2 else 0.1)
            diag = driver.cycle().diagnostics
        if fault is None:
            assert diag.fault is None
        else:
            assert diag.fault.startswith("motor 2: angle") and fault in diag.fault, diag.fault


@pytest.mark.parametrize("stamp", [math.nan, math.inf])
def test_a_reply_whose_receive_time_is_no_number_is_refused_and_counted(stamp):
    """The state's stamp is its replies' receive time: a reply without one is not taken (its motor
    goes on without a reply, the state is incomplete, and its silence names the refusals), where it
    ended the node's cycle on the stamp's conversion."""
    now = [0.0]
    with _driver_and_motors(lambda: now[0]) as (cfg, driver, reply):
        for motor_id in (1, 2, 3, 4):
            reply(motor_id, stamp=stamp if motor_id == 3 else 1.0)
        result = driver.cycle()
        assert not result.state.fresh[2] and result.state.fresh[[0, 1, 3]].all()
        assert not result.state.complete and result.diagnostics.unstamped_frames == 1
        assert result.diagnostics.foreign_frames == 0 and result.diagnostics.fault is None
        now[0] = 2 * cfg.reply_timeout
        diag = driver.cycle().diagnostics
        assert diag.fault.startswith("motor 1 silent") and "1 replies refused" in diag.fault, diag.fault


# -- safety ------------------------------------------------------------------------------------------

def test_stale_commands_trip_the_watchdog_and_latch_until_enable(make_rig):
    rig = make_rig(overrides={"watchdog_timeout": 0.021})        # 10.5 cycles at 500 Hz
    rig.driver.enable()
    rig.step(10, [3.0, 3.0, 3.0, 3.0])
    last_command = rig.t - rig.period
    for _ in range(50):                                             # bounded: fail, never hang
        now = rig.t
        result = rig.step(1)
        if result.diagnostics.mode != "enabled":
            break
    assert 0.021 < now - last_command <= 0.021 + rig.period        # the first cycle past the timeout
    assert result.diagnostics.mode == "fault" and "stale command" in result.diagnostics.fault
    assert result.diagnostics.stale_commands == 1
    np.testing.assert_array_equal(result.state.command, 0.0)
    assert np.all(pull(rig.emulator) <= T_STEP)                    # zero torque (the field's nearest pull)
    result = rig.step(5, [3.0, 3.0, 3.0, 3.0])                     # fresh commands do not clear it
    assert result.diagnostics.mode == "fault" and np.all(pull(rig.emulator) <= T_STEP)
    rig.driver.enable()
    result = rig.step(10, [3.0, 3.0, 3.0, 3.0])
    assert result.diagnostics.mode == "enabled" and result.diagnostics.fault is None
    np.testing.assert_allclose(rig.emulator.tensions, 3.0, atol=T_STEP / 2 / R)


def test_commands_are_clipped_to_the_range_and_rate_limited(make_rig):
    """Tensions are clipped to [0, max_tension] and rate-limited; a command above max_tension is
    counted (a controller that believes it can pull harder winds up against the clip), one below
    zero is not (a slack tendon's)."""
    rig = make_rig(overrides={"tension_rate_limit": 250.0})     # 0.5 N per cycle at 500 Hz
    rig.driver.enable()
    rig.step(1)
    rig.driver.command([4.0, -3.0, 2.2, 0.0])
    assert rig.driver.diagnostics().clipped_commands == 0
    sent = []
    for _ in range(14):
        sent.append(rig.step(1, [10.0, -3.0, 2.2, 0.0]).state.command)
        assert np.all(pull(rig.emulator) >= 0)
    assert rig.driver.diagnostics().clipped_commands == 14
    sent = np.array(sent)
    assert np.all(np.abs(np.diff(sent, axis=0)) <= 0.5 + 1e-12)
    np.testing.assert_allclose(sent[:4, 0], [0.5, 1.0, 1.5, 2.0])
    np.testing.assert_allclose(sent[-1], [5.0, 0.0, 2.2, 0.0])   # max_tension 5 N, never below 0
    sent = [rig.step(1, [0.0, 0.0, 0.0, 0.0]).state.command[0] for _ in range(3)]
    np.testing.assert_allclose(sent, [4.5, 4.0, 3.5])             # down at the same rate


def test_the_rate_limit_bounds_one_frames_step_after_a_late_cycle_or_a_pause_before_enable(make_rig):
    """The motors take a frame's tension at once: a cycle three periods late moves the tension by
    1.5 periods' worth of the limit (not four), and after 16 ms without cycles the first enabled
    frame moves by what the limit allows since enable(), half a period before it."""
    rig = make_rig(overrides={"tension_rate_limit": 250.0})     # 0.5 N per cycle at 500 Hz
    rig.driver.enable()
    rig.step(3, [1.0] * 4)
    held = rig.step(1, [1.0] * 4).state.command
    np.testing.assert_allclose(held, 1.0)
    rig.k += 3                                                   # the next cycle is three periods late
    late = rig.step(1, [5.0] * 4)
    assert late.diagnostics.mode == "enabled"
    np.testing.assert_allclose(late.state.command - held, 0.75)
    rig.driver.disable()
    rig.step(2)
    rig.k += 8                                                   # no cycle for 16 ms, then
    rig.now = rig.t - 0.5 * rig.period                           # enable() half a period before the next
    rig.driver.enable()
    first = rig.step(1, [5.0] * 4).state.command
    np.testing.assert_allclose(first, 0.25)


@pytest.mark.parametrize("bad", [[1.0, math.nan, 1.0, 1.0], [1.0, 1.0, math.inf, 1.0], [1.0, 1.0, 1.0],
                                 [[1.0, 1.0, 1.0, 1.0]]])
def test_malformed_commands_are_rejected_and_the_last_one_ages(make_rig, bad):
    rig = make_rig()
    rig.driver.enable()
    rig.step(5, [2.0, 2.0, 2.0, 2.0])
    for _ in range(15):                                             # watchdog: 10 cycles
        with pytest.raises(ValueError):
            rig.driver.command(bad)
        result = rig.step(1)
        if result.diagnostics.mode == "fault":
            break
        np.testing.assert_array_equal(result.state.command, 2.0)     # the previous command holds
    assert result.diagnostics.rejected_commands == 11
    assert "stale command" in result.diagnostics.fault                # ... until the watchdog trips


def test_a_silent_motor_stops_every_motor(make_rig):
    rig = make_rig(overrides={"reply_timeout": 0.011})             # 5.5 cycles at 500 Hz
    rig.driver.enable()
    rig.step(5, [2.0, 2.0, 2.0, 2.0])
    rig.emulator.inject(2, silent=True)
    silent_from = rig.t                                             # its last reply is read now
    for _ in range(50):                                             # bounded: fail, never hang
        now = rig.t
        result = rig.step(1, [2.0, 2.0, 2.0, 2.0])
        if result.diagnostics.mode != "enabled":
            break
    assert 0.011 < now - silent_from <= 0.011 + rig.period
    assert not result.state.fresh[1] and result.state.fresh[[0, 2, 3]].all()
    assert result.diagnostics.fault.startswith("motor 2 silent for")
    assert result.diagnostics.motors[1].reply_age > 0.011
    rig.step(1)
    assert np.all(pull(rig.emulator) <= T_STEP)                    # all four, the silent one too
    assert rig.emulator.tensions.max() <= T_STEP / R


@pytest.mark.parametrize("fault, reason", [({"error": 2}, "motor 3 reports error 2 (over current)"),
                                           ({"temperature": 71},
                                            "motor 3 at 71 deg C, above max_temperature 70")])
def test_error_codes_and_temperatures_stop_every_motor(make_rig, fault, reason):
    rig = make_rig()
    rig.driver.enable()
    rig.step(5, [2.0, 2.0, 2.0, 2.0])
    rig.emulator.inject(3, temperature=70)                          # at the limit: fine
    assert rig.step(3, [2.0, 2.0, 2.0, 2.0]).diagnostics.mode == "enabled"
    rig.emulator.inject(3, **fault)
    assert rig.step(1, [2.0, 2.0, 2.0, 2.0]).diagnostics.mode == "enabled"   # replies sent before
    result = rig.step(1, [2.0, 2.0, 2.0, 2.0])                              # the first faulty reply
    assert result.diagnostics.mode == "fault" and result.diagnostics.fault == reason
    np.testing.assert_array_equal(result.state.command, 0.0)
    rig.step(1)
    assert np.all(pull(rig.emulator) <= T_STEP)
    rig.emulator.inject(3, error=0, temperature=40)
    rig.step(1)                                       # the replies still in flight carry the fault
    rig.driver.enable()
    assert rig.step(5, [2.0, 2.0, 2.0, 2.0]).diagnostics.fault is None


def test_enable_disable_and_estop(make_rig):
    rig = make_rig()
    rig.step(3, [2.0, 2.0, 2.0, 2.0])
    assert not any(m.motor_mode for m in rig.emulator.motors)       # disabled: commands not applied
    assert np.all(rig.emulator.tensions == 0)
    rig.driver.enable()
    rig.step(5, [2.0, 2.0, 2.0, 2.0])
    assert all(m.motor_mode for m in rig.emulator.motors) and np.all(rig.emulator.tensions > 1.5)
    rig.driver.disable()
    result = rig.step(3, [2.0, 2.0, 2.0, 2.0])
    assert result.diagnostics.mode == "disabled" and result.diagnostics.fault is None
    assert not any(m.motor_mode for m in rig.emulator.motors) and np.all(rig.emulator.tensions == 0)
    rig.driver.enable()
    rig.step(5, [2.0, 2.0, 2.0, 2.0])
    rig.driver.estop()
    rig.emulator.advance_to(rig.t)                  # the e-stop frames act before the next cycle
    assert not any(m.motor_mode for m in rig.emulator.motors)
    assert all(rig.emulator.torque(i) == 0.0 for i in range(4))
    result = rig.step(3, [2.0, 2.0, 2.0, 2.0])
    assert result.diagnostics.mode == "fault" and result.diagnostics.fault == "e-stop"
    assert not any(m.motor_mode for m in rig.emulator.motors)
    rig.driver.disable()                                            # does not clear a latched fault
    assert rig.step(1).diagnostics.fault == "e-stop"
    rig.driver.enable()
    result = rig.step(5, [1.0, 1.0, 1.0, 1.0])
    assert result.diagnostics.mode == "enabled" and all(m.motor_mode for m in rig.emulator.motors)


def test_leaving_on_an_exception_exits_motor_mode():
    cfg = config()
    emulator_bus = can.Bus(interface="virtual", channel=cfg.channel, preserve_timestamps=True)
    emulator = CanMotorEmulator.for_config(cfg, emulator_bus)
    try:
        with pytest.raises(KeyError):
            k = 0
            with MotorDriver(cfg, clock=lambda: k * 0.002) as driver:   # opens the virtual bus itself
                driver.enable()
                for k in range(5):
                    driver.command([3.0] * 4)
                    driver.cycle()
                    emulator.advance_to((k + 1) * 0.002)
                assert all(m.motor_mode for m in emulator.motors) and emulator.torque(0) > 0.02
                raise KeyError("boom")
        emulator.advance_to(0.02)
        assert not any(m.motor_mode for m in emulator.motors)
        assert all(emulator.torque(i) == 0.0 for i in range(4))
        with pytest.raises(can.CanOperationError):                  # the driver's own bus is shut
            driver.bus.send(can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False))
        with pytest.raises(RuntimeError, match="closed"):
            driver.cycle()
    finally:
        emulator_bus.shutdown()


def test_bus_errors_latch_a_fault(make_rig):
    rig = make_rig()
    rig.driver.enable()
    rig.step(3, [1.0, 1.0, 1.0, 1.0])
    rig.bus.shutdown()
    rig.now = rig.t + rig.period
    result = rig.driver.cycle()
    assert result.diagnostics.mode == "fault" and result.diagnostics.fault.startswith("CAN ")


# -- timing ------------------------------------------------------------------------------------------

def run_once(seed):
    cfg = config()
    rig = Rig(cfg, encoder_noise=1e-3, reply_delay=4e-4, seed=seed)
    try:
        rig.emulator.set_tendons([0.01, 0.02, 0.03, 0.04], [0.001, 0.0, -0.001, 0.0])
        rig.driver.enable()
        out = [rig.step(1, [1.0 + 0.01 * k, 2.0, 0.5, 0.0]).state for k in range(30)]
        return out, rig.driver.diagnostics()
    finally:
        rig.close()


def test_runs_are_deterministic_with_explicit_time():
    a, diag = run_once(seed=11)
    b, _ = run_once(seed=11)
    c, _ = run_once(seed=12)
    assert diag.mode == "enabled" and diag.late_cycles == 0
    for x, y in zip(a, b):
        for field in ("shortening", "rate", "tension", "stamps", "command"):
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
    assert any(not np.array_equal(x.shortening, y.shortening) for x, y in zip(a, c))   # the noise is seeded
    # the reply to cycle k (at k T) is read by cycle k + 1, stamped with its send time k T + delay
    for k, state in enumerate(a[1:]):
        np.testing.assert_allclose(state.stamps, k * 0.002 + 4e-4, atol=1e-12)
    assert np.isnan(a[0].stamp) and not a[0].fresh.any()


def test_a_held_cycle_names_what_held_it(make_rig):
    """What the caller says held the cycle (the node's publishing after the previous cycle, its
    wait for the hardware lock): the watchdog's fault names each that was half the hold or more,
    and nothing of those shorter."""
    publishing, locked = "in the node's publishing after the previous cycle", \
        "waiting for the hardware lock, held by the estop service"
    faults = {}
    for publish_time, lock_wait in ((0.0, 0.0), (0.011, 0.005), (0.012, 0.0), (0.022, 0.0), (0.001, 0.015),
                                    (0.012, 0.012)):
        rig = make_rig(overrides={"watchdog_timeout": 0.021})
        rig.driver.enable()
        rig.step(10, [3.0, 3.0, 3.0, 3.0])
        rig.k += 11                                              # 24 ms since the previous cycle
        rig.now = rig.t
        rig.driver.command([3.0, 3.0, 3.0, 3.0])
        faults[publish_time, lock_wait] = rig.driver.cycle(
            ((publish_time, publishing), (lock_wait, locked))).diagnostics.fault
    held = "cycle held: 0.0240 s since the previous cycle, the motors unwatched (watchdog_timeout 0.021 s)"
    assert faults[0.0, 0.0] == faults[0.011, 0.005] == held
    assert faults[0.012, 0.0] == held + f"; 0.0120 s of it {publishing}"
    assert faults[0.022, 0.0] == held + f"; 0.0220 s of it {publishing}"
    assert faults[0.001, 0.015] == held + f"; 0.0150 s of it {locked}"
    assert faults[0.012, 0.012] == held + f"; 0.0120 s of it {publishing}; 0.0120 s of it {locked}"


def test_a_cycle_held_past_the_watchdog_timeout_trips_whatever_the_command_reads(make_rig):
    """The driver's process held for longer than the watchdog's timeout and a command taken just
    before the late cycle (the executor ran first): the command is fresh, but nothing watched the
    motors meanwhile. A cycle late by less is counted, not a fault; disabled, not a fault; enabled
    after a long gap between cycles, the watch starts at the enable."""
    rig = make_rig(overrides={"watchdog_timeout": 0.021})
    rig.driver.enable()
    rig.step(10, [3.0, 3.0, 3.0, 3.0])
    rig.k += 5                                                   # 10 ms late: counted only
    result = rig.step(1, [3.0, 3.0, 3.0, 3.0])
    assert result.diagnostics.mode == "enabled" and result.diagnostics.late_cycles == 1
    rig.k += 11                                                  # 22 ms: past the timeout
    result = rig.step(1, [3.0, 3.0, 3.0, 3.0])
    assert result.diagnostics.mode == "fault"
    assert result.diagnostics.fault == ("cycle held: 0.0240 s since the previous cycle, the motors "
                                        "unwatched (watchdog_timeout 0.021 s)")
    assert result.diagnostics.stale_commands == 0
    np.testing.assert_array_equal(result.state.command, 0.0)
    idle = make_rig(overrides={"watchdog_timeout": 0.021})
    idle.step(3)
    idle.k += 50
    result = idle.step(1)
    assert result.diagnostics.mode == "disabled" and result.diagnostics.fault is None
    idle.k += 50                                                 # enabled after a long gap: the
    idle.now = idle.t                                            # watch starts at the enable
    idle.driver.enable()
    result = idle.step(1, [3.0, 3.0, 3.0, 3.0])
    assert result.diagnostics.mode == "enabled" and result.diagnostics.fault is None


def test_late_cycles_are_counted_and_time_cannot_go_back(make_rig):
    rig = make_rig()
    assert np.isnan(rig.driver.cycle_statistics().period_max)
    rig.step(3)
    rig.k += 1                                                       # a cycle skipped
    assert rig.step(1).diagnostics.late_cycles == 1
    rig.now = rig.t - 1.0
    with pytest.raises(RuntimeError, match="not monotonic"):
        rig.driver.cycle()


def test_cycle_statistics_show_a_delayed_cycle_and_look_back_a_window(make_rig):
    """Periods between cycle starts: 200 on time, one 7 ms late (a deadline miss), the rest on
    time; the window forgets the late one after PERIOD_WINDOW cycles."""
    rig = make_rig()
    period = rig.period
    times = list(np.arange(201) * period)
    times.append(times[-1] + period + 7e-3)
    times += list(times[-1] + np.arange(1, 300) * period)
    for rig.now in times:
        rig.driver.cycle()
    stats = rig.driver.cycle_statistics()
    assert stats.cycles == len(times) - 1 and stats.deadline_misses == 1
    assert stats.period_p50 == pytest.approx(period, abs=1e-9)
    assert stats.period_max == pytest.approx(period + 7e-3, abs=1e-9)
    # one period in 500 is above the 99th percentile; the others are exact
    assert stats.period_p99 == pytest.approx(period, abs=1e-9)
    assert stats.period_error_p99 == pytest.approx(0.0, abs=1e-9)
    for rig.now in times[-1] + np.arange(1, PERIOD_WINDOW + 1) * period:
        rig.driver.cycle()
    stats = rig.driver.cycle_statistics()
    assert stats.cycles == PERIOD_WINDOW and stats.deadline_misses == 1     # a count, not a window
    assert stats.period_max == pytest.approx(period, abs=1e-9)


def test_the_percentiles_are_numpys():
    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 10, 999, PERIOD_WINDOW):
        values = np.sort(rng.exponential(2e-3, n))
        for q in (0, 1, 50, 99, 100):
            assert percentile(values, q) == pytest.approx(np.percentile(values, q), rel=1e-12, abs=1e-18)


_CYCLES_IMPORT_NOTHING = """
import sys
from can_rig import Rig, driver_config
from soft_arm_drivers.can.command_latency import CommandLatency
rig = Rig(driver_config())
latency = CommandLatency()
rig.step(2)
rig.driver.enable()
rig.step(2, [1.0, 1.0, 1.0, 1.0])
before = set(sys.modules)
for k in range(600):
    latency.published(k * 0.002, k * 0.002)
    latency.answered(k * 0.002, k * 0.002 + 1e-3)
    rig.step(1, [2.0, 1.0, 2.0, 1.0])
rig.driver.diagnostics()
rig.driver.cycle_statistics()
latency.statistics()
rig.driver.disable()
rig.step(2)
print(sorted(set(sys.modules) - before))
rig.close()
"""


def test_cycles_commands_and_reports_import_nothing_once_running():
    """A module imported in the cycle thread holds the interpreter for the whole import (numpy
    imports numpy.ma at np.percentile's first call: 7 ms idle, longer loaded, in a 2-4 ms cycle):
    once enabled, cycles, commands, the diagnostics, the cycle statistics and the command latency's
    import no module. In a fresh process, whose modules are the driver's own (this one has imported
    the whole suite's)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.dirname(__file__)] + sys.path))
    out = subprocess.run([sys.executable, "-c", _CYCLES_IMPORT_NOTHING], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


# -- the emulator ------------------------------------------------------------------------------------

def test_the_motors_firmware_timeout_zeroes_their_command_when_the_driver_stops_sending(make_rig):
    """The driver's process stops (no cycle, no frame): the watchdog, a part of it, cannot act, and
    the motors' own CAN timeout zeroes their command a timeout after their last frame, on their own
    clock; the next command frame applies again."""
    said = []
    rig = make_rig(command_timeout=0.05, on_timeout=lambda can_id, silence: said.append((can_id, silence)))
    rig.driver.enable()
    rig.step(10, [3.0, 3.0, 3.0, 3.0])
    np.testing.assert_allclose(rig.emulator.tensions, 3.0, atol=T_STEP / 2 / R)
    last_frame = rig.t - rig.period                              # the last cycle's frames
    rig.emulator.advance_to(last_frame + 0.049)                  # within the timeout: still pulling
    np.testing.assert_allclose(rig.emulator.tensions, 3.0, atol=T_STEP / 2 / R)
    assert not said
    rig.emulator.advance_to(last_frame + 0.052)                  # past it: no torque
    np.testing.assert_array_equal(rig.emulator.tensions, 0.0)
    assert sorted(c for c, _ in said) == [m.can_id for m in rig.config.motors]
    assert all(0.05 < silence <= 0.05 + rig.emulator.dt + 1e-9 for _, silence in said)
    assert [m.timeouts for m in rig.emulator.motors] == [1, 1, 1, 1]
    rig.emulator.advance_to(last_frame + 0.2)                    # once per silence, not per step
    assert len(said) == 4
    rig.k = int(round(rig.emulator.t / rig.period))              # the driver comes back: its
    result = rig.step(1, [3.0, 3.0, 3.0, 3.0])                   # watchdog missed its deadline
    assert result.diagnostics.mode == "fault" and result.diagnostics.fault.startswith("cycle held: 0.2")
    rig.driver.enable()                                          # the next commands apply again
    rig.step(10, [3.0, 3.0, 3.0, 3.0])
    np.testing.assert_allclose(rig.emulator.tensions, 3.0, atol=T_STEP / 2 / R)


def test_without_a_firmware_timeout_a_silent_driver_leaves_the_motors_pulling(make_rig):
    rig = make_rig()
    rig.driver.enable()
    rig.step(10, [3.0, 3.0, 3.0, 3.0])
    rig.emulator.advance_to(rig.t + 1.0)
    np.testing.assert_allclose(rig.emulator.tensions, 3.0, atol=T_STEP / 2 / R)


def test_emulator_applies_the_mit_law_only_in_motor_mode():
    cfg = config()
    bus = can.Bus(interface="virtual", channel=cfg.channel)
    emulator_bus = can.Bus(interface="virtual", channel=cfg.channel, preserve_timestamps=True)
    try:
        emulator = CanMotorEmulator.for_config(cfg, emulator_bus, zero_spread=0.0, reply_delay=1e-3)
        emulator.set_tendons([0.002, 0, 0, 0], [0.01, 0, 0, 0])      # 0.2 rad, 1 rad/s on motor 1
        lim = MOTOR_PRESETS["AK80-9"]
        stiff = encode_command(lim, 0.5, 0.0, 10.0, 0.2, 0.3)         # kp (0.5 - 0.2) + kd (0 - 1) + 0.3

        def send(data):
            bus.send(can.Message(arbitration_id=1, data=data, is_extended_id=False))
        send(stiff)
        emulator.advance_to(0.0005)
        assert emulator.torque(0) == 0.0 and emulator.replies_sent == 0    # rest mode; reply after 1 ms
        emulator.advance_to(0.0015)
        first = bus.recv(timeout=0)
        assert first.timestamp == pytest.approx(1e-3) and len(first.data) == 8
        send(bytes([0xFF] * 7 + [0xFC]))                              # enter motor mode: command cleared
        send(stiff)
        emulator.advance_to(0.003)
        cmd = decode_command(lim, stiff)
        expected = cmd.kp * (cmd.position - 0.2) + cmd.kd * (cmd.velocity - 1.0) + cmd.torque
        assert emulator.torque(0) == pytest.approx(expected)
        assert emulator.tensions[0] == pytest.approx(expected / R)
        assert emulator.motor(1).frames == 3
    finally:
        bus.shutdown()
        emulator_bus.shutdown()


def test_emulator_quantises_the_encoder_and_may_send_short_replies(make_rig):
    step = 2 * math.pi / 4096                                          # a 12-bit encoder [rad]
    rig = make_rig(encoder_resolution=step, extended_replies=False, zero_spread=0.0)
    true_angle = 800.4 * step
    rig.emulator.set_tendons([true_angle * R, 0.0, 0.0, 0.0])
    result = rig.step(3)
    assert result.state.shortening[0] / R == pytest.approx(800 * step, abs=P_STEP)   # 0.4 step off
    assert result.diagnostics.motors[0].temperature is None and result.diagnostics.mode == "disabled"


# -- configuration -----------------------------------------------------------------------------------

def test_the_package_rig_yaml_loads():
    cfg = load_driver_config(n_tendons=4)
    assert cfg.interface == "socketcan" and cfg.rate == 500.0 and len(cfg.motors) == 4
    assert [m.can_id for m in cfg.motors] == [1, 2, 3, 4]


@pytest.mark.parametrize("overrides, message", [
    ({"max_tension": -1.0}, "rig.motors.max_tension = -1.0 is not valid: expected a tension in (0, 1000] N"),
    ({"max_tension": 200.0, "pulley_radius": 0.1},
     "rig.motors.max_tension = 200.0 is not valid: expected a tension in (0, 180] N: the smallest torque"),
    ({"interface": "sockcan"}, "rig.motors.interface = 'sockcan' is not valid: expected a python-can"),
    ({"ids": [1, 2, 2, 4]},
     "rig.motors.ids = [1, 2, 2, 4] is not valid: expected distinct CAN ids in [1, 255]"),
    ({"directions": [1, 0, 1, 1]}, "rig.motors.directions = [1, 0, 1, 1] is not valid: expected 1 or -1"),
    ({"directions": [1, 1, 1]}, "rig.motors.directions = [1, 1, 1] is not valid: expected 4 values"),
    ({"models": ["AK80-9"] * 3 + ["AK81"]},
     "rig.motors.models = ['AK80-9', 'AK80-9', 'AK80-9', 'AK81'] is not valid: expected motor models among"),
    ({"rate": 0.0}, "rig.motors.rate = 0.0 is not valid: expected a rate in [1, 2000] Hz"),
    ({"rate": 1200.0}, "rig.motors.rate = 1200.0 is not valid: expected a rate in [1, 1126] Hz"),
    ({"reply_timeout": 0.003},
     "rig.motors.reply_timeout = 0.003 is not valid: expected a time of at least two cycles, 0.004 s"),
    ({"watchdog_timeout": "fast"},
     "rig.motors.watchdog_timeout = 'fast' is not valid: expected a time in (0, 1] s"),
    ({"bitrate": 2000000}, "rig.motors.bitrate = 2000000 is not valid: expected a bit rate in"),
    ({"speed": 1.0}, "unknown key rig.motors.speed"),
])
def test_bad_values_name_the_key_the_value_and_the_range(overrides, message):
    with pytest.raises(ConfigError) as info:
        load_driver_config(overrides=overrides)
    assert message in str(info.value)


def test_motor_count_must_match_the_tendons():
    with pytest.raises(ConfigError,
                       match=r"rig.motors.ids = \[1, 2, 3, 4\] is not valid: expected 3 CAN ids"):
        load_driver_config(n_tendons=3)


def test_a_narrower_firmware_torque_range_gives_finer_tension_steps_and_zero_pose_offsets_shortening():
    coarse = config()
    fine = config(torque_ranges=[0.5] * 4, zero_shortening=[-0.001, -0.001, 0.002, 0.0])
    assert coarse.motors[0].limits.t_max == 18.0 and fine.motors[0].limits.t_max == 0.5
    r = fine.pulley_radius
    step_coarse = 2 * 18.0 / 4095 / r
    step_fine = 2 * 0.5 / 4095 / r
    assert step_fine < 0.03 < 0.8 < step_coarse                     # N of tension per wire step
    assert fine.zero_shortening == (-0.001, -0.001, 0.002, 0.0)
    with pytest.raises(ConfigError, match="rig.motors.torque_ranges"):
        config(torque_ranges=[0.5] * 3)
    with pytest.raises(ConfigError, match="max_tension"):
        config(torque_ranges=[0.01] * 4)                            # 0.01 N m cannot pull 5 N at 1 cm


def test_zeroing_pose_shortening_is_added_to_the_readings(make_rig):
    offset = np.array([-0.001, -0.001, 0.002, 0.0])
    rig = make_rig(overrides={"zero_shortening": list(offset)}, seed=1)
    rest = np.array([0.010, 0.004, 0.007, 0.012])
    rig.emulator.set_tendons(rest)
    rig.step(2)
    rig.driver.zero()
    rig.step(2)
    rig.emulator.set_tendons(rest + 0.003)
    np.testing.assert_allclose(rig.step(2).state.shortening, offset + 0.003, atol=R * P_STEP)


def test_emulator_gives_the_plant_configuration_at_past_times():
    """The history's configuration at t is the plant's state after the last step at or before t:
    the same as an identical emulator stopped at t (the arm, settled at 0.5 N, falls back under no
    torque)."""
    def emulator_until(t_end):
        cfg = config()
        bus = can.Bus(interface="virtual", channel=cfg.channel)
        emulator = CanMotorEmulator.for_config(cfg, bus, arm_plant(tension=0.5))
        emulator.advance_to(t_end)
        bus.shutdown()
        return emulator

    late = emulator_until(0.05)
    for t in (0.0205, 0.0300):
        early = emulator_until(t)
        np.testing.assert_array_equal(late.history.at(t), early.plant.q)
    assert not np.allclose(late.history.at(0.02), late.plant.q)     # it moved meanwhile
    np.testing.assert_array_equal(late.history.at(1.0), late.plant.q)


def test_probe_finds_the_answering_motors_without_a_silence_fault(make_rig):
    """Before the cycle: motors that take longer than reply_timeout to answer first are not a
    fault; a silent one stays unanswered; an error code in a reply is."""
    rig = make_rig()
    rig.emulator.inject(2, silent=True)
    period, answered, t = rig.period, np.zeros(4, dtype=bool), 0.0
    while t < 3 * rig.config.reply_timeout:
        rig.now = t
        answered |= rig.driver.probe()
        rig.emulator.advance_to(t + period)
        t += period
    assert answered.tolist() == [True, False, True, True]
    assert rig.driver.fault is None and rig.driver.cycles == 0 and not rig.driver.diagnostics().zeroed
    rig.emulator.inject(4, error=2)
    rig.now = t
    rig.driver.probe()
    rig.emulator.advance_to(t + period)
    rig.now = t + period
    rig.driver.probe()
    assert rig.driver.fault is not None and "motor 4 reports error 2" in rig.driver.fault


def test_an_emulator_thread_that_does_not_end_is_named_within_its_bound():
    """An emulator whose serving does not return (a plant step that hangs): stopping its thread
    waits at most the bound and names the emulator; one that ends raises what it ended on."""
    import threading
    import time
    from types import SimpleNamespace
    release = threading.Event()
    stuck = EmulatorThread(SimpleNamespace(serve=lambda clock, stop: release.wait(10.0))).start()
    start = time.monotonic()
    with pytest.raises(RuntimeError, match="the CAN motor emulator's thread did not end within 0.2 s"):
        stuck.stop(timeout=0.2)
    assert time.monotonic() - start < 2.0
    release.set()

    def fails(clock, stop):
        raise can.CanError("bus gone")
    failed = EmulatorThread(SimpleNamespace(serve=fails)).start()
    with pytest.raises(can.CanError, match="bus gone"):
        failed.stop()
