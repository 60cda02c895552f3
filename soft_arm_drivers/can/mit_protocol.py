"""MIT mini-cheetah CAN protocol ("MIT mode" of CubeMars / T-Motor AK actuators), without ROS.

Pure codec: bytes in, floats out and back. The CAN driver node and the motor emulator both build on
it; neither the arbitration id nor the bus is handled here.

Bus conventions (for the caller): classic CAN 2.0 at 1 Mbit/s, standard 11-bit ids. Commands are
sent with the motor's CAN id as arbitration id; replies go to the host id (0 by default), so a reply
is matched to its motor by the id in payload byte 0, never by the arbitration id.

Command frame, 8 bytes, fields big-endian and bit-packed (bit 0 = LSB of each field)::

    byte 0: p[15:8]    byte 1: p[7:0]                      p:  16-bit position      [rad]
    byte 2: v[11:4]    byte 3: v[3:0] << 4 | kp[11:8]      v:  12-bit velocity      [rad/s]
    byte 4: kp[7:0]                                        kp: 12-bit stiffness     [N*m/rad]
    byte 5: kd[11:4]   byte 6: kd[3:0] << 4 | t[11:8]      kd: 12-bit damping       [N*m*s/rad]
    byte 7: t[7:0]                                         t:  12-bit feed-forward  [N*m]

i.e. the 64-bit big-endian integer ``p << 48 | v << 36 | kp << 24 | kd << 12 | t``. The motor
applies ``tau = kp * (p_des - p) + kd * (v_des - v) + t_ff``.

Reply frame, 6 bytes, or 8 on CubeMars firmware that appends temperature and error code::

    byte 0: motor id
    byte 1: p[15:8]    byte 2: p[7:0]                      p: 16-bit position       [rad]
    byte 3: v[11:4]    byte 4: v[3:0] << 4 | t[11:8]       v: 12-bit velocity       [rad/s]
    byte 5: t[7:0]                                         t: 12-bit torque         [N*m]
    byte 6: temperature [deg C, uint8]   byte 7: error code (see ``MOTOR_ERRORS``)

Special frames are seven 0xFF bytes followed by 0xFC (enter motor mode; also polls a reply),
0xFD (exit motor mode) or 0xFE (set the current position as zero).

Scaling is linear over per-model ranges (``MotorLimits``): ``u = trunc((x - min) * (2**bits - 1)
/ (max - min))`` after clipping ``x`` into ``[min, max]``, and ``x = u * (max - min) / (2**bits - 1)
+ min``. The firmware truncates, so a round trip loses less than one LSB, always downwards. The
firmware computes in float32 and this module in float64; the two can differ by one LSB when the
scaled value lands within float32 rounding of an integer.

Sources: bgkatz/motorcontrol ``Core/Src/can.c`` (``pack_reply``, ``unpack_cmd``) and
``Core/Src/math_ops.c`` (``float_to_uint``, ``uint_to_float``); CubeMars "AK Series Actuator Driver
Manual V1.0.8", section 5.3, pp. 48-50 (special frames, frame layouts, range table).
"""
import functools
import math
from dataclasses import dataclass, fields
from numbers import Real
from typing import NamedTuple, Optional

__all__ = [
    "COMMAND_LENGTH", "ENTER_MOTOR_MODE", "EXIT_MOTOR_MODE", "MOTOR_ERRORS", "MOTOR_PRESETS",
    "MotorCommand", "MotorLimits", "MotorReply", "REPLY_LENGTHS", "SET_ZERO_POSITION",
    "SPECIAL_FRAMES", "decode_command", "decode_reply", "encode_command", "encode_reply",
    "float_to_uint", "is_special_frame", "torque_command", "torque_frame", "uint_to_float",
]

COMMAND_LENGTH = 8
REPLY_LENGTHS = (6, 8)

ENTER_MOTOR_MODE = bytes([0xFF] * 7 + [0xFC])
EXIT_MOTOR_MODE = bytes([0xFF] * 7 + [0xFD])
SET_ZERO_POSITION = bytes([0xFF] * 7 + [0xFE])
SPECIAL_FRAMES = frozenset({ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, SET_ZERO_POSITION})

