"""The cyclic path of the driver against the emulated drives (fake plant, in-process virtual bus):
holding torque at enable, heartbeat deadlines checked every cycle, the safe state after any
run-time error, stale feedback never used as fresh, the feedback timeout and miss budget.

Everything is counted in cycles; the only clocks are the driver's own timeouts (generous here).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.bus_guard import BusIntruderError
from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import State
from drivers.config import DriveBusConfig
from drivers.errors import (
    DriveCommandError,
    DriveError,
    DriveFaultError,
    DriveStateError,
    FeedbackTimeoutError,
    HeartbeatLostError,
)
from sim_target.testing.drive_rig import Rig, make_rig, wait_until

SAFE_STATES = {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED, State.FAULT}


@pytest.fixture(params=[False, True], ids=["classical", "fd"])
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    rig = make_rig(n=3, fd=request.param, feedback_timeout_s=0.2)
    yield rig
    rig.close()


# --- (a) enable(hold_torque_nm) -------------------------------------------------------------------


def test_enable_applies_the_holding_torque_from_the_first_enabled_period(rig: Rig) -> None:
    hold = np.array([2.0, -1.0, 0.5])
    steps_before = rig.plant.steps
    feedback = rig.driver.enable(hold_torque_nm=hold)
    assert feedback.states == (State.OPERATION_ENABLED,) * 3
    # The drives applied the holding torque in the period they entered Operation Enabled: the
    # measured torque of that cycle is it, and the (gravity-free) plant already accelerated.
    np.testing.assert_allclose(feedback.torque_nm, hold, atol=0.005)
    np.testing.assert_allclose(feedback.commanded_torque_nm, hold, atol=0.005)
    assert rig.plant.steps > steps_before
    velocity = rig.plant.state().velocity_rad_s
    assert (np.sign(velocity) == np.sign(hold)).all()
    enabled_periods = round(velocity[0] * rig.plant.inertia_kg_m2 / (hold[0] * rig.plant.period_s))
    assert enabled_periods >= 1
    np.testing.assert_allclose(velocity, hold / rig.plant.inertia_kg_m2 * rig.plant.period_s * enabled_periods)


def test_enable_without_hold_torque_leaves_the_joints_unpowered(rig: Rig) -> None:
    feedback = rig.driver.enable()
    np.testing.assert_array_equal(feedback.torque_nm, 0.0)
    np.testing.assert_array_equal(rig.plant.state().velocity_rad_s, 0.0)


def test_enable_refuses_a_bad_holding_torque_before_the_bus(rig: Rig) -> None:
    sent = rig.driver.counters.frames_sent
    with pytest.raises(DriveCommandError, match="hold_torque_nm has shape"):
        rig.driver.enable(hold_torque_nm=np.zeros(2))
    with pytest.raises(DriveCommandError, match="non-finite"):
        rig.driver.enable(hold_torque_nm=np.array([0.0, np.inf, 0.0]))
    assert rig.driver.counters.frames_sent == sent
    assert not rig.driver.enabled


# --- (b) heartbeat deadlines on every cycle --------------------------------------------------------


def test_heartbeat_loss_is_reported_within_two_cycles_of_its_deadline_at_full_rate() -> None:
    """Unpaced cycles (thousands a second with the fake plant): the consumer deadline must be
    checked by the cycles themselves, not by a poll every few milliseconds."""
    rig = make_rig(n=3, fd=True, heartbeat_producer_ms=10, heartbeat_timeout_s=0.05, feedback_timeout_s=0.2)
    bus = rig.driver
    try:
        bus.enable()
        rig.drives.silence_heartbeat(2)
        deadlines: list[float] = []
        starts: list[float] = []
        error: DriveError | None = None
        for _ in range(200_000):  # bounded; the error comes after ~0.05 s of cycles
            deadlines.append(bus.nodes[1].last_heartbeat_s + bus.config.heartbeat_timeout_s)
            starts.append(bus._network.last_cycle_end_s)
            try:
                bus.exchange(np.zeros(3))
            except DriveError as exc:
                error = exc
                break
        assert isinstance(error, HeartbeatLostError), repr(error)
        assert error.node_id == 2
        # Cycles that began after the deadline the driver itself knew at that time.
        late_cycles = sum(1 for start, deadline in zip(starts, deadlines, strict=True) if start > deadline)
        assert late_cycles <= 2, f"reported {late_cycles} cycles after the heartbeat deadline"
        assert len(starts) > 2
    finally:
        rig.close()


# --- (c) the safe state after any run-time error ---------------------------------------------------


def _inject(rig: Rig, kind: str) -> type[DriveError]:
    if kind == "feedback-timeout":
        rig.drives.drop_tpdos(2, cycles=1_000_000)
        return FeedbackTimeoutError
    if kind == "drive-fault":
        rig.drives.inject_drive_fault(2, 0x2310)
        return DriveFaultError
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["feedback-timeout", "drive-fault"])
def test_runtime_error_quick_stops_every_drive_and_disables_the_bus(rig: Rig, kind: str) -> None:
    bus = rig.driver
    bus.enable()
    for _ in range(3):
        bus.exchange(np.ones(3))
    expected = _inject(rig, kind)
    with pytest.raises(expected):
        for _ in range(5):
            bus.exchange(np.ones(3))
    assert not bus.enabled
    # Every drive, the silent one included (it still receives its RPDOs), is braked.
    assert set(rig.drives.states()) <= SAFE_STATES, rig.drives.states()
    assert rig.drives.brake_engaged().all()
    assert not rig.drives.commanded_torque_nm().any()
    with pytest.raises(DriveStateError, match="not enabled"):
        bus.exchange(np.ones(3))


def test_feedback_timeout_error_is_typed_and_names_the_drive(rig: Rig) -> None:
    bus = rig.driver
    bus.enable()
    rig.drives.drop_tpdos(3, cycles=1_000_000)
    with pytest.raises(FeedbackTimeoutError) as info:
        for _ in range(5):
            bus.exchange(np.zeros(3))
    assert info.value.node_ids == (3,)
    assert not bus.enabled


# --- (d) stale feedback is never fresh ---------------------------------------------------------------


def test_tpdos_of_an_older_sync_are_late_never_fresh() -> None:
    """Drive 2's TPDOs held 1.5 feedback timeouts for three cycles: each arrives inside the next
    cycle's window (or before its SYNC). Feedback marked fresh must be this cycle's plant state."""
    rig = make_rig(n=3, fd=True, feedback_timeout_s=0.05, max_missed_cycles=100, heartbeat_timeout_s=5.0)
    bus, plant = rig.driver, rig.plant
    try:
        bus.enable()
        resolution = 1.5 / bus.counts_per_rad[0]
        torque = np.array([3.0, 3.0, 3.0])  # accelerating: every cycle's position differs
        for _ in range(5):
            bus.exchange(torque)
        rig.drives.delay_tpdos(2, delay_s=0.075, cycles=3)
        fresh_after_delay = 0
        for _ in range(8):
            feedback = bus.exchange(torque)
            truth = plant.state().position_rad  # lock-step: the state this SYNC produced
            for i in np.flatnonzero(feedback.fresh):
                assert abs(feedback.position_rad[i] - truth[i]) <= resolution, (i, feedback.cycle)
            fresh_after_delay += bool(feedback.fresh[1])
        assert fresh_after_delay >= 4  # it recovered once the delays ended
        assert wait_until(lambda: bus.counters.late == 3)  # each delayed TPDO, exactly once
        assert bus.counters.dropped >= 3
    finally:
        rig.close()


@pytest.mark.parametrize("fd", [False, True], ids=["classical", "fd"])
def test_tpdos_queued_before_the_sync_are_drained_as_late(fd: bool) -> None:
    """A well-formed TPDO already on the bus when the cycle starts cannot answer its SYNC; and as a
    frame no SYNC asked for, it is another sender's (drivers/bus_guard.py): FAULT."""
    rig = make_rig(n=2, fd=fd, feedback_timeout_s=0.2)
    intruder = can.Bus(
        interface="virtual", channel=rig.config.transport.channel, ignore_config=True, protocol=can.CanProtocol.CAN_FD
    )
    bus, plant = rig.driver, rig.plant
    try:
        bus.enable()
        bus.exchange(np.ones(2))
        statusword = 0x1237  # operation enabled
        bogus_counts = 123_456_789
        if fd:
            # Echoing the counter the next SYNC will carry: still queued before that SYNC.
            counter = fr.next_sync_counter(bus.sync_counter)
            frames = [
                can.Message(
                    arbitration_id=0x181,
                    is_extended_id=False,
                    is_fd=True,
                    data=fr.encode_tpdo_fd_sync(statusword, 0, bogus_counts, 0, counter),
                )
            ]
        else:
            frames = [
                can.Message(
                    arbitration_id=0x181, is_extended_id=False, data=fr.encode_tpdo1(statusword, 0, bogus_counts)
                ),
                can.Message(arbitration_id=0x281, is_extended_id=False, data=fr.encode_tpdo2(0)),
            ]
        late = bus.counters.late
        for msg in frames:
            intruder.send(msg)
        with pytest.raises(BusIntruderError, match="second sender of TPDO 0x181"):
            bus.exchange(np.ones(2))
        assert bus.counters.late == late + len(frames)  # drained as late: never taken as feedback
        assert bus.counters.dropped == 0
        assert not bus.enabled and plant is rig.plant
    finally:
        intruder.shutdown()
        rig.close()


