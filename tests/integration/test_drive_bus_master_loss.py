"""The drives stop the arm on their own when the master dies (CiA 301 heartbeat consumer 0x1016,
RPDO timeout 0x1400:05, SYNC timeout 0x2101; CiA 402 abort connection option 0x6007 = quick stop).

(a) start-up: DriveBus configures every watch and produces its own heartbeat; (b) each watch on
its own, with a hand-driven master on the virtual bus; (c) a master idle while enabled; (d) the
master process SIGKILLed mid-run, over the loopback bridge, against the emulated drives and against
the pybullet target on its real-time clock: every drive quick-stops within the configured timeout.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from canopen.sdo import SdoVariable

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.state_machine import State
from drivers.errors import DriveFaultError
from drivers.transport import start_bridge_server
from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
from sim_target.testing.drive_rig import make_rig, wait_until

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
# Reaction bound beyond the timeout: the drives' receive thread checks at least every 10 ms; the
# rest is for a loaded 2-core machine (it bounds a wait, the drives' own record says how long).
SLACK_S = 0.3


# --- (a) start-up --------------------------------------------------------------------------------


def test_connect_configures_the_master_watches_on_every_drive() -> None:
    rig = make_rig(n=2, fd=True, comm_loss_timeout_s=0.6, master_node_id=100, master_heartbeat_ms=15)
    try:
        for node_id in (1, 2):
            assert rig.driver.sdo_read_int(node_id, odx.CONSUMER_HEARTBEAT, 1) == (100 << 16) | 600
            assert rig.driver.sdo_read_int(node_id, odx.RPDO1_COMM, 5) == 600
            assert rig.driver.sdo_read_int(node_id, odx.SYNC_TIMEOUT) == 600
            assert rig.driver.sdo_read_int(node_id, odx.ABORT_CONNECTION_OPTION) == 3  # quick stop
            assert rig.driver.sdo_read_int(node_id, odx.COMM_CYCLE_PERIOD) == 1000  # µs
    finally:
        rig.close()


def test_the_master_produces_its_heartbeat_at_the_configured_period() -> None:
    rig = make_rig(n=1, fd=True, master_heartbeat_ms=20, master_node_id=99)
    sniffer = can.Bus(interface="virtual", channel=rig.config.transport.channel, ignore_config=True)
    try:
        sniffer.set_filters([{"can_id": fr.HEARTBEAT_BASE + 99, "can_mask": 0x7FF}])
        start = time.monotonic()
        stamps = []
        while time.monotonic() - start < 0.5:  # idle master: its background thread sends them
            msg = sniffer.recv(0.1)
            if msg is not None:
                assert fr.decode_heartbeat(bytes(msg.data)) is fr.NmtState.OPERATIONAL
                stamps.append(msg.timestamp)
        assert 12 <= len(stamps) <= 30, len(stamps)  # 25 expected; sent from 10 ms wake-ups
        # The period, within the background thread's 10 ms wake-up granularity.
        assert 0.015 <= float(np.median(np.diff(stamps))) <= 0.03, np.diff(stamps)
    finally:
        sniffer.shutdown()
        rig.close()


def test_no_watch_when_comm_loss_timeout_is_null() -> None:
    rig = make_rig(n=1, fd=True, comm_loss_timeout_s=None)
    try:
        assert rig.driver.sdo_read_int(1, odx.CONSUMER_HEARTBEAT, 1) == 0
        assert rig.driver.sdo_read_int(1, odx.RPDO1_COMM, 5) == 0
    finally:
        rig.close()


# --- (b) each watch on its own, a hand-driven master ------------------------------------------------


class _HandMaster:
    """Raw frames on the virtual bus: SDO-free set-up of one emulated drive, then the streams
    (heartbeat, RPDO, SYNC) a test can stop one at a time."""

    def __init__(self) -> None:
        self.channel = f"loss-{uuid.uuid4().hex[:8]}"
        self.side = can.Bus(interface="virtual", channel=self.channel, ignore_config=True)
        self.master = can.Bus(interface="virtual", channel=self.channel, ignore_config=True)
        self.drives = EmulatedDrives(self.side, EmulatedDrivesConfig(node_ids=(1,)))
        self.drives.start()
        self.drive = self.drives._drive(1)

    def watch(self, heartbeat_ms: int = 0, rpdo_ms: int = 0, sync_ms: int = 0, option: int = 3) -> None:
        self._write(odx.CONSUMER_HEARTBEAT, 1, (127 << 16) | heartbeat_ms)
        self._write(odx.RPDO1_COMM, 5, rpdo_ms)
        self._write(odx.SYNC_TIMEOUT, 0, sync_ms)
        self._write(odx.ABORT_CONNECTION_OPTION, 0, option)

    def _write(self, index: int, subindex: int, value: int) -> None:
        """Set the drive's own object (as its local application would); subindex ignored for a variable."""
        entry = self.drive.node.sdo[index]
        variable = entry if isinstance(entry, SdoVariable) else entry[subindex]
        variable.raw = value

    def enable(self) -> None:
        self.send(0, fr.encode_nmt(fr.NmtCommand.START, 1))
        for controlword in (0x06, 0x07, 0x0F):
            self.cycle(controlword)
        assert wait_until(lambda: self.drives.states() == (State.OPERATION_ENABLED,))

    def send(self, cob_id: int, data: bytes) -> None:
        self.master.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def cycle(self, controlword: int = 0x0F, rpdo: bool = True, sync: bool = True, heartbeat: bool = True) -> None:
        if heartbeat:
            self.send(0x77F, b"\x05")  # the master's heartbeat, node 127 operational
        if rpdo:
            self.send(0x201, fr.encode_rpdo(controlword, 0))
        if sync:
            self.send(0x80, b"\x01")
        time.sleep(0.005)

    def emcy_codes(self) -> list[int]:
        codes = []
        while (msg := self.master.recv(0.0)) is not None:
            if msg.arbitration_id == fr.EMCY_BASE + 1:
                codes.append(fr.decode_emcy(bytes(msg.data)).error_code)
        return codes

    def close(self) -> None:
        self.drives.close()
        self.master.shutdown()
        self.side.shutdown()


