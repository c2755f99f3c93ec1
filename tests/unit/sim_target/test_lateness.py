"""The free-running target's lateness and the rule that voids a HIL run (sim_target/lateness.py),
the held arm, the SYNC phase lock and the start-up cost warning (sim_target/server.py)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from unittest import mock

import numpy as np
import pybullet
import pytest

from sim_target.config import parse_target_config
from sim_target.lateness import Lateness, invalid_reason
from sim_target.plant import PybulletPlant
from sim_target.plant_protocol import JointState
from sim_target.rt_settings import split_cpus
from sim_target.server import TargetServer, make_plant

Q0 = [0.0, -0.5, 0.8, -0.3, 0.0, 0.0]
PERIOD_S = 1e-3


def test_a_run_is_invalid_above_a_tenth_of_a_percent_skipped_or_one_period_of_lag() -> None:
    assert invalid_reason(None, PERIOD_S) is None  # lock-step: no wall clock to lag
    ok = {"periods": 5000, "skipped_periods": 5, "worst_lag_s": 0.9e-3}
    assert invalid_reason(ok, PERIOD_S) is None
    skipped = invalid_reason({**ok, "skipped_periods": 6}, PERIOD_S)
    assert skipped is not None and "skipped 6 of 5000 periods" in skipped
    lagged = invalid_reason({**ok, "worst_lag_s": 1.2e-3}, PERIOD_S)
    assert lagged is not None and "lagged the wall clock by 1.20 ms" in lagged


def test_lateness_counts_ticks_skips_and_the_worst_lag() -> None:
    late = Lateness.starting_now()
    late.tick(50e-6, 0)
    late.tick(300e-6, 2)
    late.tick(10e-6, 0)
    out = late.as_dict(PERIOD_S)
    assert (out["periods"], out["late_ticks"], out["skipped_periods"]) == (5, 1, 2)
    assert out["worst_lag_s"] == pytest.approx(300e-6) and out["skipped_fraction"] == pytest.approx(0.4)
    assert invalid_reason(out, PERIOD_S) is not None


def test_a_held_arm_is_not_integrated_until_something_changes() -> None:
    with PybulletPlant(period_s=PERIOD_S, substeps=8, initial_position_rad=Q0) as plant:
        braked, free = np.ones(6, dtype=bool), np.zeros(6, dtype=bool)
        for _ in range(20):
            plant.step(np.zeros(6), braked)
        q_held = plant.state().position_rad.copy()
        with mock.patch.object(pybullet, "stepSimulation", side_effect=AssertionError("integrated")):
            for _ in range(100):
                state = plant.step(np.zeros(6), braked)
        assert state.time_s == pytest.approx(120 * PERIOD_S)
        np.testing.assert_array_equal(state.position_rad, q_held)
        np.testing.assert_array_equal(state.velocity_rad_s, np.zeros(6))
        # What pybullet would have done with the brakes holding: the same pose, to 1e-8 rad.
        plant._held = None
        np.testing.assert_allclose(plant.step(np.zeros(6), braked).position_rad, q_held, rtol=0, atol=1e-8)
        # A payload, or a drive enabled, is integrated again at once.
        plant.set_payload(40.0)
        with mock.patch.object(pybullet, "stepSimulation", wraps=pybullet.stepSimulation) as step:
            plant.step(np.zeros(6), braked)
            plant.step(np.zeros(6), free)
            calls = step.call_args_list
        assert len(calls) == 2
        assert not np.array_equal(plant.state().position_rad, q_held)  # unbraked under gravity: it falls


class _Drives:
    """A drive layer with no bus: serve_until waits out the time; a SYNC is a direct call."""

    def __init__(self) -> None:
        self.handler: Callable[[], None] | None = None
        self.published = 0

    def set_sync_handler(self, handler: Callable[[], None]) -> None:
        self.handler = handler

    def serve_until(self, deadline_s: float, return_on_sync: bool = False) -> None:
        time.sleep(max(0.0, deadline_s - time.monotonic()))

    def commanded_torque_nm(self) -> np.ndarray:
        return np.zeros(6)

    def operation_enabled(self) -> np.ndarray:
        return np.ones(6, dtype=bool)

    def publish_feedback(self, state: object) -> None:
        self.published += 1

    def apply_fault(self, fault: object) -> None: ...

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None: ...

    def safe_stop(self) -> None: ...

    def close(self) -> None: ...


def _server(**overrides: object) -> TargetServer:
    data = {
        "clock": "realtime",
        "plant": {"substeps": 4, "initial_position_rad": Q0},
        "bus": {"interface": "virtual", "channel": "lateness", "fd": True, "data_bitrate": 5_000_000},
        "realtime": {"fifo_priority": 0, "lock_memory": False},  # not for the pytest process
        **overrides,
    }
    config = parse_target_config(data)
    return TargetServer(config, make_plant(config), _Drives())  # a stand-in: satisfies the DriveBank protocol


def test_the_physics_tick_locks_its_phase_to_the_sync() -> None:
    server = _server()
    server._deadline_s = 0.0004  # the next tick 0.4 ms after a SYNC at 0: 0.4 ms off the lock
    for k in range(40):
        sync_s = k * PERIOD_S
        while server._deadline_s < sync_s - PERIOD_S / 2:  # the ticks the loop would run meanwhile
            server._deadline_s += PERIOD_S
        server._lock_phase_to_sync(sync_s)
        if k == 0:  # a quarter of the error per SYNC, never a jump
            assert 0.0004 - server._deadline_s == pytest.approx(0.25 * 0.4 * PERIOD_S)
    assert server._deadline_s - 39 * PERIOD_S == pytest.approx(0.0, abs=1e-6)
    server.shutdown()


class _FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def monotonic(self) -> float:
        return self.now_s


class _SyncingDrives(_Drives):
    """SYNCs at given times on a fake clock; a physics step costs ``step_s`` of it."""

    def __init__(self, clock: _FakeClock, syncs_s: list[float], server_stop: list[TargetServer]) -> None:
        super().__init__()
        self.clock = clock
        self.syncs_s = syncs_s
        self.stop = server_stop
        self.answered: list[tuple[float, float]] = []  # (SYNC sent, answered)

    def serve_until(self, deadline_s: float, return_on_sync: bool = False) -> None:
        if not self.syncs_s:
            self.stop[0].stop()
            return
        if self.syncs_s[0] <= deadline_s:
            sent_s = self.syncs_s.pop(0)
            self.clock.now_s = max(self.clock.now_s, sent_s)  # a step still running delays the answer
            self.answered.append((sent_s, self.clock.now_s))
            assert self.handler is not None, "the server set its SYNC handler"
            self.handler()
            if return_on_sync:
                return
        self.clock.now_s = max(self.clock.now_s, deadline_s)


@pytest.mark.parametrize(("jitter", "step_periods"), [(0.0, 0.8), (0.2, 0.5)])
def test_a_sync_is_answered_before_the_physics_of_its_period_steps(jitter: float, step_periods: float) -> None:
    """A physics step of 0.8 period, or 0.5 with the master's SYNCs jittering by up to 0.2 period:
    run right after each SYNC's answer, it never delays the next SYNC (a tick a quarter period
    after the SYNC delayed them); one tick per period, on the wall clock."""
    clock = _FakeClock()
    rng = np.random.default_rng(1)
    syncs_s = [clock.now_s + 0.37e-3 + k * PERIOD_S + jitter * PERIOD_S * rng.uniform(-1, 1) for k in range(300)]
    server = _server()
    holder = [server]
    drives = _SyncingDrives(clock, syncs_s, holder)
    server.drives = drives
    drives.set_sync_handler(server._on_sync)
    plant_step = server.plant.step

    def slow_step(torque_nm: np.ndarray, brake_engaged: np.ndarray) -> JointState:
        clock.now_s += step_periods * PERIOD_S
        return plant_step(torque_nm, brake_engaged)

    with (
        mock.patch("sim_target.server.time", clock),
        mock.patch.object(server, "_apply_realtime_settings"),
        mock.patch.object(server.plant, "step", slow_step),
    ):
        server.run()
    delays_s = np.array([answered - sent for sent, answered in drives.answered])
    assert len(delays_s) == 300 and np.all(delays_s[20:] == 0.0)  # after the phase lock settles
    assert server.stats.steps == pytest.approx(300, abs=2)  # one tick per period, never a burst
    assert server.lateness.skipped_periods == 0 and server.lateness.worst_lag_s < 0.6 * PERIOD_S


def test_a_target_that_cannot_keep_real_time_says_so_and_its_run_is_invalid(caplog: pytest.LogCaptureFixture) -> None:
    server = _server(plant={"substeps": 2000, "initial_position_rad": Q0})  # ~10 ms a period here
    runner = threading.Thread(target=server.run)
    with caplog.at_level(logging.WARNING):
        runner.start()
        deadline = time.monotonic() + 30.0
        while server.stats.steps < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        server.stop()
        runner.join(timeout=30)
    warnings = [r.getMessage() for r in caplog.records if "cannot keep real time" in r.getMessage()]
    assert len(warnings) == 1 and "2000 substeps" in warnings[0] and "% of the 1 ms period" in warnings[0]
    lateness = server.lateness.as_dict(PERIOD_S)
    assert lateness["skipped_periods"] > 0 and server.stats.late_ticks > 0
    assert invalid_reason(lateness, PERIOD_S) is not None
    assert server.realtime_settings["plant_step_fraction"] > 0.5


def test_cpus_are_split_apart_or_refused_with_one_line() -> None:
    import os

    available = sorted(os.sched_getaffinity(0))
    runtime, target = split_cpus("auto")
    if len(available) >= 2:
        assert runtime is not None and target is not None and set(runtime).isdisjoint(target)
    assert split_cpus("none") == (None, None)
    with pytest.raises(ValueError, match="--cpus: expected auto, none or RUNTIME,TARGET"):
        split_cpus("1")
    with pytest.raises(ValueError, match="--cpus: CPU 999 is not one this process may use"):
        split_cpus(f"999,{available[0]}")


@pytest.mark.parametrize("in_lockstep", [False, True])
def test_lockstep_applies_the_realtime_settings_only_when_asked(in_lockstep: bool) -> None:
    import os

    cpu = sorted(os.sched_getaffinity(0))[-1]
    realtime = {"fifo_priority": 0, "lock_memory": False, "cpus": [cpu], "in_lockstep": in_lockstep}
    server = _server(clock="lockstep", realtime=realtime)  # SCHED_FIFO and mlockall: not for pytest
    seen: list[set[int]] = []

    def probe(deadline_s: float, return_on_sync: bool = False) -> None:  # on the serving thread
        seen.append(os.sched_getaffinity(0))
        server.stop()

    with mock.patch.object(server.drives, "serve_until", probe):
        runner = threading.Thread(target=server.run)
        runner.start()
        runner.join(timeout=30)
    assert seen
    if in_lockstep:  # the thread serving the SYNCs took them, and the status says so
        assert seen[0] == {cpu} and server.realtime_settings["applied"] == [f"CPU [{cpu}]"]
        assert server.status()["realtime"]["refused"] == []
    else:
        assert server.realtime_settings == {}


def test_serve_until_returns_on_a_sync_found_while_draining_not_after_the_next_frame() -> None:
    """The drives drain the bus every few ms (the master watch); a SYNC handled there must end a
    ``return_on_sync`` wait at once: waiting on for the next frame made the free-running target
    step its physics a period late, into the next cycle's frames."""
    import can

    from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig

    with (
        can.Bus(interface="virtual", channel="drain-sync") as bus,
        can.Bus(interface="virtual", channel="drain-sync") as master,
    ):
        drives = EmulatedDrives(bus, EmulatedDrivesConfig(node_ids=(1,)))
        drives.start(own_thread=False)
        syncs: list[float] = []
        drives.set_sync_handler(lambda: syncs.append(time.monotonic()))
        drives.serve_until(time.monotonic() + 0.05)  # boot-up sent, the first drain done
        master.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        drives._next_check_s = 0.0  # the next wait begins with a drain, which finds the SYNC
        waits: list[tuple[float | None, int]] = []  # (recv timeout, SYNCs handled before the call)
        real_recv = bus.recv

        def recv(timeout: float | None = None) -> can.Message | None:
            waits.append((timeout, len(syncs)))
            return real_recv(timeout)

        vars(bus)["recv"] = recv  # an instance attribute shadows the method: counts the waits of this one bus
        drives.serve_until(time.monotonic() + 5.0, return_on_sync=True)
        assert len(syncs) == 1
        assert [timeout for timeout, seen in waits if seen] == [0.0]  # the drain's last look, no wait
        drives.close()
