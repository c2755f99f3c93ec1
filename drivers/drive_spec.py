"""Per-drive configuration: a real CiA 402 drive described by its own EDS/DCF (in the spirit of
ros2_canopen's ``bus.yml``: a DCF per node, an SDO initialisation list, scaling, reactions).

One joint of ``bus.joints`` with a ``drive`` section::

    - name: shoulder_pan_joint
      node_id: 1
      max_torque_nm: 102.0
      drive:
        eds: drives/maxon_epos4_50_15.dcf   # EDS or DCF; relative to the config file
        rated_torque: drive                # 0x6076 read from the drive at start-up, or a number
        rated_torque_unit_nm: 1.0e-6       # what one unit of 0x6076 is (CiA 402: mN·m; maxon: µN·m)
        encoder_increments: 4096           # per motor revolution; "drive": 0x608F:01 / 0x608F:02
        gear_ratio: 160.0                  # motor revolutions per joint revolution; "drive": 0x6091
        polarity: -1                       # the joint turns against the motor: every sign flipped
        zero_offset_rad: 0.0               # joint angle = drive angle - zero offset
        interpolation_period: true         # write 0x60C2 = the control period (ms, index -3)
        reactions: {quick_stop: 2, fault: 0, abort_connection: 3}   # 0x605A, 0x605E, 0x6007
        sdo:                               # written in order, after the runtime's own objects
          - {index: 0x3001, sub_index: 2, value: 10000}

Scaling (the drive's integer objects <-> the joint's SI units):

- torque: 0x6071/0x6077 are INTEGER16 per mille of 0x6076 (the *motor's* rated torque), so one
  per mille is ``rated_torque * rated_torque_unit_nm * gear_ratio / 1000`` N·m at the joint;
- position: 0x6064 counts ``encoder_increments * gear_ratio`` per joint revolution: the runtime
  takes positions in encoder increments (a drive applying the CiA 402 factor group divides them by
  0x6092 feed constant: set it to 1/1 with ``sdo`` entries); velocity 0x606C in increments/s;
- polarity -1 flips torque, position and velocity at the master (0x607E is the drive's own flag:
  leave it as the drive's commissioning tool set it, or put it in ``sdo``).

Validated offline against the EDS by :mod:`drivers.eds_check` before anything is written to a
drive; the values read from the drive are checked again at start-up (:mod:`drivers.commissioning`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from drivers.strict_input import StrictModel, config_relative_path

FromDrive = Literal["drive"]


class _Frozen(StrictModel):
    """Frozen, no unknown fields, no .inf/.nan, no ``true`` or ``"1"`` read as a number."""


class SdoInit(_Frozen):
    """One entry of the SDO initialisation list (ros2_canopen's ``sdo: [{index, sub_index, value}]``)."""

    index: int = Field(ge=0x1000, le=0xFFFF)
    sub_index: int = Field(0, ge=0, le=0xFF)
    value: int


class Reactions(_Frozen):
    """CiA 402 reactions written at start-up; None leaves the drive's own setting."""

    quick_stop: int | None = Field(None, ge=-32768, le=32767)  # 0x605A quick stop option code
    fault: int | None = Field(None, ge=-32768, le=32767)  # 0x605E fault reaction option code
    abort_connection: int | None = Field(None, ge=-32768, le=32767)  # 0x6007 abort connection option


class DriveSpec(_Frozen):
    """One joint's real drive: its dictionary, scaling, reactions and SDO initialisation list."""

    eds: Path  # the drive's EDS or DCF
    rated_torque: float | FromDrive = "drive"  # 0x6076 in its own unit; "drive": read at start-up
    rated_torque_unit_nm: float = Field(1e-3, gt=0)  # CiA 402: mN·m (1e-3); maxon EPOS4: µN·m (1e-6)
    encoder_increments: float | FromDrive = "drive"  # per motor revolution (0x608F:01 / :02)
    gear_ratio: float | FromDrive = 1.0  # motor revolutions per joint revolution (0x6091:01 / :02)
    polarity: Literal[1, -1] = 1
    zero_offset_rad: float = 0.0
    interpolation_period: bool = True  # write 0x60C2 (the control period) where the EDS has it
    reactions: Reactions = Reactions()
    sdo: tuple[SdoInit, ...] = ()

    @field_validator("rated_torque", "encoder_increments", "gear_ratio", mode="before")
    @classmethod
    def _number_or_drive(cls, value: object) -> object:
        # StrictModel cannot tell a YAML boolean from a number behind the Literal alternative.
        if isinstance(value, bool) or (isinstance(value, str) and value != "drive"):
            raise ValueError(f"expected a number or 'drive', got {value!r}")
        return value

    @field_validator("eds", mode="after")
    @classmethod
    def _resolve(cls, value: Path, info: ValidationInfo) -> Path:
        return config_relative_path(value, info)

    @model_validator(mode="after")
    def _check(self) -> DriveSpec:
        for name in ("rated_torque", "encoder_increments", "gear_ratio"):
            value = getattr(self, name)
            if value != "drive" and (not math.isfinite(value) or value <= 0):
                raise ValueError(f"{name} must be a positive finite number or 'drive'")
        if not math.isfinite(self.zero_offset_rad):
            raise ValueError("zero_offset_rad must be finite")
        return self


class DriveScale:
    """The numbers the master needs to convert one drive's integers: built once at start-up from
    the spec and what the drive reported (``"drive"`` entries)."""

    __slots__ = ("counts_per_rad", "nm_per_permille", "zero_offset_rad")

    def __init__(
        self,
        rated_torque: float,
        rated_torque_unit_nm: float,
        encoder_increments: float,
        gear_ratio: float,
        polarity: int,
        zero_offset_rad: float,
    ) -> None:
        # Signed: polarity -1 flips every conversion (torque, position and velocity) at once.
        self.nm_per_permille = polarity * rated_torque * rated_torque_unit_nm * gear_ratio / 1000.0
        self.counts_per_rad = polarity * encoder_increments * gear_ratio / (2.0 * math.pi)
        self.zero_offset_rad = zero_offset_rad

    @property
    def permille_per_nm(self) -> float:
        return 1.0 / self.nm_per_permille


def spec_scale(spec: DriveSpec, read: dict[str, float]) -> DriveScale:
    """The spec's scaling with its ``"drive"`` entries taken from ``read`` (values from the drive)."""

    def pick(name: str) -> float:
        value = getattr(spec, name)
        return float(read[name]) if value == "drive" else float(value)

    return DriveScale(
        pick("rated_torque"),
        spec.rated_torque_unit_nm,
        pick("encoder_increments"),
        pick("gear_ratio"),
        spec.polarity,
        spec.zero_offset_rad,
    )