@pytest.fixture
def hand() -> Iterator[_HandMaster]:
    master = _HandMaster()
    yield master
    master.close()


@pytest.mark.parametrize(
    ("stopped", "cause", "code"),
    [
        ("heartbeat", "heartbeat", fr.EMCY_HEARTBEAT),
        ("rpdo", "rpdo", fr.EMCY_RPDO_TIMEOUT),
        ("sync", "sync", fr.EMCY_COMMUNICATION),
    ],
)
def test_each_watch_alone_quick_stops_the_drive(hand: _HandMaster, stopped: str, cause: str, code: int) -> None:
    hand.watch(**{f"{stopped}_ms": 60})
    hand.enable()
    for _ in range(30):  # 150 ms of a healthy master: the watch must not fire
        hand.cycle()
    assert hand.drives.states() == (State.OPERATION_ENABLED,) and not hand.drives.master_losses
    hand.emcy_codes()
    silenced = time.monotonic()
    while time.monotonic() - silenced < 0.3:  # the other two streams go on
        hand.cycle(**{stopped: False})
    # Quick Stop Active, then Switch On Disabled at the next SYNC when one still comes (0x605A = 2).
    assert hand.drives.states()[0] in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
    assert not hand.drives.operation_enabled().any()  # brake on
    (loss,) = hand.drives.master_losses
    assert (loss.cause, loss.reaction) == (cause, "quick stop")
    assert 0.06 <= loss.silent_s <= 0.06 + SLACK_S
    assert loss.time_s - silenced <= 0.06 + SLACK_S
    assert code in hand.emcy_codes()
    assert hand.drives.counters.master_lost == 1


@pytest.mark.parametrize(
    ("option", "state"),
    [(0, State.OPERATION_ENABLED), (1, State.FAULT), (2, State.SWITCH_ON_DISABLED), (3, State.QUICK_STOP_ACTIVE)],
)
def test_abort_connection_option_code_picks_the_reaction(hand: _HandMaster, option: int, state: State) -> None:
    hand.watch(heartbeat_ms=50, option=option)
    hand.enable()
    hand.cycle()
    assert wait_until(lambda: bool(hand.drives.master_losses), timeout_s=1.0)
    assert hand.drives.states() == (state,)
    reactions = {0: "none", 1: "fault", 2: "disable voltage", 3: "quick stop"}
    assert hand.drives.master_losses[0].reaction == reactions[option]


def test_a_drive_that_is_not_enabled_does_not_react(hand: _HandMaster) -> None:
    hand.watch(heartbeat_ms=40, rpdo_ms=40, sync_ms=40)
    hand.enable()
    hand.cycle(controlword=0x00)  # disable voltage: Switch On Disabled
    assert wait_until(lambda: hand.drives.states() == (State.SWITCH_ON_DISABLED,))
    hand.emcy_codes()
    time.sleep(0.2)  # the master idle between runs
    assert not hand.drives.master_losses and hand.emcy_codes() == []


def test_watches_start_at_the_first_frame_and_reset_communication_clears_them(hand: _HandMaster) -> None:
    hand.watch(heartbeat_ms=40)
    hand.enable()  # heartbeats sent during enable: the watch runs
    hand.send(0, fr.encode_nmt(fr.NmtCommand.RESET_COMMUNICATION, 1))
    assert wait_until(lambda: hand.drive.master_heartbeat_timeout_ms == 0)
    assert hand.drive.last_master_heartbeat_s == 0.0


# --- (c) a master idle while enabled --------------------------------------------------------------


