"""The driver against the emulated CiA 402 drives on python-can's in-process virtual bus.

Every fault (malformed frame, lost/late/corrupt TPDO, heartbeat loss, SDO abort, drive fault) must
be counted and reported through a typed exception or the feedback, never crash or hang.
"""

from __future__ import annotations

from collections.abc import Iterator

import can
import numpy as np
import pytest

from drivers.bus_guard import BusIntruderError
from drivers.cia402.state_machine import State
from drivers.errors import (
    DriveCommandError,
    DriveConfigError,
    DriveFaultError,
    DriveStateError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    SdoAbortError,
)
from sim_target.drives import FrameFaults
from sim_target.testing.drive_rig import Rig, make_rig, wait_until


@pytest.fixture(params=[False, True], ids=["classical", "fd"])
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    rig = make_rig(fd=request.param, feedback_timeout_s=0.2)
    yield rig
    rig.close()


def _expected_position(torque_nm: float, inertia: float, period_s: float, cycles: int) -> float:
    # Fake plant: semi-implicit Euler from rest, torque applied from the first enabled SYNC on.
    return period_s**2 * torque_nm / inertia * cycles * (cycles + 1) / 2


def test_lockstep_exchange_moves_the_plant(rig: Rig) -> None:
    bus, plant = rig.driver, rig.plant
    bus.enable()
    assert bus.states == (State.OPERATION_ENABLED,) * 6
    assert not rig.drives.brake_engaged().any()
    torque = np.array([1.0, -2.0, 0.5, 3.0, -0.25, 0.0])
    steps_before = plant.steps
    cycles = 50
    for _ in range(cycles):
        feedback = bus.exchange(torque)
    assert plant.steps - steps_before == cycles  # lock-step: one SYNC, one period
    expected = _expected_position(1.0, plant.inertia_kg_m2, plant.period_s, cycles) * torque
    resolution = 1 / bus.counts_per_rad[0]
    np.testing.assert_allclose(feedback.position_rad, expected, atol=resolution)
    np.testing.assert_allclose(feedback.position_rad, plant.state().position_rad, atol=resolution)
    np.testing.assert_allclose(feedback.velocity_rad_s, plant.state().velocity_rad_s, atol=resolution)
    np.testing.assert_allclose(feedback.torque_nm, torque, atol=0.005)
    assert feedback.fresh.all()
    assert (feedback.rx_time_s >= feedback.sync_time_s).all()
    counters = bus.counters
    assert counters.dropped == counters.late == counters.malformed == 0


def test_setpoints_are_clipped_and_quantised(rig: Rig) -> None:
    rig.driver.enable()
    feedback = rig.driver.exchange(np.array([1000.0, -1000.0, 0.0012, 0.0037, 0, 0]))
    np.testing.assert_allclose(feedback.commanded_torque_nm[:4], [150.0, -150.0, 0.0, 0.005])
    np.testing.assert_allclose(rig.drives.commanded_torque_nm()[:4], [150.0, -150.0, 0.0, 0.005])


def test_bad_setpoints_are_refused_before_the_bus() -> None:
    rig = make_rig(n=2)
    try:
        with pytest.raises(DriveStateError, match="enable"):
            rig.driver.exchange(np.zeros(2))
        rig.driver.enable()
        sent = rig.driver.counters.frames_sent
        with pytest.raises(DriveCommandError, match=r"drive\(s\) \[2\]"):
            rig.driver.exchange(np.array([0.0, np.nan]))
        with pytest.raises(DriveCommandError, match="shape"):
            rig.driver.exchange(np.zeros(3))
        assert rig.driver.counters.frames_sent == sent
    finally:
        rig.close()


def test_malformed_frames_are_counted_on_both_ends() -> None:
    rig = make_rig(n=2)
    intruder = can.Bus(interface="virtual", channel=rig.config.transport.channel, ignore_config=True)
    try:
        rig.driver.enable()
        junk = [
            can.Message(arbitration_id=0x181, data=b"\x27\x00\x00", is_extended_id=False),  # short TPDO1
            can.Message(arbitration_id=0x281, data=bytes(8), is_extended_id=False),  # long TPDO2
            can.Message(arbitration_id=0x182, data=bytes.fromhex("6100000000000000"), is_extended_id=False),
            can.Message(arbitration_id=0x701, data=b"\x06", is_extended_id=False),  # no such NMT state
            can.Message(arbitration_id=0x081, data=b"\x10\x23", is_extended_id=False),  # short EMCY
            can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=True),  # extended id
            can.Message(arbitration_id=0x3FF, data=b"\x00", is_extended_id=False),  # nobody's COB-ID
            can.Message(arbitration_id=0x201, data=b"\x0f\x00\x10", is_extended_id=False),  # short RPDO
            can.Message(arbitration_id=0x080, data=b"\x01\x02", is_extended_id=False),  # 2-byte SYNC
            can.Message(arbitration_id=0x000, data=b"\x01", is_extended_id=False),  # short NMT
        ]
        for msg in junk:
            intruder.send(msg)
        # Driver: the first six; the drives: extended id, short RPDO, 2-byte SYNC, short NMT.
        assert wait_until(lambda: rig.driver.counters.malformed >= 6 and rig.drives.counters.malformed >= 4)
        assert rig.driver.counters.malformed == 6
        assert rig.drives.counters.malformed == 4
        assert rig.driver.counters.unknown_cob_id == 4  # 0x3FF and the master-to-drive frames
        # Frames only a master sends, and a drive's frames from someone else: not junk to count
        # and forget but a second master and a second sender (drivers/bus_guard.py): FAULT.
        with pytest.raises(BusIntruderError, match="second (master on the bus|sender of)"):
            rig.driver.exchange(np.ones(2))
        assert not rig.driver.enabled
    finally:
        intruder.shutdown()
        rig.close()