def test_sync_frames_carry_the_counter_and_the_drives_echo_it() -> None:
    rig = make_rig(n=1, fd=True)
    try:
        assert rig.driver.sdo_read_int(1, 0x1019) == 240
        rig.driver.enable()
        for _ in range(3):
            rig.driver.exchange(np.zeros(1))
        counter = rig.driver.sync_counter
        assert 1 <= counter <= 240
        assert rig.driver.sdo_read_int(1, 0x2100) == counter  # what the drive answered last
    finally:
        rig.close()


def test_sync_counter_wraps_after_240() -> None:
    assert [fr.next_sync_counter(c) for c in (0, 1, 239, 240)] == [1, 2, 240, 1]
    data = fr.encode_tpdo_fd_sync(0x1237, -2, 5, -6, 240)
    assert data == bytes.fromhex("3712feff05000000fafffffff0000000")
    assert fr.decode_tpdo_fd_sync(data) == (fr.TpdoData(0x1237, -2, 5, -6), 240)
    with pytest.raises(fr.MalformedFrameError):
        fr.decode_tpdo_fd_sync(data[:13])


# --- (e) feedback timeout and miss budget, configurable ---------------------------------------------


def _documented_value(text: str) -> float:
    """'20 ms' -> 0.02, '1.0 s' -> 1.0, '25' -> 25.0."""
    number, _, unit = text.strip().partition(" ")
    return float(number) * {"": 1.0, "s": 1.0, "ms": 1e-3}[unit.strip()]