def test_a_master_that_stops_exchanging_while_enabled_finds_its_drives_stopped() -> None:
    rig = make_rig(n=3, fd=True, comm_loss_timeout_s=0.1, feedback_timeout_s=0.05)
    try:
        rig.driver.enable()
        for _ in range(20):
            rig.driver.exchange(np.zeros(3))
        assert wait_until(lambda: len(rig.drives.master_losses) == 3, timeout_s=0.1 + SLACK_S + 1.0)
        # The set-points and SYNCs stopped; the heartbeat went on (the background thread sends it).
        assert {loss.cause for loss in rig.drives.master_losses} <= {"rpdo", "sync"}
        assert rig.drives.states() == (State.QUICK_STOP_ACTIVE,) * 3
        with pytest.raises(DriveFaultError, match="0x8250|0x8100") as info:
            rig.driver.exchange(np.zeros(3))
        assert "from the master" in str(info.value)
        assert not rig.driver.enabled
    finally:
        rig.close()


# --- (d) the master process killed ----------------------------------------------------------------


def _start_master(args: list[str]) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(HERE), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(
        [sys.executable, str(HERE / "drive_master_process.py"), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _reap(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=10)  # and close its pipes


def _wait_running(proc: subprocess.Popen[str], timeout_s: float = 60.0) -> None:
    assert proc.stdout is not None and proc.stderr is not None
    selector = selectors.DefaultSelector()
    selector.register(proc.stdout, selectors.EVENT_READ)
    if not selector.select(timeout_s):
        proc.kill()
        raise AssertionError(f"master did not start: {proc.communicate()[1][-2000:]}")
    line = proc.stdout.readline()
    if not line:
        raise AssertionError(f"master exited {proc.wait()}: {proc.stderr.read()[-2000:]}")
    assert "running" in json.loads(line)


def test_killing_the_master_quick_stops_every_emulated_drive_within_the_timeout() -> None:
    channel = f"kill-{uuid.uuid4().hex[:8]}"
    bridge = start_bridge_server("127.0.0.1", 0, channel)
    side = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    drives = EmulatedDrives(side, EmulatedDrivesConfig(node_ids=(1, 2, 3, 4, 5, 6)))
    drives.start()
    timeout_s = 0.1
    master = _start_master(["--bridge-url", bridge.url, "--comm-loss-timeout-s", str(timeout_s)])
    try:
        _wait_running(master)
        assert drives.states() == (State.OPERATION_ENABLED,) * 6
        killed = time.monotonic()
        master.send_signal(signal.SIGKILL)
        master.wait(timeout=10)
        assert wait_until(lambda: not drives.operation_enabled().any(), timeout_s=timeout_s + SLACK_S + 2.0)
        stopped = time.monotonic() - killed
        losses = drives.master_losses
        assert sorted(loss.node_id for loss in losses) == [1, 2, 3, 4, 5, 6]
        assert all(loss.reaction == "quick stop" for loss in losses)
        assert drives.states() == (State.QUICK_STOP_ACTIVE,) * 6
        # The drives' own clock: each reacted once its master had been silent for the timeout,
        # within the 10 ms check period beyond it (plus what a loaded machine adds).
        for loss in losses:
            assert timeout_s <= loss.silent_s <= timeout_s + SLACK_S, loss
            assert loss.time_s - killed <= timeout_s + SLACK_S, loss
        assert stopped <= timeout_s + SLACK_S + 0.05
        # The bridge let go of the dead client's bus: only the drives' queue is left on the channel.
        from can.interfaces.virtual import channels

        assert wait_until(lambda: len(channels[channel]) == 1, timeout_s=5.0), len(channels[channel])
    finally:
        _reap(master)
        drives.close()
        side.shutdown()
        bridge.close()


def test_killing_the_master_brakes_the_realtime_pybullet_arm(tmp_path: Path) -> None:
    """The issue's case: the target on its real-time clock keeps simulating after the master dies;
    within the timeout every drive is quick-stopped and the brakes hold the arm."""
    pytest.importorskip("pybullet")
    from sim_target.server import send_control
    from sim_target.testing.hil_target import target_process

    timeout_s = 0.1
    with target_process(tmp_path, 0.002, substeps=16, clock="realtime") as target:
        master = _start_master(
            [
                "--bridge-url",
                target.bridge_url,
                "--comm-loss-timeout-s",
                str(timeout_s),
                "--period-s",
                "0.002",
                "--torque-nm",
                "0.0",
            ]
        )
        try:
            _wait_running(master)
            assert send_control(target.control_socket, {"kind": "status"})["operation_enabled"] == [True] * 6
            killed = time.monotonic()
            master.send_signal(signal.SIGKILL)
            master.wait(timeout=10)
            status = send_control(target.control_socket, {"kind": "status"})
            while any(status["operation_enabled"]) and time.monotonic() - killed < 5.0:
                time.sleep(0.005)
                status = send_control(target.control_socket, {"kind": "status"})
            stopped = time.monotonic() - killed
            assert status["operation_enabled"] == [False] * 6, status
            assert stopped <= timeout_s + SLACK_S + 0.05, stopped
            held = np.array(status["position_rad"])
            time.sleep(0.3)  # the plant runs on: the brakes hold every joint
            later = np.array(send_control(target.control_socket, {"kind": "status"})["position_rad"])
            assert np.abs(later - held).max() < 1e-3, (held, later)
        finally:
            _reap(master)
