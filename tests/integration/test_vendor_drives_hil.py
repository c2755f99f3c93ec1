"""``hil run``'s runtime drives the pybullet arm through real vendors' drive sets (issue 26).

The HIL target presents each vendor's dictionary on all six joints (sim_target/emulated/profile.py:
the maxon EPOS4's DCF with 0x6076 in µN·m, no 0x6072, no 0x1019, no 0x608F; the Nanotec C5-E's EDS
without 0x6076 and with its own 0x2101), with gears and two joints mounted against their motor;
the runtime configures them from the same files (drivers/drive_spec.py) and tracks condition C1
in lock-step. The tracking must be that of the default (emulated) drive set: per joint within
1 mrad of it, and inside the bounds test_runtime_hil.py holds the default set to.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from drivers.drive_bus import DriveBus
from hil_runtime.config import parse_runtime_config
from hil_runtime.factory import build_runtime
from sim_target.testing.hil_target import target_in_process, unique_channel
from sim_target.testing.ur5 import MAX_TORQUE_NM, NODE_IDS
from sim_target.testing.vendor_drives import VENDORS, target_profiles, vendor_bus_joints
from tests.integration.test_runtime_hil import TRACKING_BOUND_RAD, runtime_config

TRACK_CYCLES = 1500  # 1.5 s of C1 after the 2 s ramp
SAME_AS_DEFAULT_RAD = 1e-3  # per joint: the vendor set's worst error within this of the default set's


def _track(vendor: str | None) -> dict[str, Any]:
    channel = unique_channel()
    data = runtime_config({"interface": "virtual", "channel": channel})
    drives: dict[str, Any] = {"node_ids": list(NODE_IDS)}
    if vendor is not None:
        data["bus"]["joints"] = vendor_bus_joints(vendor)
        drives["profiles"] = target_profiles(vendor)
    config = parse_runtime_config(data)
    with target_in_process(channel, 0.001, drives=drives) as target:
        runtime = build_runtime(config, record_cycles=TRACK_CYCLES + 3000)
        try:
            runtime.configure()
            assert runtime.activate()
            ramp = runtime.reference.ramp_cycles
            result = runtime.run(max_cycles=ramp + TRACK_CYCLES, stop_on_fault=True)
            assert result.reason == "cycles" and result.fault is None, result.fault
            bus = runtime.bus
            assert isinstance(bus, DriveBus)
            assert target.stats.steps == bus.counters.cycles  # lock-step: one plant step per SYNC
            rec = runtime.record.arrays()
            limits = runtime.bundle.manifest.limits.model_dump()
            scales = [(node.permille_per_nm, node.counts_per_rad) for node in bus.nodes]
        finally:
            runtime.shutdown()
        assert not target.drives.operation_enabled().any()  # stopped: every joint braked
    assert np.all(np.abs(rec["q"]) <= np.asarray(limits["position_rad"]))
    assert np.all(np.abs(rec["qd"]) <= np.asarray(limits["velocity_rad_s"]))
    assert np.all(np.abs(rec["tau"]) <= np.asarray(MAX_TORQUE_NM) + 1e-9)
    np.testing.assert_allclose(np.diff(rec["t_s"]), 0.001, atol=1e-12)
    error = np.abs(rec["q"] - rec["q_ref"])[ramp:].max(axis=0)
    moved = np.ptp(rec["q"][ramp:], axis=0)
    return {"error": error, "moved": moved, "scales": scales}


@pytest.fixture(scope="module")
def default_set() -> dict[str, Any]:
    return _track(None)


@pytest.mark.parametrize("vendor", sorted(VENDORS))
def test_runtime_tracks_c1_through_the_vendors_drives_as_through_the_default_set(
    vendor: str, default_set: dict[str, Any]
) -> None:
    run = _track(vendor)
    # The figures of docs/drivers.md (python -m pytest -s tests/integration/test_vendor_drives_hil.py).
    print(f"\n{vendor}: max |q - q_ref| after the ramp (mrad): {np.round(run['error'] * 1e3, 3).tolist()}")
    print(f"default set: {np.round(default_set['error'] * 1e3, 3).tolist()}")
    assert np.all(run["error"] < TRACKING_BOUND_RAD), f"tracking error {run['error']}"
    assert np.all(run["error"] <= default_set["error"] + SAME_AS_DEFAULT_RAD), (
        f"{vendor}: {run['error']} vs the default set's {default_set['error']}"
    )
    assert np.all(run["moved"] > 0.1), run["moved"]  # C1 moved every joint
    # The vendor's scaling took effect: its units, its gears, the reversed joints (2 and 5).
    signs = [np.sign(counts) for _, counts in run["scales"]]
    assert signs == [1, -1, 1, 1, -1, 1]
    assert all(np.sign(permille) == sign for (permille, _), sign in zip(run["scales"], signs, strict=True))