def test_lost_tpdo_is_counted_then_raises_after_max_missed(rig: Rig) -> None:
    bus = rig.driver
    bus.enable()
    bus.exchange(np.zeros(6))
    rig.drives.drop_tpdos(3, cycles=1)
    feedback = bus.exchange(np.zeros(6))  # one miss is tolerated (max_missed_cycles = 1)...
    assert feedback.fresh.tolist() == [True, True, False, True, True, True]
    per_drive = 1 if rig.config.transport.fd else 2
    assert bus.counters.dropped == per_drive
    assert bus.exchange(np.zeros(6)).fresh.all()
    rig.drives.drop_tpdos(3, cycles=2)
    bus.exchange(np.zeros(6))
    with pytest.raises(FeedbackTimeoutError, match=r"drive\(s\) 3 for 2 consecutive") as info:
        bus.exchange(np.zeros(6))  # ...two in a row are reported: within two cycles
    assert info.value.node_ids == (3,)
    assert bus.counters.dropped == 3 * per_drive


def test_late_tpdo_is_counted_as_late(rig: Rig) -> None:
    bus = rig.driver
    bus.enable()
    rig.drives.delay_tpdos(2, delay_s=0.4, cycles=1)  # beyond the 0.2 s feedback timeout
    feedback = bus.exchange(np.zeros(6))
    assert not feedback.fresh[1]
    per_drive = 1 if rig.config.transport.fd else 2
    assert wait_until(lambda: bus.counters.late == per_drive)
    assert bus.exchange(np.zeros(6)).fresh.all()
    assert bus.counters.late == per_drive and bus.counters.dropped == per_drive


def test_corrupt_tpdo_is_malformed_not_fresh(rig: Rig) -> None:
    bus = rig.driver
    bus.enable()
    rig.drives.corrupt_tpdos(4, cycles=1)
    feedback = bus.exchange(np.zeros(6))
    assert not feedback.fresh[3]
    per_drive = 1 if rig.config.transport.fd else 2
    assert bus.counters.malformed == per_drive
    assert rig.drives.counters.corrupted_injected == per_drive


def test_random_frame_faults_at_run_time_are_all_accounted_for() -> None:
    rig = make_rig(n=3, feedback_timeout_s=0.1, max_missed_cycles=1000, heartbeat_timeout_s=5.0)
    try:
        rig.driver.enable()
        rig.drives.apply_fault(_FrameFault(node_ids=(1, 2, 3), drop_probability=0.05, corrupt_probability=0.05, seed=7))
        for _ in range(100):
            rig.driver.exchange(np.zeros(3))
        rig.drives.apply_fault(_FrameFault(node_ids=None))  # probabilities 0: faults off
        injected = rig.drives.counters
        assert injected.dropped_injected > 0 and injected.corrupted_injected > 0
        assert wait_until(lambda: rig.driver.counters.malformed == injected.corrupted_injected)
        counters = rig.driver.counters
        # Heartbeats are faulted too, so TPDO losses are bounded by, not equal to, the injections.
        assert 0 < counters.dropped <= injected.dropped_injected + injected.corrupted_injected
        assert counters.late == 0
        assert rig.driver.exchange(np.zeros(3)).fresh.all()
    finally:
        rig.close()


def test_frame_faults_from_config_apply_from_boot() -> None:
    """Every frame dropped from the start: connect fails fast with a typed error naming the drive."""
    with pytest.raises(DriveStateError, match=r"drive\(s\) 1: no boot-up"):
        make_rig(n=1, state_change_timeout_s=0.2, emulated={"frame_faults": _faults(drop=1.0, corrupt=0.0, seed=0)})


