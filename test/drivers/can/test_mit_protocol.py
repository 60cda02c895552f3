"""MIT mini-cheetah CAN codec: exact bytes, round trips, clipping, special frames, replies."""
import math

import pytest
from hypothesis import given, settings, strategies as st

from soft_arm_drivers.can.mit_protocol import (ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, MOTOR_PRESETS,
                                               SET_ZERO_POSITION, MotorLimits, MotorReply, decode_command,
                                               decode_reply, encode_command, encode_reply, float_to_uint,
                                               is_special_frame, torque_command, torque_frame,
                                               uint_to_float)

AK80_9 = MotorLimits.preset("AK80-9")


def pack_by_hand(p, v, kp, kd, t):
    """The command layout written out byte by byte, independently of the encoder."""
    return bytes([p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | kp >> 8, kp & 0xFF, kd >> 4,
                  (kd & 0xF) << 4 | t >> 8, t & 0xFF])


def lsb(low, high, bits):
    return (high - low) / ((1 << bits) - 1)


# --- exact byte vectors (AK80-9: p +-12.5, v +-50, t +-18, kp 0..500, kd 0..5) -------------------

def test_zero_command_bytes():
    # p: trunc(12.5 * 65535 / 25) = 32767 = 0x7FFF; v: trunc(50 * 4095 / 100) = 2047 = 0x7FF;
    # kp = kd = 0; t: trunc(18 * 4095 / 36) = 2047 = 0x7FF.
    expected = pack_by_hand(0x7FFF, 0x7FF, 0, 0, 0x7FF)
    assert expected == bytes.fromhex("7F FF 7F F0 00 00 07 FF")
    assert encode_command(AK80_9, 0.0, 0.0, 0.0, 0.0, 0.0) == expected


def test_mixed_command_bytes():
    # p = 1.0:  trunc(13.5 * 65535 / 25) = trunc(35388.9) = 35388 = 0x8A3C
    # v = -2.0: trunc(48 * 4095 / 100) = trunc(1965.6) = 1965 = 0x7AD
    # kp = 10:  trunc(10 * 4095 / 500) = trunc(81.9) = 81 = 0x051
    # kd = 0.5: trunc(0.5 * 4095 / 5) = trunc(409.5) = 409 = 0x199
    # t = 1.5:  trunc(19.5 * 4095 / 36) = trunc(2218.125) = 2218 = 0x8AA
    expected = pack_by_hand(0x8A3C, 0x7AD, 0x051, 0x199, 0x8AA)
    assert expected == bytes.fromhex("8A 3C 7A D0 51 19 98 AA")
    assert encode_command(AK80_9, 1.0, -2.0, 10.0, 0.5, 1.5) == expected


def test_command_is_one_big_endian_word():
    frame = encode_command(AK80_9, 1.0, -2.0, 10.0, 0.5, 1.5)
    word = 0x8A3C << 48 | 0x7AD << 36 | 0x051 << 24 | 0x199 << 12 | 0x8AA
    assert frame == word.to_bytes(8, "big")


def test_clipped_command_bytes():
    # Everything beyond its range lands on the range end: p max, v min, kp max, kd min, t max.
    frame = encode_command(AK80_9, 100.0, -1e3, 1e6, -1.0, 18.0)
    assert frame == pack_by_hand(0xFFFF, 0x000, 0xFFF, 0x000, 0xFFF)
    assert frame == bytes.fromhex("FF FF 00 0F FF 00 0F FF")


def test_reply_bytes_without_and_with_temperature():
    # id 1, p 0 -> 0x7FFF, v 0 -> 0x7FF, t 0 -> 0x7FF; byte 4 = (0x7FF & 0xF) << 4 | 0x7FF >> 8.
    short = bytes.fromhex("01 7F FF 7F F7 FF")
    assert encode_reply(AK80_9, 1, 0.0, 0.0, 0.0) == short
    assert encode_reply(AK80_9, 1, 0.0, 0.0, 0.0, temperature=30, error=0) == short + b"\x1e\x00"


# --- special frames ------------------------------------------------------------------------------

def test_special_frame_constants():
    assert ENTER_MOTOR_MODE == bytes.fromhex("FF FF FF FF FF FF FF FC")
    assert EXIT_MOTOR_MODE == bytes.fromhex("FF FF FF FF FF FF FF FD")
    assert SET_ZERO_POSITION == bytes.fromhex("FF FF FF FF FF FF FF FE")
    assert all(is_special_frame(f) for f in (ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, SET_ZERO_POSITION))
    assert not is_special_frame(bytes.fromhex("FF FF FF FF FF FF FF FF"))
    assert not is_special_frame(ENTER_MOTOR_MODE[:7])


