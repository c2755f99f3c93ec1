"""Drive sets of real vendors for ur5_paper's six joints: the emulated drives present each vendor's
EDS/DCF (tests/data/eds, see its README) with a plausible motor and gear behind it, and the
runtime's ``bus.joints`` configure them from the same files. One table, shared by the tests, the
benchmarks and docs/drivers.md.

- ``maxon_epos4``: maxon EPOS4 50/15 (its DCF for an EC 90 flat motor, GP 52 C gear, MILE encoder):
  0x6076 is in µN·m and read from the drive; encoder and gear given (the EPOS4 has no 0x608F/0x6091
  in its dictionary); two joints mounted against their motor (polarity -1); no 0x6072.
- ``nanotec_c5``: Nanotec C5-E-2-09: no 0x6076 in its dictionary (the rated torque is given, in
  mN·m); encoder resolution 0x608F and gear 0x6091 read from the drive; no consumer-heartbeat
  needed beyond 0x1016.

Light: no pybullet, no runtime imports.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sim_target.testing.ur5 import bus_joints

EDS_DIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "eds"
MAXON_EPOS4_DCF = EDS_DIR / "maxon_epos4_50_15.dcf"
NANOTEC_C5_EDS = EDS_DIR / "nanotec_c5_e_2_09.eds"

# Per joint: (gear ratio, polarity). Large joints through a 160:1 gear, the wrist through 100:1.
_GEARS = (160.0, 160.0, 160.0, 100.0, 100.0, 100.0)
_POLARITY = (1, -1, 1, 1, -1, 1)

VENDORS: dict[str, dict[str, Any]] = {
    "maxon_epos4": {
        "eds": MAXON_EPOS4_DCF,
        "rated_torque": 512_871,  # the DCF's own 0x6076 for its EC 90 flat: µN·m
        "rated_torque_unit_nm": 1e-6,
        "encoder_increments": 3200,  # MILE 800 counts per turn, quadrature
        "runtime": {"rated_torque": "drive", "encoder_increments": 3200},
    },
    "nanotec_c5": {
        "eds": NANOTEC_C5_EDS,
        "rated_torque": 440,  # mN·m (a DB87 class motor); the C5-E has no 0x6076
        "rated_torque_unit_nm": 1e-3,
        "encoder_increments": 4000,
        "runtime": {"rated_torque": 440, "encoder_increments": "drive", "gear_ratio": "drive"},
    },
}


def target_profiles(vendor: str) -> list[dict[str, Any]]:
    """The target config's ``drives.profiles``: the vendor's dictionary with the motor behind it."""
    v = VENDORS[vendor]
    return [
        {
            "eds": str(v["eds"]),
            "rated_torque": v["rated_torque"],
            "rated_torque_unit_nm": v["rated_torque_unit_nm"],
            "encoder_increments": v["encoder_increments"],
            "gear_ratio": gear,
            "polarity": polarity,
        }
        for gear, polarity in zip(_GEARS, _POLARITY, strict=True)
    ]


def vendor_bus_joints(vendor: str) -> list[dict[str, Any]]:
    """The runtime's ``bus.joints`` for the vendor's drives: each with its ``drive`` section."""
    v = VENDORS[vendor]
    joints = bus_joints()
    for joint, gear, polarity in zip(joints, _GEARS, _POLARITY, strict=True):
        drive: dict[str, Any] = {
            "eds": str(v["eds"]),
            "rated_torque_unit_nm": v["rated_torque_unit_nm"],
            "gear_ratio": gear,
            "polarity": polarity,
            "reactions": {"quick_stop": 2, "fault": 0, "abort_connection": 3},
        }
        drive.update(v["runtime"])
        joint["drive"] = drive
    return joints


__all__ = ["EDS_DIR", "MAXON_EPOS4_DCF", "NANOTEC_C5_EDS", "VENDORS", "target_profiles", "vendor_bus_joints"]
