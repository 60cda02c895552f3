"""Whether each motor's velocity is read on the scale its firmware sends it with.

The MIT protocol carries a velocity as a 12-bit field scaled over the firmware's range (+-V rad/s);
one model name covers firmware releases with different ranges (the AK80-9: +-50, +-25.64 in
firmware 2, +-22.5 in firmware 1.1). Read with the wrong preset, every velocity is off by the
ratio of the two ranges, and the inner loop's derivative term with it; positions and torques share
their ranges across those releases and read right. So while a motor moves, the rate of its reported
position is compared with its reported velocity, block by block: over ``block`` seconds, the
position's change ``dp`` and the velocity's integral ``v dt``. A block counts when the position
moved at least ``min_step`` (ten position steps of the 16-bit field: quantisation and noise then
move the block's ratio by a few per cent, not by the factor two a wrong scale gives). Every
``blocks`` counted blocks, the median of their ratios ``dp / (v dt)`` is the firmware's velocity
range over the preset's (1 when they agree; 0.45 for a firmware-1.1 AK80-9 read as +-50 rad/s); two
consecutive medians outside ``[1 / tolerance, tolerance]`` make a mismatch, reported with the
preset that would fit.

The samples' times are the replies' bus stamps; a gap, a repeat or a step of that clock starts a new
block, so that the integral never spans a hole.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

from .mit_protocol import MOTOR_PRESETS, MotorLimits

BLOCK = 0.02            # s: the blocks the position change and the velocity integral are taken over
MIN_STEP = 10           # position steps (LSB of the 16-bit field) a block must move to count
BLOCKS = 8              # counted blocks per verdict
TOLERANCE = 1.25        # a ratio within [1/1.25, 1.25] is the preset's
CONFIRM = 2             # consecutive verdicts out of tolerance before a mismatch is called
MAX_GAP = 0.05          # s between two samples before the block restarts


@dataclass
class _Motor:
    """One motor's last sample, open block and the counted blocks' ratios."""
    t: float = math.nan
    p: float = math.nan
    v: float = math.nan
    block_t: float = 0.0
    block_dp: float = 0.0
    block_vdt: float = 0.0
    ratios: list = field(default_factory=list)
    ratio: float = math.nan     # the last verdict's median
    misses: int = 0             # consecutive verdicts out of tolerance


class VelocityScaleCheck:
    """The velocity scale of each motor (``models``: their ``MOTOR_PRESETS`` names, ``limits``: the
    limits the driver decodes with). :meth:`add` takes one reply; :meth:`ratios` the latest ratio
    per motor (NaN until a verdict)."""

    def __init__(self, models: Sequence[str], limits: Sequence[MotorLimits], *, block: float = BLOCK,
                 min_step: int = MIN_STEP, blocks: int = BLOCKS, tolerance: float = TOLERANCE,
                 confirm: int = CONFIRM):
        if len(models) != len(limits):
            raise ValueError(f"{len(models)} models for {len(limits)} motors")
        if not (block > 0 and min_step > 0 and blocks >= 1 and tolerance > 1 and confirm >= 1):
            raise ValueError("block, min_step and blocks must be > 0, tolerance > 1 and confirm >= 1")
        self.models, self.limits = tuple(models), tuple(limits)
        self.block, self.blocks, self.tolerance, self.confirm = block, blocks, tolerance, confirm
        self._min_dp = [min_step * (lim.p_max - lim.p_min) / 65535 for lim in limits]
        self._motors = [_Motor() for _ in models]

    def ratios(self) -> list:
        """Per motor, the last verdict's ratio of position rate to reported velocity (NaN before)."""
        return [m.ratio for m in self._motors]

    def add(self, i: int, t: float, position: float, velocity: float) -> Optional[str]:
        """Motor ``i``'s reply sampled at ``t`` [s]: position [rad], velocity [rad/s] as decoded.
        The mismatch's description when this reply confirms one, else None."""
        m = self._motors[i]
        dt = t - m.t
        if not (0.0 < dt <= MAX_GAP):        # the first sample, a gap, a repeat or a step: a new block
            m.t, m.p, m.v = t, position, velocity
            m.block_t = m.block_dp = m.block_vdt = 0.0
            return None
        m.block_dp += position - m.p
        m.block_vdt += 0.5 * (velocity + m.v) * dt
        m.block_t += dt
        m.t, m.p, m.v = t, position, velocity
        if m.block_t < self.block:
            return None
        dp, vdt = m.block_dp, m.block_vdt
        m.block_t = m.block_dp = m.block_vdt = 0.0
        if abs(dp) < self._min_dp[i]:
            return None
        m.ratios.append(dp / vdt if vdt != 0.0 else math.copysign(math.inf, dp))
        if len(m.ratios) < self.blocks:
            return None
        ordered = sorted(m.ratios)
        m.ratios.clear()
        half = len(ordered) // 2
        m.ratio = ordered[half] if len(ordered) % 2 else 0.5 * (ordered[half - 1] + ordered[half])
        if 1.0 / self.tolerance <= m.ratio <= self.tolerance:
            m.misses = 0
            return None
        m.misses += 1
        return self.describe(i) if m.misses == self.confirm else None

    def describe(self, i: int) -> str:
        """What motor ``i``'s last ratio says about its firmware."""
        ratio, model, limits = self._motors[i].ratio, self.models[i], self.limits[i]
        text = (f"its position moves at {ratio:.3g} times the velocity it reports: the preset {model} "
                f"(+-{limits.v_max:g} rad/s) is not its firmware's, which sends about "
                f"+-{abs(ratio) * limits.v_max:.3g} rad/s")
        better = fitting_preset(model, limits, ratio, self.tolerance)
        return text + (f"; the preset {better} would fit" if better else "; no preset fits")


def fitting_preset(model: str, limits: MotorLimits, ratio: float, tolerance: float = TOLERANCE
                   ) -> Optional[str]:
    """The preset of the same position range whose velocity range is nearest ``ratio`` times that
    of ``limits`` (the firmware's, seen through the wrong preset), within ``tolerance``; None if
    none is. Among those, one of the same model family (``AK80-9`` for ``AK80-9-fw2``) first."""
    if not (math.isfinite(ratio) and ratio > 0):
        return None
    wanted = ratio * limits.v_max
    family = model.split("-fw")[0]
    best = None
    for name, preset in MOTOR_PRESETS.items():
        if (preset.p_min, preset.p_max) != (limits.p_min, limits.p_max):
            continue
        error = abs(math.log(preset.v_max / wanted))
        if error > math.log(tolerance) or name == model:
            continue
        key = (name.split("-fw")[0] != family, error)
        if best is None or key < best[0]:
            best = (key, name)
    return None if best is None else best[1]