def test_heartbeat_loss_raises_typed_error() -> None:
    rig = make_rig(n=3, heartbeat_producer_ms=10, heartbeat_timeout_s=0.2)
    try:
        rig.driver.enable()
        rig.drives.silence_heartbeat(2)
        with pytest.raises(HeartbeatLostError, match="drive 2: no heartbeat") as info:
            for _ in range(10_000):  # 40 s of cycles at most: the error comes after ~0.2 s
                rig.driver.exchange(np.zeros(3))
        assert info.value.node_id == 2
        assert not rig.driver.enabled
    finally:
        rig.close()


def test_sdo_abort_codes_reach_the_caller() -> None:
    rig = make_rig(n=1)
    try:
        with pytest.raises(SdoAbortError, match="0x06090030") as info:
            rig.driver.sdo_write(1, 0x6060, 0, 3)  # profile position: not emulated
        assert info.value.code == 0x06090030 and info.value.exit_code == 3
        with pytest.raises(SdoAbortError, match="object does not exist") as info:
            rig.driver.sdo_read(1, 0x2000, 0)
        assert info.value.code == 0x06020000
        with pytest.raises(SdoAbortError, match="read only"):
            rig.driver.sdo_write(1, 0x6041, 0, 0)
        with pytest.raises(SdoAbortError) as info:
            rig.driver.sdo_write(1, 0x1A00, 1, 0x60FF0010)  # TPDO1 is valid: cannot remap now
        assert info.value.code == 0x08000022
        assert rig.driver.sdo_read_int(1, 0x6076) == 5000  # what connect() configured
    finally:
        rig.close()


def test_drive_fault_is_reported_with_its_emcy_code_then_reset(rig: Rig) -> None:
    bus = rig.driver
    bus.enable()
    bus.exchange(np.zeros(6))
    rig.drives.inject_drive_fault(2, 0x4310)
    with pytest.raises(DriveFaultError) as info:
        for _ in range(2):  # within two cycles
            bus.exchange(np.zeros(6))
    assert (info.value.node_id, info.value.code) == (2, 0x4310)
    assert bus.counters.emcy >= 1
    assert rig.drives.brake_engaged()[1]
    states = bus.quick_stop()
    assert states[1] is State.FAULT
    with pytest.raises(DriveFaultError, match="fault_reset"):
        bus.enable()
    bus.fault_reset()
    bus.enable()
    assert bus.exchange(np.ones(6)).fresh.all()


def test_quick_stop_and_disable_brake_every_joint(rig: Rig) -> None:
    bus = rig.driver
    bus.enable()
    bus.exchange(np.ones(6))
    assert bus.quick_stop() == (State.QUICK_STOP_ACTIVE,) * 6  # 0x605A = 2 ends in SOD next
    assert rig.drives.brake_engaged().all()
    assert not rig.drives.commanded_torque_nm().any()
    assert bus.disable() == (State.SWITCH_ON_DISABLED,) * 6
    with pytest.raises(DriveStateError):
        bus.exchange(np.ones(6))
    bus.enable()
    bus.exchange(np.ones(6))


def test_missing_drive_fails_connect_with_its_node_id() -> None:
    with pytest.raises(DriveStateError, match=r"drive\(s\) 3: no boot-up"):
        make_rig(n=3, drive_ids=(1, 2), state_change_timeout_s=0.2)


def test_encoder_resolution_mismatch_is_a_config_error() -> None:
    joints = [{"name": "a", "node_id": 1, "max_torque_nm": 10.0, "encoder_counts_per_rev": 4096}]
    with pytest.raises(DriveConfigError, match="joints.0.encoder_counts_per_rev: 4096 but drive 1"):
        make_rig(n=1, joints=joints)


def test_drive_reboot_is_reported() -> None:
    rig = make_rig(n=2)
    intruder = can.Bus(interface="virtual", channel=rig.config.transport.channel, ignore_config=True)
    try:
        rig.driver.enable()
        # Drive 2's boot-up message, as after a power cycle (an NMT reset from here would be a
        # second master, drivers/bus_guard.py, refused before the drive could reboot).
        intruder.send(can.Message(arbitration_id=0x702, data=b"\x00", is_extended_id=False))
        with pytest.raises(DriveStateError, match="drive 2: rebooted"):
            for _ in range(100):
                rig.driver.exchange(np.zeros(2))
    finally:
        intruder.shutdown()
        rig.close()


# --- helpers ---------------------------------------------------------------------------------------


class _FrameFault:
    """Duck-typed sim_target.config.FrameFault (kind "frames")."""

    kind = "frames"

    def __init__(
        self,
        node_ids: tuple[int, ...] | None,
        drop_probability: float = 0.0,
        corrupt_probability: float = 0.0,
        delay_s: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.node_ids = node_ids
        self.drop_probability = drop_probability
        self.corrupt_probability = corrupt_probability
        self.delay_s = delay_s
        self.seed = seed


def _faults(drop: float, corrupt: float, seed: int) -> FrameFaults:
    return FrameFaults(drop_probability=drop, corrupt_probability=corrupt, seed=seed)
