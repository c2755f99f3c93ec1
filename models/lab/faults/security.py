"""The fault campaign's security cases (issue 20, docs/security.md): a forged TPDO, a second sender
of a drive's frames, a second master (at run time and at start-up), a bus directory and a control
socket squatted by another local user.

In-process injections (``inject(rig, rng) -> detail``, run by models/lab/faults/cases.run_in_process
once the loop is ACTIVE) and whole cases (``case(name, repeat, seed, work) -> CaseResult``). The
multi-user cases act as a second, unprivileged user (:mod:`models.lab.faults.other_user`); not run
as root, they report that they were not run and why.
"""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from drivers.cia402 import frames as fr
from models.lab import rigs
from models.lab.faults.cases import CaseResult, run_cli_in_process
from models.lab.faults.other_user import OtherUserUnavailable, other_user, run_as, shared_directory
from models.lab.rigs import InProcessRig

FORGED_OFFSET_RAD = 0.03  # the campaign's forger: drive 3's TPDO moved by this much
FORGED_NODE = 3


def _intruder_bus(rig: InProcessRig) -> can.BusABC:
    """Another station on the rig's bus (an ipc peer of this uid, or a virtual bus in-process)."""
    transport = rig.config.bus.transport
    if transport.interface == "ipc":
        from drivers.ipc import IpcBus

        return IpcBus(transport.channel, fd=transport.fd)
    protocol = can.CanProtocol.CAN_FD if transport.fd else can.CanProtocol.CAN_20
    return can.Bus(interface="virtual", channel=transport.channel, ignore_config=True, protocol=protocol)


class _Forger:
    """Answers each SYNC with drive 3's last TPDO, moved by +0.03 rad and echoing the SYNC's counter."""

    def __init__(self, bus: can.BusABC, counts_per_rad: float, last: tuple[int, int, int, int | None]) -> None:
        """``last``: drive 3's last feedback (statusword, torque ‰, position and velocity counts), so
        the very first SYNC after the injection is answered."""
        self.bus = bus
        self.offset_counts = round(FORGED_OFFSET_RAD * counts_per_rad)
        self.sent = 0
        self._last: tuple[int, int, int, int | None] | None = last
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="forger", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        cob_id = fr.TPDO1_BASE + FORGED_NODE
        while not self._stop.is_set():
            msg = self.bus.recv(0.01)
            if msg is None:
                continue
            if msg.arbitration_id == cob_id and msg.is_fd:
                with contextlib.suppress(ValueError, fr.MalformedFrameError):
                    self._last, _counter = fr.decode_tpdo_fd_sync(bytes(msg.data))
            elif msg.arbitration_id == fr.SYNC_COB_ID and self._last is not None:
                statusword, torque, position, velocity = self._last
                counter = fr.decode_sync(bytes(msg.data)) or 0
                data = fr.encode_tpdo_fd_sync(statusword, torque, position + self.offset_counts, velocity or 0, counter)
                self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_fd=True, is_extended_id=False))
                self.sent += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.bus.shutdown()


def forge_tpdo(rig: InProcessRig, rng: np.random.Generator) -> dict[str, Any]:
    """A second process on the bus answering each SYNC first with drive 3's TPDO (+0.03 rad)."""
    node = rig.drive_bus.nodes[FORGED_NODE - 1]
    last = (node.statusword, node.torque_permille, node.position_counts, node.velocity_counts_s)
    forger = _Forger(_intruder_bus(rig), float(rig.drive_bus.counts_per_rad[FORGED_NODE - 1]), last)
    rig.cleanups.append(forger.close)
    return {"node": FORGED_NODE, "offset_rad": FORGED_OFFSET_RAD, "transport": rig.config.bus.transport.interface}


def second_sender(rig: InProcessRig, rng: np.random.Generator) -> dict[str, Any]:
    """One heartbeat of a drive (operational, as the drive's own) from another station."""
    node = int(rng.integers(1, 7))
    bus = _intruder_bus(rig)
    data = fr.encode_heartbeat(fr.NmtState.OPERATIONAL)
    bus.send(can.Message(arbitration_id=fr.HEARTBEAT_BASE + node, data=data, is_extended_id=False))
    rig.cleanups.append(bus.shutdown)
    return {"node": node, "frame": f"heartbeat 0x{fr.HEARTBEAT_BASE + node:03X}"}


def foreign_nmt(rig: InProcessRig, rng: np.random.Generator) -> dict[str, Any]:
    """Another master's NMT command on the bus (reset node 2, as a second ``hil run`` would)."""
    bus = _intruder_bus(rig)
    data = fr.encode_nmt(fr.NmtCommand.RESET_NODE, 2)
    bus.send(can.Message(arbitration_id=fr.NMT_COB_ID, data=data, is_extended_id=False))
    rig.cleanups.append(bus.shutdown)
    return {"frame": "NMT reset node 2"}


# --- whole cases -----------------------------------------------------------------------------------