# Error codes in reply byte 7 (CubeMars firmware that sends 8-byte replies). Taken from the table in
# neurobionics/TMotorCANControl ``mit_can.py``; the CubeMars manual V1.0.8 names the byte but does
# not list the codes, so treat the texts as unverified against CubeMars' own documentation.
MOTOR_ERRORS = {
    0: "no error",
    1: "over temperature",
    2: "over current",
    3: "over voltage",
    4: "under voltage",
    5: "encoder fault",
    6: "phase current unbalance",
}

_POSITION_BITS = 16
_FIELD_BITS = 12


@dataclass(frozen=True)
class MotorLimits:
    """Float ranges of one actuator model and firmware; every field is a finite float, min < max.

    Units: position rad, velocity rad/s, torque N*m, kp N*m/rad, kd N*m*s/rad. Gains cannot be
    negative. The ranges are a property of the motor firmware, not a safety limit: they must match
    what the motor was flashed with or every value is scaled wrongly.
    """

    p_min: float
    p_max: float
    v_min: float
    v_max: float
    t_min: float
    t_max: float
    kp_min: float = 0.0
    kp_max: float = 500.0
    kd_min: float = 0.0
    kd_max: float = 5.0

    def __post_init__(self):
        for field in fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
                raise ValueError(f"MotorLimits.{field.name} must be a finite number, got {value!r}")
        for name in ("p", "v", "t", "kp", "kd"):
            low, high = getattr(self, f"{name}_min"), getattr(self, f"{name}_max")
            if not low < high:
                raise ValueError(f"MotorLimits.{name}_min must be smaller than {name}_max, "
                                 f"got {name}_min={low!r} and {name}_max={high!r}")
        for name in ("kp_min", "kd_min"):
            if getattr(self, name) < 0:
                raise ValueError(f"MotorLimits.{name} must be >= 0 (gains cannot be negative), "
                                 f"got {getattr(self, name)!r}")

    @classmethod
    def preset(cls, model: str) -> "MotorLimits":
        """The limits of a known model, by name (see ``MOTOR_PRESETS``); ValueError if unknown."""
        try:
            return MOTOR_PRESETS[model]
        except KeyError:
            raise ValueError(f"unknown motor model {model!r}; known models: "
                             f"{', '.join(sorted(MOTOR_PRESETS))}") from None


# Position +-12.5 rad, kp 0..500 and kd 0..5 for every model in the CubeMars "AK Series Actuator
# Driver Manual V1.0.8", p. 50 (table headed AK10-9, AK60-6, AK70-10, AK80-6, AK80-9, AK80-80; the
# last column is the AK80-64); velocity and torque per column as below. The same manual's own sample
# code uses P +-95.5 and V +-30 instead, and other firmware releases differ: DFKI's
# mini-cheetah-tmotor-python-can (``motor_driver/canmotorlib.py``) uses V +-22.5 for AK80-9
# firmware V1.1 and +-25.64 for V2, listed as separate presets; neurobionics/TMotorCANControl uses
# V +-50 (not +-45) for the AK60-6. Check the firmware of the actual motor before relying on these.
MOTOR_PRESETS = {
    "AK10-9": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-50.0, v_max=50.0, t_min=-65.0, t_max=65.0),
    "AK60-6": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-45.0, v_max=45.0, t_min=-15.0, t_max=15.0),
    "AK70-10": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-50.0, v_max=50.0, t_min=-25.0, t_max=25.0),
    "AK80-6": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-76.0, v_max=76.0, t_min=-12.0, t_max=12.0),
    "AK80-9": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-50.0, v_max=50.0, t_min=-18.0, t_max=18.0),
    "AK80-64": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-8.0, v_max=8.0, t_min=-144.0, t_max=144.0),
    "AK80-9-fw1.1": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-22.5, v_max=22.5,
                                t_min=-18.0, t_max=18.0),
    "AK80-9-fw2": MotorLimits(p_min=-12.5, p_max=12.5, v_min=-25.64, v_max=25.64,
                              t_min=-18.0, t_max=18.0),
}


class MotorCommand(NamedTuple):
    """A decoded command frame: position rad, velocity rad/s, kp N*m/rad, kd N*m*s/rad, torque N*m."""

    position: float
    velocity: float
    kp: float
    kd: float
    torque: float


