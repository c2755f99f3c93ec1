"""An emulated drive presenting a real vendor's object dictionary (its EDS or DCF), with the motor
and mechanics behind it that the dictionary alone does not say: the motor's rated torque in the
vendor's unit of 0x6076, the encoder's increments, the gear ratio and the mounting polarity.

The drive then answers SDO reads from that dictionary (its device type, identity, supported modes,
defaults, access rights), refuses writes its EDS marks read-only, and scales its PDOs as that
drive would: torque in per mille of *its* rated torque, position in *its* increments through
*its* gear. The emulated drive's own manufacturer objects (0x2100 SYNC counter echo, 0x2101 SYNC
timeout) are not there: on a vendor's drive those indices mean something else.

In a target config (``hil target serve``), one entry per joint::

    drives:
      profiles:
        - {eds: tests/data/eds/maxon_epos4_50_15.dcf, rated_torque: 512871, rated_torque_unit_nm: 1.0e-6,
           encoder_increments: 4096, gear_ratio: 100, polarity: -1}
        - ...
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import Field, ValidationInfo, field_validator

from drivers.strict_input import StrictModel, config_relative_path


class DriveProfile(StrictModel):
    """What an emulated vendor drive is: its dictionary and the motor behind it."""

    eds: Path  # the vendor's EDS or DCF
    rated_torque: int = Field(gt=0)  # the motor's 0x6076, in the vendor's unit (where the EDS has none or 0)
    rated_torque_unit_nm: float = Field(1e-3, gt=0)  # one unit of 0x6076 in N·m (CiA 402: mN·m)
    encoder_increments: int = Field(4096, gt=0)  # per motor revolution (0x608F:01 where the EDS has it)
    gear_ratio: float = Field(1.0, gt=0)  # motor revolutions per joint revolution
    polarity: int = Field(1, ge=-1, le=1)  # -1: the joint turns against the motor
    device_type: int | None = Field(None, ge=0, le=0xFFFFFFFF)  # answer 0x1000 with this instead

    @field_validator("eds", mode="after")
    @classmethod
    def _resolve(cls, value: Path, info: ValidationInfo) -> Path:
        return config_relative_path(value, info)

    @field_validator("polarity")
    @classmethod
    def _sign(cls, value: int) -> int:
        if value not in (1, -1):
            raise ValueError("polarity must be 1 or -1")
        return value

    @property
    def counts_per_rad(self) -> float:
        """0x6064 increments per joint radian, signed by the polarity."""
        return self.polarity * self.encoder_increments * self.gear_ratio / (2.0 * math.pi)

    @property
    def joint_nm_per_unit_permille(self) -> float:
        """N·m at the joint per (per mille x one unit of 0x6076), signed by the polarity."""
        return self.polarity * self.rated_torque_unit_nm * self.gear_ratio / 1000.0
