"""Per-joint scaling between SI units and the drive's integer objects.

Torque objects (0x6071 target, 0x6077 actual, 0x6072 max) are INTEGER16 per-mille of the rated
torque 0x6076 (UNSIGNED32, mN·m). The resolution is therefore rated/1000: a 150 N·m joint with a
rated torque of 150 N·m would move in 0.15 N·m steps, too coarse for a learned feedback law, so the
rated torque is chosen per joint (:func:`rated_torque_for_resolution`) to make the step small while
the maximum torque still fits the INTEGER16 range.

Position 0x6064 is INTEGER32 encoder counts; velocity 0x606C is INTEGER32 counts per second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

INT16_MAX: Final = 32767
INT32_MAX: Final = 2**31 - 1


@dataclass(frozen=True, slots=True)
class JointScaling:
    counts_per_rad: float  # encoder counts per joint radian
    rated_torque_mnm: int  # 0x6076: 1000 ‰ equals this many mN·m

    @property
    def torque_resolution_nm(self) -> float:
        return self.rated_torque_mnm * 1e-6

    @property
    def permille_per_nm(self) -> float:
        return 1e6 / self.rated_torque_mnm

    def max_representable_torque_nm(self) -> float:
        return INT16_MAX / self.permille_per_nm

    def torque_to_permille(self, torque_nm: float) -> int:
        """Rounded and saturated to INTEGER16 (callers clip to the max torque first)."""
        value = round(torque_nm * self.permille_per_nm)
        return max(-INT16_MAX, min(INT16_MAX, value))

    def permille_to_torque(self, permille: int) -> float:
        return permille / self.permille_per_nm

    def rad_to_counts(self, position_rad: float) -> int:
        return max(-INT32_MAX, min(INT32_MAX, round(position_rad * self.counts_per_rad)))

    def counts_to_rad(self, counts: int) -> float:
        return counts / self.counts_per_rad


def counts_per_rad_from_resolution(increments_per_rev: int, revolutions: int = 1) -> float:
    """From 0x608F (position encoder resolution: increments / motor revolutions), joint side."""
    if increments_per_rev <= 0 or revolutions <= 0:
        raise ValueError("encoder resolution must be positive")
    return increments_per_rev / (revolutions * 2.0 * math.pi)


def rated_torque_for_resolution(max_torque_nm: float, resolution_nm: float) -> int:
    """Rated torque (mN·m, for 0x6076) giving at most ``resolution_nm`` per ‰ step.

    Raises ValueError when no rated torque gives that resolution while ``max_torque_nm`` still
    fits the INTEGER16 per-mille range.
    """
    if max_torque_nm <= 0 or resolution_nm <= 0:
        raise ValueError("max torque and resolution must be positive")
    rated_mnm = max(1, math.floor(resolution_nm * 1e6))
    if max_torque_nm * 1e6 / rated_mnm > INT16_MAX:
        finest_nm = math.ceil(max_torque_nm * 1e6 / INT16_MAX) * 1e-6
        raise ValueError(
            f"a max torque of {max_torque_nm} N·m in INTEGER16 ‰ allows at best "
            f"{finest_nm:.2e} N·m resolution, not {resolution_nm:.2e}"
        )
    return rated_mnm


def check_torque_range(max_torque_nm: float, rated_torque_mnm: int) -> None:
    """ValueError if the max torque does not fit INTEGER16 ‰ (0x6071) or UNSIGNED16 ‰ (0x6072)."""
    permille = max_torque_nm * 1e6 / rated_torque_mnm
    if permille > INT16_MAX:
        need = math.ceil(max_torque_nm * 1e6 / INT16_MAX)
        raise ValueError(
            f"max torque {max_torque_nm} N·m is {permille:.0f} ‰ of a rated "
            f"{rated_torque_mnm} mN·m, above the INTEGER16 limit {INT16_MAX}; "
            f"use a rated torque of at least {need} mN·m"
        )