def _refusal(result: CaseResult, code: int, err: str, expected: str, started_s: float) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    result.detected_s = round(time.monotonic() - started_s, 3)
    result.detail.update({"exit_code": code, "stderr": lines[-3:]})
    result.action = f"refused: exit {code}, one line"
    result.daemon_note = "exit 2: refused before anything was sent (allowed)"
    result.telemetry_event = None
    result.status_shows = None
    result.max_torque_ratio = 0.0
    if code != 2:
        result.failures.append(f"exit {code}, expected 2")
    if len(lines) != 1 or "Traceback" in err:
        result.failures.append(f"{len(lines)} lines on stderr, expected one")
    if expected not in err:
        result.failures.append(f"'{expected}' not in the message")


def second_master_at_start_up(name: str, repeat: int, seed: int, work: Path) -> CaseResult:
    """A first master holds the bus (connected, drives operational); ``hil run`` on the same bus
    must refuse (exit 2) without sending a frame: the first master's drives never notice."""
    import yaml

    from drivers.config import parse_drive_bus_config
    from drivers.drive_bus import DriveBus
    from sim_target.launch import launch_target

    result = CaseResult(name, repeat, seed)
    work.mkdir(parents=True, exist_ok=True)
    with launch_target(rigs.target_config(), "virtual") as target:
        data = rigs.runtime_config_dict(dict(target.transport), telemetry_port=None)
        first = DriveBus(parse_drive_bus_config(data["bus"], "first master"))
        first.connect()
        try:
            path = work / "runtime.yaml"
            path.write_text(yaml.safe_dump(data))
            t0 = time.monotonic()
            code, err = run_cli_in_process(["run", "--config", str(path)])
            _refusal(result, code, err, "second master on the bus", t0)
            nmt = [s.name for s in target.server.drives.nmt_states()]
            result.detail["first_master_drives_nmt"] = nmt
            if any(s != "OPERATIONAL" for s in nmt):
                result.failures.append(f"the first master's drives were disturbed: {nmt}")
            first.enable()
            fresh = all(bool(first.exchange(np.zeros(first.n_joints)).fresh.all()) for _ in range(20))
            result.detail["first_master_goes_on"] = fresh
            if not fresh:
                result.failures.append("the first master lost its feedback")
            result.drives_final = [s.value for s in first.quick_stop()]
        finally:
            first.close()
        arm = np.asarray(target.server.plant.state().position_rad)
    result.daemon_alive = True
    result.arm_in_limits = bool(np.all(np.abs(arm) <= np.pi))
    result.passed = not result.failures
    return result


def _as_other_user(result: CaseResult) -> Any:
    try:
        return other_user()
    except OtherUserUnavailable as exc:
        result.action = f"not run: {exc}"
        result.detail["not_run"] = str(exc)
        result.passed = True  # nothing to judge; the reason is in the table
        return None


def squatted_bus_directory(name: str, repeat: int, seed: int, work: Path) -> CaseResult:
    """Another user made the bus directory first (as anyone can in /tmp): the target refuses it."""
    import yaml

    result = CaseResult(name, repeat, seed)
    user = _as_other_user(result)
    if user is None:
        return result
    with shared_directory() as shared:
        squatted = shared / "hil-can"
        proc = run_as(user, "import os, sys; os.mkdir(sys.argv[1], 0o755)", str(squatted))
        proc.wait(10)
        config = rigs.target_config()
        config["bus"] = {**config["bus"], "interface": "ipc", "channel": str(squatted)}
        config.pop("control_socket", None)
        path = work / "target.yaml"
        path.write_text(yaml.safe_dump(config))
        t0 = time.monotonic()
        code, err = run_cli_in_process(["target", "serve", "--config", str(path)])
        _refusal(result, code, err, f"belongs to {user.name}", t0)
        result.detail["squatter_uid"] = user.uid
        result.drives_final = "no drive started"
        if any(squatted.iterdir()):
            result.failures.append("a socket of ours went into her directory")
    result.daemon_alive = code == 2
    result.passed = not result.failures
    return result


_FAKE_RUNTIME = """
import os, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.bind(sys.argv[1]); os.chmod(sys.argv[1], 0o777); s.listen(8)
print("listening", flush=True)
while True:
    c, _ = s.accept(); c.recv(4096); c.sendall(b'{"ok": true, "state": "ACTIVE"}\\n'); c.close()
"""


def squatted_control_socket(name: str, repeat: int, seed: int, work: Path) -> CaseResult:
    """Another user serves a fake runtime at the control socket's path: ``hil stop`` refuses it."""
    result = CaseResult(name, repeat, seed)
    user = _as_other_user(result)
    if user is None:
        return result
    with shared_directory() as shared:
        path = shared / "hil-runtime.sock"
        proc = run_as(user, _FAKE_RUNTIME, str(path))
        try:
            ready = proc.stdout.readline().strip() if proc.stdout is not None else ""
            if ready != "listening":
                result.failures.append(f"the squatter did not start: {ready!r}")
            t0 = time.monotonic()
            code, err = run_cli_in_process(["stop", "--socket", str(path)])
            _refusal(result, code, err, f"belongs to {user.name}", t0)
        finally:
            proc.kill()
            proc.wait()
    result.detail["squatter_uid"] = user.uid
    result.drives_final = "no runtime involved"
    result.daemon_alive = True
    result.passed = not result.failures
    return result


__all__ = [
    "forge_tpdo",
    "foreign_nmt",
    "second_master_at_start_up",
    "second_sender",
    "squatted_bus_directory",
    "squatted_control_socket",
]