@dataclass(frozen=True)
class MotorReply:
    """A decoded reply frame; ``temperature`` and ``error`` are None in 6-byte replies.

    ``temperature`` is byte 6 read as plain deg C, as the CubeMars manual V1.0.8 and
    TMotorCANControl do; whether newer firmware adds an offset is unverified.
    """

    motor_id: int
    position: float
    velocity: float
    torque: float
    temperature: Optional[int] = None
    error: Optional[int] = None

    @property
    def error_text(self) -> Optional[str]:
        """Human-readable error code, or None for a 6-byte reply."""
        if self.error is None:
            return None
        return MOTOR_ERRORS.get(self.error, f"unknown error code {self.error}")


def _check_finite(name: str, value: float) -> float:
    """``value`` as a float; ValueError naming ``name`` if it is NaN or infinite."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


def float_to_uint(x: float, x_min: float, x_max: float, bits: int) -> int:
    """Map ``x`` (clipped into ``[x_min, x_max]``) linearly onto ``0 .. 2**bits - 1``, truncating.

    This is the firmware's ``float_to_uint``. NaN or infinite ``x`` raises ValueError.
    """
    x = min(max(_check_finite("value", x), x_min), x_max)
    top = (1 << bits) - 1
    return min(int((x - x_min) * top / (x_max - x_min)), top)


def uint_to_float(u: int, x_min: float, x_max: float, bits: int) -> float:
    """Map ``u`` in ``0 .. 2**bits - 1`` back onto ``[x_min, x_max]`` (the firmware's inverse)."""
    top = (1 << bits) - 1
    if not 0 <= u <= top:
        raise ValueError(f"raw value {u} does not fit in {bits} bits")
    return u * (x_max - x_min) / top + x_min


def is_special_frame(data: bytes) -> bool:
    """True for the enter-motor-mode, exit-motor-mode and set-zero frames."""
    return bytes(data) in SPECIAL_FRAMES


def _pack_command(p: int, v: int, kp: int, kd: int, t: int) -> bytes:
    """Raw fields (16, 12, 12, 12, 12 bit) into the 8-byte big-endian command layout."""
    return (p << 48 | v << 36 | kp << 24 | kd << 12 | t).to_bytes(COMMAND_LENGTH, "big")


def encode_command(limits: MotorLimits, position: float, velocity: float, kp: float, kd: float,
                   torque: float) -> bytes:
    """Command frame for position (rad), velocity (rad/s), kp, kd and feed-forward torque (N*m).

    Values outside ``limits`` are clipped; NaN or infinity raises ValueError. A fully saturated
    command (maximum position, velocity, kp and kd, torque within three LSB of its maximum) would
    have the bytes of a special frame; its position is then lowered by one LSB, well inside the
    quantisation, so that the motor never mistakes a command for a mode change.
    """
    raw_p = float_to_uint(_check_finite("position", position), limits.p_min, limits.p_max,
                          _POSITION_BITS)
    raw = (float_to_uint(_check_finite("velocity", velocity), limits.v_min, limits.v_max,
                         _FIELD_BITS),
           float_to_uint(_check_finite("kp", kp), limits.kp_min, limits.kp_max, _FIELD_BITS),
           float_to_uint(_check_finite("kd", kd), limits.kd_min, limits.kd_max, _FIELD_BITS),
           float_to_uint(_check_finite("torque", torque), limits.t_min, limits.t_max, _FIELD_BITS))
    frame = _pack_command(raw_p, *raw)
    if frame in SPECIAL_FRAMES:
        frame = _pack_command(raw_p - 1, *raw)
    return frame


def torque_command(limits: MotorLimits, torque: float) -> bytes:
    """Pure feed-forward torque command (N*m): kp and kd at their minimum, zero for every preset."""
    return encode_command(limits, 0.0, 0.0, limits.kp_min, limits.kd_min, torque)


@functools.lru_cache(maxsize=64)
def _torque_fields(limits: MotorLimits) -> int:
    """The command word of a pure torque command (0 rad, 0 rad/s, the minimum gains) with its torque
    field zero (the minimum torque's)."""
    return int.from_bytes(torque_command(limits, limits.t_min), "big")


def torque_frame(limits: MotorLimits, raw_torque: int) -> bytes:
    """The pure torque command (that of :func:`torque_command`) whose 12-bit torque field is
    ``raw_torque`` (0..4095), packed without the float conversions: the frame a driver's cycle sends
    to each motor. ValueError if ``raw_torque`` does not fit."""
    if not 0 <= raw_torque <= (1 << _FIELD_BITS) - 1:
        raise ValueError(f"raw torque {raw_torque!r} does not fit in {_FIELD_BITS} bits")
    return (_torque_fields(limits) | raw_torque).to_bytes(COMMAND_LENGTH, "big")


def decode_command(limits: MotorLimits, data: bytes) -> MotorCommand:
    """Decode an 8-byte command frame (as the motor firmware does); ValueError if malformed.

    Special frames are rejected: check ``is_special_frame`` first when both can arrive.
    """
    data = bytes(data)
    if len(data) != COMMAND_LENGTH:
        raise ValueError(f"MIT command frame must be {COMMAND_LENGTH} bytes, got {len(data)}")
    if data in SPECIAL_FRAMES:
        raise ValueError(f"frame {data.hex(' ')} is a special frame, not a command")
    word = int.from_bytes(data, "big")
    mask = (1 << _FIELD_BITS) - 1
    return MotorCommand(
        position=uint_to_float(word >> 48, limits.p_min, limits.p_max, _POSITION_BITS),
        velocity=uint_to_float(word >> 36 & mask, limits.v_min, limits.v_max, _FIELD_BITS),
        kp=uint_to_float(word >> 24 & mask, limits.kp_min, limits.kp_max, _FIELD_BITS),
        kd=uint_to_float(word >> 12 & mask, limits.kd_min, limits.kd_max, _FIELD_BITS),
        torque=uint_to_float(word & mask, limits.t_min, limits.t_max, _FIELD_BITS),
    )


def _check_byte(name: str, value: int) -> int:
    """``value`` if it is an int in 0..255, else ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ValueError(f"{name} must be an integer in 0..255, got {value!r}")
    return value


def encode_reply(limits: MotorLimits, motor_id: int, position: float, velocity: float,
                 torque: float, temperature: Optional[int] = None,
                 error: Optional[int] = None) -> bytes:
    """Reply frame as a motor sends it (for the emulator); values are clipped into ``limits``.

    Without ``temperature`` and ``error`` the frame has 6 bytes; with both (deg C and error code,
    each 0..255) it has 8. Giving only one of them raises ValueError, as does NaN or infinity.
    """
    if (temperature is None) != (error is None):
        raise ValueError("give both temperature and error (8-byte reply) or neither (6-byte reply)")
    p = float_to_uint(_check_finite("position", position), limits.p_min, limits.p_max,
                      _POSITION_BITS)
    v = float_to_uint(_check_finite("velocity", velocity), limits.v_min, limits.v_max, _FIELD_BITS)
    t = float_to_uint(_check_finite("torque", torque), limits.t_min, limits.t_max, _FIELD_BITS)
    frame = bytes([_check_byte("motor_id", motor_id)]) + (p << 24 | v << 12 | t).to_bytes(5, "big")
    if temperature is None:
        return frame
    return frame + bytes([_check_byte("temperature", temperature), _check_byte("error", error)])


def decode_reply(limits: MotorLimits, data: bytes) -> MotorReply:
    """Decode a 6- or 8-byte reply frame; ValueError for any other length."""
    data = bytes(data)
    if len(data) not in REPLY_LENGTHS:
        raise ValueError(f"MIT reply frame must be 6 or 8 bytes, got {len(data)}")
    word = int.from_bytes(data[1:6], "big")
    mask = (1 << _FIELD_BITS) - 1
    return MotorReply(
        motor_id=data[0],
        position=uint_to_float(word >> 24, limits.p_min, limits.p_max, _POSITION_BITS),
        velocity=uint_to_float(word >> 12 & mask, limits.v_min, limits.v_max, _FIELD_BITS),
        torque=uint_to_float(word & mask, limits.t_min, limits.t_max, _FIELD_BITS),
        temperature=data[6] if len(data) == 8 else None,
        error=data[7] if len(data) == 8 else None,
    )