@pytest.mark.parametrize("raw_torque", [0xFFC, 0xFFD, 0xFFE])
def test_saturated_command_never_looks_like_a_special_frame(raw_torque):
    t_lsb = lsb(AK80_9.t_min, AK80_9.t_max, 12)
    torque = AK80_9.t_min + (raw_torque + 0.5) * t_lsb
    frame = encode_command(AK80_9, AK80_9.p_max, AK80_9.v_max, AK80_9.kp_max, AK80_9.kd_max, torque)
    assert not is_special_frame(frame)
    assert frame == pack_by_hand(0xFFFE, 0xFFF, 0xFFF, 0xFFF, raw_torque)
    decoded = decode_command(AK80_9, frame)
    assert decoded.position == pytest.approx(AK80_9.p_max - lsb(AK80_9.p_min, AK80_9.p_max, 16))


def test_fully_saturated_command_is_not_special():
    frame = encode_command(AK80_9, 99.0, 99.0, 999.0, 99.0, 99.0)
    assert frame == bytes([0xFF] * 8)


@pytest.mark.parametrize("frame", [ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, SET_ZERO_POSITION])
def test_decode_command_rejects_special_frames(frame):
    with pytest.raises(ValueError, match="special frame"):
        decode_command(AK80_9, frame)


# --- round trips ---------------------------------------------------------------------------------

def _in_range(low, high):
    return st.floats(min_value=low, max_value=high, allow_nan=False, allow_infinity=False)


@st.composite
def commands(draw):
    limits = MOTOR_PRESETS[draw(st.sampled_from(sorted(MOTOR_PRESETS)))]
    values = (draw(_in_range(limits.p_min, limits.p_max)), draw(_in_range(limits.v_min, limits.v_max)),
              draw(_in_range(limits.kp_min, limits.kp_max)),
              draw(_in_range(limits.kd_min, limits.kd_max)),
              draw(_in_range(limits.t_min, limits.t_max)))
    return limits, values


def _assert_within_one_lsb(value, decoded, step):
    # The firmware truncates: the decoded value is never above the input and less than 1 LSB below.
    assert -1e-9 <= value - decoded < step + 1e-9


@settings(max_examples=300, deadline=None)
@given(commands())
def test_command_round_trip_within_one_lsb(case):
    limits, values = case
    frame = encode_command(limits, *values)
    decoded = decode_command(limits, frame)
    nudged = frame[:2] == b"\xff\xfe" and frame[2:7] == b"\xff" * 5 and frame[7] in (0xFC, 0xFD, 0xFE)
    p_step = lsb(limits.p_min, limits.p_max, 16) * (2 if nudged else 1)
    steps = (p_step, lsb(limits.v_min, limits.v_max, 12), lsb(limits.kp_min, limits.kp_max, 12),
             lsb(limits.kd_min, limits.kd_max, 12), lsb(limits.t_min, limits.t_max, 12))
    for value, result, step in zip(values, decoded, steps):
        _assert_within_one_lsb(value, result, step)


@settings(max_examples=200, deadline=None)
@given(commands(), st.integers(0, 255), st.none() | st.tuples(st.integers(0, 255), st.integers(0, 255)))
def test_reply_round_trip_within_one_lsb(case, motor_id, extra):
    limits, (position, velocity, _, _, torque) = case
    temperature, error = extra if extra else (None, None)
    frame = encode_reply(limits, motor_id, position, velocity, torque, temperature, error)
    assert len(frame) == (8 if extra else 6)
    reply = decode_reply(limits, frame)
    assert (reply.motor_id, reply.temperature, reply.error) == (motor_id, temperature, error)
    _assert_within_one_lsb(position, reply.position, lsb(limits.p_min, limits.p_max, 16))
    _assert_within_one_lsb(velocity, reply.velocity, lsb(limits.v_min, limits.v_max, 12))
    _assert_within_one_lsb(torque, reply.torque, lsb(limits.t_min, limits.t_max, 12))