def test_defaults_are_the_documented_ones() -> None:
    """docs/drivers.md's "Timeouts and what they trade" table and the master heartbeat paragraph,
    read from the page: the code and the page cannot drift apart."""
    config = DriveBusConfig.model_validate(
        {"period_s": 0.001, "joints": [{"name": "a", "node_id": 1, "max_torque_nm": 1.0}]}
    )
    page = (Path(__file__).resolve().parents[2] / "docs" / "drivers.md").read_text()
    table = page.split("## Timeouts and what they trade", 1)[1].split("\n\n")[2]
    rows = [line.split("|")[1:3] for line in table.splitlines() if line.startswith("| `")]
    documented = {name.strip().strip("`"): _documented_value(value) for name, value in rows}
    assert set(documented) == {
        "feedback_timeout_s",
        "max_missed_cycles",
        "heartbeat_timeout_s",
        "comm_loss_timeout_s",
        "state_change_timeout_s",
    }
    for name, value in documented.items():
        assert getattr(config, name) == pytest.approx(value), name
    heartbeat = re.search(r"`master_node_id`, default (\d+), every\s+`master_heartbeat_ms`, default (\d+) ms", page)
    assert heartbeat is not None, "docs/drivers.md no longer states the master heartbeat defaults"
    assert (config.master_node_id, config.master_heartbeat_ms) == (int(heartbeat[1]), int(heartbeat[2]))


@pytest.mark.parametrize("max_missed", [0, 3])
def test_miss_budget_is_counted_in_cycles(max_missed: int) -> None:
    rig = make_rig(n=2, fd=True, feedback_timeout_s=0.05, max_missed_cycles=max_missed)
    bus = rig.driver
    try:
        bus.enable()
        bus.exchange(np.zeros(2))
        rig.drives.drop_tpdos(1, cycles=max_missed)
        for _ in range(max_missed):  # exactly the budget: tolerated
            assert not bus.exchange(np.zeros(2)).fresh[0]
        assert bus.exchange(np.zeros(2)).fresh.all()
        rig.drives.drop_tpdos(1, cycles=max_missed + 1)
        for _ in range(max_missed):
            bus.exchange(np.zeros(2))
        with pytest.raises(FeedbackTimeoutError, match=f"for {max_missed + 1} consecutive"):
            bus.exchange(np.zeros(2))
    finally:
        rig.close()


def test_a_tpdo_within_the_feedback_timeout_is_fresh_beyond_it_is_not() -> None:
    rig = make_rig(n=2, fd=True, feedback_timeout_s=0.1, max_missed_cycles=5)
    bus = rig.driver
    try:
        bus.enable()
        rig.drives.delay_tpdos(2, delay_s=0.02, cycles=1)  # well inside the 0.1 s window
        assert bus.exchange(np.zeros(2)).fresh.all()
        rig.drives.delay_tpdos(2, delay_s=0.3, cycles=1)  # beyond it
        assert bus.exchange(np.zeros(2)).fresh.tolist() == [True, False]
        assert wait_until(lambda: bus.counters.late == 1)
        assert bus.exchange(np.zeros(2)).fresh.all()
    finally:
        rig.close()
