"""Where a runtime cycle's time goes: each part of the cycle timed on its own, interleaved round by
round with a bare onnxruntime call of a one-node graph (the machine's per-call floor), so every
figure also reads as a ratio to that floor and compares across machines (bench_runtime.py).

Parts, each as one cycle runs it (6 joints, CAN FD):

- ``policy_call``: ``Controller.step`` (the bundle's input row filled, one onnxruntime call with
  IOBinding, the output checked) and ``Controller.commit``;
- ``supervisor``: ``check_feedback`` + ``select_torque`` (the one clip, the one substitution);
- ``reference``: one row of the condition's reference;
- ``frame_encode``: six RPDOs packed into their reused buffers (``encode_rpdo_into``);
- ``frame_decode``: six CAN FD TPDOs decoded (``unpack_tpdo_fd_sync``, the master's cycle's);
- ``ipc_send_receive``: the master's cycle on the project's ipc bus, its raw path (drivers/pdo.py):
  6 RPDOs + SYNC packed into a preallocated ``FrameBatch`` and sent with ``send_frames``, the
  6 TPDOs' datagram received undecoded with ``recv_frames`` (another bus instance in this process
  stands in for the drives and answers with one datagram, as the target does);
- ``ipc_send_receive_messages``: the same through python-can's message API (``send_batch``, one
  ``recv`` and one ``can.Message`` per frame: every other bus's path), not in the parts' sum;
- ``telemetry_handoff``: ``ZenohTelemetry.offer_state`` (the state payload encoded, queued);
- ``record``: ``RunRecord.add``;
- ``onnx_1node``: ``run_with_iobinding`` of y = x + x on one (1, 6) row.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import numpy as np

from drivers.cia402 import frames as fr
from drivers.ipc.frame import FrameBatch
from hil_runtime.record import RunRecord
from hil_runtime.runtime import Runtime
from hil_runtime.telemetry.config import TelemetryConfig
from hil_runtime.telemetry.publisher import ZenohTelemetry


def one_node_runner(tmp: Path) -> Callable[[], object]:
    """The bare onnxruntime call: a one-node graph, bound rows (lmpc_graphs.py's floor, as bench_lmpc.py)."""
    from lmpc_graphs import bound_runner, make_session, one_node_graph

    path = tmp / "add_1.onnx"
    one_node_graph(path, width=6, nodes=1)
    return bound_runner(make_session(str(path)), 6)


@contextmanager
def ipc_pair(tmp: Path) -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """Two ipc bus instances on one bus directory: the runtime's end and the drives' end."""
    channel = str(tmp / "bus")
    master = can.Bus(interface="ipc", channel=channel, fd=True)
    drives = can.Bus(interface="ipc", channel=channel, fd=True)
    try:
        yield master, drives
    finally:
        master.shutdown()
        drives.shutdown()


def _ipc_runner(master: can.BusABC, drives: can.BusABC, n: int, raw: bool) -> Callable[[], object]:
    rpdos = [
        can.Message(arbitration_id=0x200 + i + 1, data=bytearray(fr.RPDO_LENGTH), is_extended_id=False, is_fd=True)
        for i in range(n)
    ]
    frames = [*rpdos, can.Message(arbitration_id=0x80, data=b"\x01", is_extended_id=False, is_fd=True)]
    tpdo = fr.encode_tpdo_fd_sync(0x0237, 10, 1000, -20, 1)
    answers = [can.Message(arbitration_id=0x180 + i + 1, data=tpdo, is_extended_id=False, is_fd=True) for i in range(n)]
    answer_batch = FrameBatch(answers)
    batch = FrameBatch(frames)
    send_frames = master.send_frames  # type: ignore[attr-defined]  # the ipc bus's raw path
    recv_frames = master.recv_frames  # type: ignore[attr-defined]
    send_batch = master.send_batch  # type: ignore[attr-defined]  # the ipc bus's batch send

    def drives_answer() -> None:  # not timed: what the drives do meanwhile
        while drives.recv_frames(0.0) is not None:  # type: ignore[attr-defined]
            pass
        drives.send_frames(answer_batch)  # type: ignore[attr-defined]  # one datagram, as the target

    def raw_cycle() -> object:
        for payload in batch.payloads[:n]:
            fr.encode_rpdo_into(payload, 0x000F, 123)
        send_frames(batch)
        received = 0
        while received < n:
            got = recv_frames(0.05)
            if got is None:
                break
            received += len(got[1])
        return None

    def message_cycle() -> object:
        send_batch(frames)
        for _ in range(n):
            master.recv(0.05)
        return None

    cycle = raw_cycle if raw else message_cycle
    cycle.before = drives_answer  # type: ignore[attr-defined]  # run untimed before each timed call
    return cycle


def time_parts(runtime: Runtime, rounds: int) -> dict[str, Any]:
    """Each part timed once per round, interleaved, ``rounds`` rounds (the first 100 dropped)."""
    n = runtime.bundle.n_joints
    pipeline = runtime.pipeline
    controller, supervisor, reference = runtime.controller, runtime.supervisor, runtime.reference
    sample = pipeline.sample
    q, qd = sample.q.copy(), sample.qd.copy()
    fresh = np.ones(n, dtype=bool)
    out = np.zeros(n)
    k0 = max(runtime.loop.ref_base - 1, 0)
    tau, tau_fb, fallback = controller.step(q, qd, *reference.at(k0))
    tau, tau_fb = tau.copy(), tau_fb.copy()
    publisher = ZenohTelemetry(
        TelemetryConfig(enabled=True, queue_size=64), runtime.config.robot, {"joints": list(runtime.config.joint_names)}
    )
    record = RunRecord(1, n)
    buffers = [bytearray(fr.RPDO_LENGTH) for _ in range(n)]
    tpdo = bytes(fr.encode_tpdo_fd_sync(0x0237, 10, 1000, -20, 1))

    def policy() -> None:
        controller.step(q, qd, *reference.at(k0))
        controller.commit(out)

    def supervise() -> None:
        supervisor.check_feedback(q, qd, fresh)
        supervisor.select_torque(tau, tau_fb, fallback, out)

    def encode() -> None:
        for buffer in buffers:
            fr.encode_rpdo_into(buffer, 0x000F, 123)

    def decode() -> None:
        for _ in range(n):
            fr.unpack_tpdo_fd_sync(tpdo)

    def add_record() -> None:
        record.n = 0
        record.add(sample, 0.0, 0.0, 0.0)

    with tempfile.TemporaryDirectory() as name, ipc_pair(Path(name)) as (master, drives):
        tmp = Path(name)
        runners: dict[str, Callable[[], object]] = {
            "policy_call": policy,
            "supervisor": supervise,
            "reference": lambda: reference.at(k0),
            "frame_encode": encode,
            "frame_decode": decode,
            "ipc_send_receive": _ipc_runner(master, drives, n, raw=True),
            "ipc_send_receive_messages": _ipc_runner(master, drives, n, raw=False),
            "telemetry_handoff": lambda: publisher.offer_state(sample),
            "record": add_record,
            "onnx_1node": one_node_runner(tmp),
        }
        times = {key: np.zeros(rounds) for key in runners}
        clock = time.perf_counter
        for i in range(rounds):
            for key, run in runners.items():
                before = getattr(run, "before", None)
                if before is not None:
                    before()
                start = clock()
                run()
                times[key][i] = clock() - start
    controller.reset(q)
    supervisor.reset_counters()
    return {key: values[100:] for key, values in times.items()}