@settings(max_examples=100, deadline=None)
@given(st.integers(0, (1 << 12) - 1))
def test_uint_float_uint_is_identity(raw):
    # Exact for every 12-bit code on the AK80-9 ranges (no code is lost by truncation).
    for low, high in ((AK80_9.v_min, AK80_9.v_max), (AK80_9.t_min, AK80_9.t_max),
                      (AK80_9.kp_min, AK80_9.kp_max)):
        value = uint_to_float(raw, low, high, 12) + 1e-9 * (high - low)
        assert float_to_uint(value, low, high, 12) == raw


# --- clipping and invalid input ------------------------------------------------------------------

def test_float_to_uint_ends_and_clipping():
    assert float_to_uint(-12.5, -12.5, 12.5, 16) == 0
    assert float_to_uint(12.5, -12.5, 12.5, 16) == 0xFFFF
    assert float_to_uint(-1e9, -12.5, 12.5, 16) == 0
    assert float_to_uint(1e9, -25.64, 25.64, 12) == 0xFFF
    assert uint_to_float(0, -50.0, 50.0, 12) == -50.0
    assert uint_to_float(0xFFF, -50.0, 50.0, 12) == 50.0


@pytest.mark.parametrize("raw", [-1, 1 << 12])
def test_uint_to_float_rejects_out_of_range(raw):
    with pytest.raises(ValueError, match="12 bits"):
        uint_to_float(raw, -1.0, 1.0, 12)


def test_out_of_range_values_are_clipped():
    limits = MotorLimits.preset("AK60-6")
    assert encode_command(limits, -40.0, 80.0, 600.0, 7.0, -30.0) == encode_command(
        limits, limits.p_min, limits.v_max, limits.kp_max, limits.kd_max, limits.t_min)
    reply = decode_reply(limits, encode_reply(limits, 3, 40.0, -80.0, 30.0))
    assert (reply.position, reply.velocity, reply.torque) == (limits.p_max, limits.v_min, limits.t_max)


@pytest.mark.parametrize("index", range(5))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_command_rejects_non_finite(index, bad):
    values = [0.0] * 5
    values[index] = bad
    name = ("position", "velocity", "kp", "kd", "torque")[index]
    with pytest.raises(ValueError, match=name):
        encode_command(AK80_9, *values)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_reply_and_torque_command_reject_non_finite(bad):
    with pytest.raises(ValueError, match="velocity"):
        encode_reply(AK80_9, 1, 0.0, bad, 0.0)
    with pytest.raises(ValueError, match="torque"):
        torque_command(AK80_9, bad)
    with pytest.raises(ValueError, match="finite"):
        float_to_uint(bad, -1.0, 1.0, 12)


@pytest.mark.parametrize("length", [0, 6, 7, 9])
def test_decode_command_rejects_wrong_length(length):
    with pytest.raises(ValueError, match="8 bytes"):
        decode_command(AK80_9, bytes(length))


@pytest.mark.parametrize("length", [0, 5, 7, 9])
def test_decode_reply_rejects_wrong_length(length):
    with pytest.raises(ValueError, match="6 or 8 bytes"):
        decode_reply(AK80_9, bytes(length))


@pytest.mark.parametrize("kwargs", [{"temperature": 30}, {"error": 0}])
def test_reply_needs_both_or_neither_extra_byte(kwargs):
    with pytest.raises(ValueError, match="both temperature and error"):
        encode_reply(AK80_9, 1, 0.0, 0.0, 0.0, **kwargs)


@pytest.mark.parametrize("field, value", [("motor_id", 256), ("motor_id", -1), ("motor_id", 1.0),
                                          ("temperature", 300), ("error", True)])
def test_reply_rejects_bad_bytes(field, value):
    kwargs = {"motor_id": 1, "temperature": 20, "error": 0, field: value}
    with pytest.raises(ValueError, match=field):
        encode_reply(AK80_9, position=0.0, velocity=0.0, torque=0.0, **kwargs)


# --- torque mode and replies ---------------------------------------------------------------------

def test_torque_command_has_zero_gains():
    command = decode_command(AK80_9, torque_command(AK80_9, 2.5))
    assert command.kp == 0.0 and command.kd == 0.0
    assert 0.0 <= 2.5 - command.torque < lsb(AK80_9.t_min, AK80_9.t_max, 12)


@pytest.mark.parametrize("model", sorted(MOTOR_PRESETS))
def test_torque_frame_is_the_torque_command_of_its_level(model):
    limits = MotorLimits.preset(model)
    step = lsb(limits.t_min, limits.t_max, 12)
    for raw in range(4096):
        torque = limits.t_min + (raw + 0.25) * step     # quantises to ``raw`` (the field truncates)
        assert torque_frame(limits, raw) == torque_command(limits, torque), raw
    for bad in (-1, 4096):
        with pytest.raises(ValueError, match="12 bits"):
            torque_frame(limits, bad)


def test_decode_reply_with_temperature_and_error():
    reply = decode_reply(AK80_9, bytes.fromhex("05 7F FF 7F F7 FF 2D 01"))
    assert reply == MotorReply(motor_id=5, position=pytest.approx(0.0, abs=4e-4),
                               velocity=pytest.approx(0.0, abs=0.025),
                               torque=pytest.approx(0.0, abs=0.01), temperature=45, error=1)
    assert reply.error_text == "over temperature"


def test_decode_reply_without_temperature():
    reply = decode_reply(AK80_9, bytearray.fromhex("02 00 00 FF F0 00"))
    assert reply.motor_id == 2
    assert (reply.position, reply.velocity, reply.torque) == (AK80_9.p_min, AK80_9.v_max, AK80_9.t_min)
    assert reply.temperature is None and reply.error is None and reply.error_text is None


def test_unknown_error_code_text():
    assert decode_reply(AK80_9, bytes(7) + b"\x63").error_text == "unknown error code 99"


# --- limits --------------------------------------------------------------------------------------

def test_presets_match_the_cubemars_table():
    table = {"AK10-9": (50.0, 65.0), "AK60-6": (45.0, 15.0), "AK70-10": (50.0, 25.0),
             "AK80-6": (76.0, 12.0), "AK80-9": (50.0, 18.0), "AK80-64": (8.0, 144.0)}
    for model, (v_max, t_max) in table.items():
        limits = MotorLimits.preset(model)
        assert (limits.p_min, limits.p_max) == (-12.5, 12.5)
        assert (limits.v_min, limits.v_max, limits.t_min, limits.t_max) == (-v_max, v_max, -t_max, t_max)
        assert (limits.kp_min, limits.kp_max, limits.kd_min, limits.kd_max) == (0.0, 500.0, 0.0, 5.0)


def test_unknown_preset_lists_the_known_models():
    with pytest.raises(ValueError, match="AK80-9") as info:
        MotorLimits.preset("AK99-1")
    assert "AK99-1" in str(info.value)


def test_limits_are_frozen():
    with pytest.raises(AttributeError):
        AK80_9.p_max = 95.5


@pytest.mark.parametrize("overrides, field", [
    ({"p_max": math.nan}, "p_max"),
    ({"v_min": math.inf}, "v_min"),
    ({"t_min": "1"}, "t_min"),
    ({"kd_max": True}, "kd_max"),
    ({"p_min": 12.5}, "p_min must be smaller than p_max"),
    ({"v_min": 60.0}, "v_min must be smaller than v_max"),
    ({"kp_min": -1.0}, "kp_min must be >= 0"),
    ({"kd_min": -0.5, "kd_max": 5.0}, "kd_min must be >= 0"),
])
def test_limits_validation_names_the_field(overrides, field):
    kwargs = dict(p_min=-12.5, p_max=12.5, v_min=-50.0, v_max=50.0, t_min=-18.0, t_max=18.0)
    kwargs.update(overrides)
    with pytest.raises(ValueError, match=field):
        MotorLimits(**kwargs)


# --- over a python-can bus -----------------------------------------------------------------------

def test_command_and_reply_over_a_virtual_can_bus():
    can = pytest.importorskip("can")
    with can.Bus(interface="virtual", channel="mit-test", receive_own_messages=False) as host, \
            can.Bus(interface="virtual", channel="mit-test", receive_own_messages=False) as motor:
        host.send(can.Message(arbitration_id=3, is_extended_id=False,
                              data=encode_command(AK80_9, 1.0, -2.0, 10.0, 0.5, 1.5)))
        received = motor.recv(timeout=1.0)
        command = decode_command(AK80_9, received.data)
        motor.send(can.Message(arbitration_id=0, is_extended_id=False,
                               data=encode_reply(AK80_9, received.arbitration_id, command.position,
                                                 command.velocity, command.torque, 40, 0)))
        reply = decode_reply(AK80_9, host.recv(timeout=1.0).data)
    assert reply.motor_id == 3 and reply.temperature == 40 and reply.error_text == "no error"
    assert reply.position == pytest.approx(1.0, abs=lsb(-12.5, 12.5, 16))
    assert reply.torque == pytest.approx(1.5, abs=2 * lsb(-18.0, 18.0, 12))
