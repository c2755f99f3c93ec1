"""The ``ipc`` interface back to back, as python-can tests its own transports: buses in one process,
peers joining late, leaving and not reading. Across processes: tests/integration/test_ipc_bus_processes.py."""

from __future__ import annotations

import os
import select
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from drivers.config import TransportConfig
from drivers.ipc import IpcBus, IpcMessage, bus_directory
from drivers.ipc.frame import CAN_ERR_CRTL, CAN_ERR_CRTL_RX_OVERFLOW, FrameBatch
from drivers.transport import open_bus

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the ipc bus is Linux only")


@pytest.fixture
def bus_dir(tmp_path: Path) -> Path:
    return tmp_path / "bus"


@pytest.fixture
def pair(bus_dir: Path) -> Iterator[tuple[IpcBus, IpcBus]]:
    a = IpcBus(bus_dir, fd=True)
    b = IpcBus(bus_dir, fd=True)
    try:
        yield a, b
    finally:
        a.shutdown()
        b.shutdown()


def _msg(
    can_id: int,
    data: bytes = b"",
    *,
    is_extended_id: bool = False,
    is_remote_frame: bool = False,
    is_error_frame: bool = False,
    is_fd: bool = False,
    bitrate_switch: bool = False,
    error_state_indicator: bool = False,
    dlc: int | None = None,
) -> can.Message:
    return can.Message(
        arbitration_id=can_id,
        data=data,
        is_extended_id=is_extended_id,
        is_remote_frame=is_remote_frame,
        is_error_frame=is_error_frame,
        is_fd=is_fd,
        bitrate_switch=bitrate_switch,
        error_state_indicator=error_state_indicator,
        dlc=dlc,
    )


def _recv(bus: can.BusABC, timeout_s: float) -> can.Message:
    """The next frame; fails the test when none arrives within ``timeout_s``."""
    message = bus.recv(timeout_s)
    assert message is not None, f"no frame within {timeout_s} s"
    return message


def _sockets(bus_dir: Path) -> list[str]:
    return sorted(p.name for p in bus_dir.iterdir() if p.name.endswith(".sock"))


def test_opened_by_name_through_python_cans_entry_point(bus_dir: Path) -> None:
    with can.Bus(interface="ipc", channel=str(bus_dir)) as a, can.Bus(interface="ipc", channel=str(bus_dir)) as b:
        assert isinstance(a, IpcBus)
        a.send(_msg(0x10, b"\x01"))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x10 and got.channel == str(bus_dir)


def test_opened_from_the_drivers_transport_config(bus_dir: Path) -> None:
    config = TransportConfig(interface="ipc", channel=str(bus_dir), fd=True, data_bitrate=5_000_000)
    bus = open_bus(config)
    try:
        assert isinstance(bus, IpcBus) and bus.protocol == can.CanProtocol.CAN_FD
    finally:
        bus.shutdown()


def test_a_bare_name_is_a_directory_under_the_users_runtime_dir() -> None:
    assert bus_directory("hil").parts[-2:] == ("hil-can" if os.environ.get("XDG_RUNTIME_DIR") else "can", "hil")
    assert bus_directory("/srv/can") == Path("/srv/can")
    assert bus_directory("./rel") == Path("./rel")


def test_no_message_times_out(pair: tuple[IpcBus, IpcBus]) -> None:
    _, b = pair
    start = time.monotonic()
    assert b.recv(0.1) is None
    assert 0.09 <= time.monotonic() - start < 1.0
    assert b.recv(0) is None


def test_frame_kinds_arrive_intact(pair: tuple[IpcBus, IpcBus]) -> None:
    a, b = pair
    sent = [
        _msg(0x7FF, bytes(range(8))),
        _msg(0x000),
        _msg(0x1ABCDEF0 & 0x1FFFFFFF, b"\xaa", is_extended_id=True),
        _msg(0x601, is_remote_frame=True, dlc=4),
        _msg(0x181, bytes(range(64)), is_fd=True, bitrate_switch=True),
        _msg(0x182, bytes(range(12)), is_fd=True, error_state_indicator=True),
        _msg(0x0040, bytes(8), is_error_frame=True),
    ]
    before = time.time()
    for msg in sent:
        a.send(msg)
    for msg in sent:
        got = b.recv(2.0)
        assert got is not None
        assert got.equals(msg, timestamp_delta=None, check_channel=False, check_direction=False), (got, msg)
        assert got.is_rx and before <= got.timestamp <= time.time()


def test_frames_of_one_sender_keep_their_order_and_none_is_lost(pair: tuple[IpcBus, IpcBus]) -> None:
    a, b = pair
    n = 2000  # below the default 1 MiB queue, so none may be dropped
    for i in range(n):
        a.send(_msg(0x100 + i % 16, i.to_bytes(4, "little")))
    received = [int.from_bytes(_recv(b, 2.0).data, "little") for _ in range(n)]
    assert received == list(range(n))
    assert b.recv(0) is None
    assert a.stats.frames_sent == n and a.stats.frames_dropped == 0 and b.stats.frames_received == n


def test_classical_bus_refuses_to_send_fd_and_ignores_fd_it_receives(bus_dir: Path) -> None:
    fd_bus = IpcBus(bus_dir, fd=True)
    classic = IpcBus(bus_dir)
    try:
        assert classic.protocol == can.CanProtocol.CAN_20
        with pytest.raises(can.CanOperationError, match="CAN FD frame on a classical bus"):
            classic.send(_msg(0x1, bytes(12), is_fd=True))
        fd_bus.send(_msg(0x2, bytes(12), is_fd=True))
        fd_bus.send(_msg(0x3, b"\x01"))
        got = classic.recv(2.0)
        assert got is not None and got.arbitration_id == 0x3
        assert classic.stats.fd_frames_ignored == 1
    finally:
        fd_bus.shutdown()
        classic.shutdown()


def test_a_batch_is_one_datagram_handed_out_frame_by_frame_in_order(bus_dir: Path) -> None:
    """send_batch: one datagram per peer (one wake-up and one system call for a cycle's frames);
    the receiver's recv hands its frames out one by one, in order, classical and FD mixed, with
    the sender; a classical receiver ignores the FD frames of a batch."""
    raw_path = bus_dir / "0-raw.sock"
    bus_dir.mkdir(mode=0o700, exist_ok=True)
    raw = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    raw.bind(os.fspath(raw_path))
    raw.listen(1)
    sender, fd_rx, classic_rx = IpcBus(bus_dir, fd=True), IpcBus(bus_dir, fd=True), IpcBus(bus_dir)
    conn, _ = raw.accept()  # the sender joined the raw listener as a peer
    try:
        batch = [_msg(0x181 + i, bytes([i]) * 12, is_fd=True) for i in range(6)] + [_msg(0x80, b"\x07")]
        sender.send_batch(batch)
        conn.settimeout(2.0)
        datagram = conn.recv(65536)
        assert len(datagram) == 6 * 72 + 16  # the whole batch, one datagram
        got = [_recv(fd_rx, 2.0) for _ in batch]
        assert [(m.arbitration_id, bytes(m.data), m.is_fd) for m in got] == [
            (m.arbitration_id, bytes(m.data), m.is_fd) for m in batch
        ]
        senders = [m.sender for m in got if isinstance(m, IpcMessage)]  # every received frame carries its sender
        assert len(senders) == len(got) and all(s is senders[0] for s in senders) and fd_rx.recv(0) is None
        only = _recv(classic_rx, 2.0)
        assert only.arbitration_id == 0x80 and classic_rx.stats.fd_frames_ignored == 6
        assert sender.stats.frames_sent == 7 and fd_rx.stats.frames_received == 7
        conn.send(datagram[:-3])  # to the sender, a batch cut short: counted, nothing handed out
        assert sender.recv(0.5) is None and sender.stats.malformed == 1
    finally:
        conn.close()
        raw.close()
        for bus in (sender, fd_rx, classic_rx):
            bus.shutdown()


def test_invalid_message_is_a_can_operation_error(pair: tuple[IpcBus, IpcBus]) -> None:
    a, _ = pair
    with pytest.raises(can.CanOperationError, match="exceeds 11 bits"):
        a.send(_msg(0x800))


def test_receive_own_messages_come_back_marked_tx_and_wake_fileno(bus_dir: Path) -> None:
    a = IpcBus(bus_dir, receive_own_messages=True)
    b = IpcBus(bus_dir)
    try:
        a.send(_msg(0x55, b"\x01"))
        readable, _, _ = select.select([a.fileno()], [], [], 2.0)
        assert readable == [a.fileno()]
        own = a.recv(1.0)
        assert own is not None and own.arbitration_id == 0x55 and not own.is_rx
        other = b.recv(1.0)
        assert other is not None and other.is_rx
        b.send(_msg(0x66))
        got = a.recv(1.0)
        assert got is not None and got.arbitration_id == 0x66 and got.is_rx
        assert b.recv(0.05) is None  # without receive_own_messages nothing comes back
    finally:
        a.shutdown()
        b.shutdown()


def test_filters_apply(bus_dir: Path) -> None:
    a = IpcBus(bus_dir)
    b = IpcBus(bus_dir, can_filters=[{"can_id": 0x180, "can_mask": 0x780}])
    try:
        for can_id in (0x201, 0x181, 0x601, 0x182):
            a.send(_msg(can_id))
        assert [_recv(b, 1.0).arbitration_id for _ in range(2)] == [0x181, 0x182]
        assert b.recv(0.05) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_notifier_receives_through_fileno(pair: tuple[IpcBus, IpcBus]) -> None:
    a, b = pair
    assert b.fileno() >= 0
    reader = can.BufferedReader()
    notifier = can.Notifier(b, [reader], timeout=0.1)
    try:
        for i in range(10):
            a.send(_msg(0x300 + i))
        got = [reader.get_message(2.0) for _ in range(10)]
        assert [m.arbitration_id for m in got if m is not None] == [0x300 + i for i in range(10)]
    finally:
        notifier.stop()


def test_many_peers_each_see_every_other(bus_dir: Path) -> None:
    buses = [IpcBus(bus_dir) for _ in range(8)]
    try:
        for i, bus in enumerate(buses):
            for k in range(3):
                bus.send(_msg(0x100 + i, bytes([k])))
        for i, bus in enumerate(buses):
            got = [_recv(bus, 2.0) for _ in range(3 * 7)]
            by_sender: dict[int, list[int]] = {}
            for m in got:
                by_sender.setdefault(m.arbitration_id, []).append(m.data[0])
            assert sorted(by_sender) == [0x100 + j for j in range(8) if j != i]
            assert all(seq == [0, 1, 2] for seq in by_sender.values())  # each sender's order kept
            assert bus.recv(0) is None
            assert bus.peer_count == 7
    finally:
        for bus in buses:
            bus.shutdown()
    assert _sockets(bus_dir) == []


def test_late_joiner_gets_frames_sent_after_it_opened_even_from_a_peer_that_never_reads(bus_dir: Path) -> None:
    sender = IpcBus(bus_dir)  # never calls recv: it takes newcomers in on its next send
    try:
        sender.send(_msg(0x1))  # nobody there yet: lost, as on a bus with no other node
        late = IpcBus(bus_dir)
        try:
            sender.send(_msg(0x2))
            got = late.recv(2.0)
            assert got is not None and got.arbitration_id == 0x2
            assert late.recv(0.05) is None
        finally:
            late.shutdown()
    finally:
        sender.shutdown()


def test_a_peer_that_leaves_removes_only_its_socket_and_the_others_go_on(bus_dir: Path) -> None:
    a, b, c = IpcBus(bus_dir), IpcBus(bus_dir), IpcBus(bus_dir)
    try:
        assert len(_sockets(bus_dir)) == 3
        b.shutdown()
        assert len(_sockets(bus_dir)) == 2
        a.send(_msg(0x7))
        got = c.recv(2.0)
        assert got is not None and got.arbitration_id == 0x7
        assert c.recv(0.05) is None
        c.send(_msg(0x8))
        assert a.recv(2.0) is not None
        assert a.peer_count == 1 and a.stats.peers_left == 1
        b.shutdown()  # twice: harmless
        with pytest.raises(can.CanOperationError, match="shut down"):
            b.send(_msg(0x9))
    finally:
        a.shutdown()
        c.shutdown()


def test_asyncio_notifier_reads_through_fileno(pair: tuple[IpcBus, IpcBus]) -> None:
    import asyncio

    a, b = pair

    async def main() -> list[int]:
        reader = can.AsyncBufferedReader()
        notifier = can.Notifier(b, [reader], loop=asyncio.get_running_loop())  # add_reader(b.fileno())
        try:
            for i in range(5):
                a.send(_msg(0x400 + i))
            return [(await asyncio.wait_for(reader.get_message(), 2.0)).arbitration_id for _ in range(5)]
        finally:
            notifier.stop()

    assert asyncio.run(main()) == [0x400 + i for i in range(5)]


def test_shutdown_removes_its_socket_only_if_the_path_is_still_its_socket(bus_dir: Path) -> None:
    bus = IpcBus(bus_dir)
    (own,) = _sockets(bus_dir)
    (bus_dir / own).unlink()
    (bus_dir / own).write_text("someone else's file now")  # e.g. a stale-socket sweep raced us
    bus.shutdown()
    assert (bus_dir / own).read_text() == "someone else's file now"


def test_send_and_receive_from_two_threads_while_peers_come_and_go(bus_dir: Path) -> None:
    a = IpcBus(bus_dir)
    b = IpcBus(bus_dir)
    n = 3000
    received: list[int] = []

    def reader() -> None:
        while len(received) < n:
            msg = b.recv(2.0)
            if msg is None:
                return
            if msg.arbitration_id == 0x123:
                received.append(int.from_bytes(msg.data, "little"))

    thread = threading.Thread(target=reader)
    thread.start()
    try:
        for i in range(n):
            a.send(_msg(0x123, i.to_bytes(2, "little")))
            if i % 500 == 0:
                IpcBus(bus_dir).shutdown()  # a peer joins and leaves mid-stream
    finally:
        thread.join(10)
        a.shutdown()
        b.shutdown()
    assert received == list(range(n))
    assert a.stats.frames_dropped == 0


def test_shutdown_wakes_a_reader_blocked_without_timeout(pair: tuple[IpcBus, IpcBus]) -> None:
    _, b = pair
    raised: list[BaseException] = []

    def reader() -> None:
        try:
            b.recv()
        except can.CanOperationError as exc:
            raised.append(exc)

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    time.sleep(0.1)
    b.shutdown()
    thread.join(2.0)
    assert not thread.is_alive() and raised and "shut down" in str(raised[0])


def test_files_in_the_directory_that_are_not_live_peers(bus_dir: Path) -> None:
    bus_dir.mkdir()
    (bus_dir / "notes.sock").write_text("a regular file named like a socket")  # refused, not removed
    (bus_dir / "README").write_text("ignored")
    bus = IpcBus(bus_dir)
    try:
        assert bus.peer_count == 0 and bus.stats.stale_sockets_removed == 0
        assert (bus_dir / "notes.sock").is_file()
    finally:
        bus.shutdown()
    assert sorted(p.name for p in bus_dir.iterdir()) == ["README", "notes.sock"]


def test_a_too_long_path_is_refused_with_a_clear_error(tmp_path: Path) -> None:
    deep = tmp_path / ("d" * 100)
    with pytest.raises(can.CanInitializationError, match="longer than 107 bytes"):
        IpcBus(deep)


def test_a_slow_reader_loses_frames_without_blocking_the_sender_and_is_told(bus_dir: Path) -> None:
    sender = IpcBus(bus_dir, queue_bytes=4096)  # the kernel's floor: a few frames per peer
    slow = IpcBus(bus_dir)
    fast = IpcBus(bus_dir)
    try:
        sender.send(_msg(0x1))  # takes both in
        assert slow.recv(1.0) is not None and fast.recv(1.0) is not None
        n = 2000
        start = time.perf_counter()
        for i in range(n):
            sender.send(_msg(0x200, i.to_bytes(2, "little")))
            fast_msg = fast.recv(1.0)  # the fast reader keeps up and gets every frame
            assert fast_msg is not None and int.from_bytes(fast_msg.data, "little") == i
        elapsed_s = time.perf_counter() - start
        assert elapsed_s < 5.0  # never waited on the slow peer
        assert sender.stats.frames_dropped > 0
        # The slow reader drains what fitted, in order; then the overflow is reported once space frees.
        first = []
        while (msg := slow.recv(0.05)) is not None:
            first.append(msg)
        assert first and all(not m.is_error_frame for m in first)
        seq = [int.from_bytes(m.data, "little") for m in first]
        assert seq == sorted(seq) and seq[0] == 0
        sender.send(_msg(0x201, b"\x00\x00"))
        overflow = slow.recv(1.0)
        assert overflow is not None and overflow.is_error_frame and overflow.arbitration_id == CAN_ERR_CRTL
        assert overflow.data[1] == CAN_ERR_CRTL_RX_OVERFLOW
        after = slow.recv(1.0)
        assert after is not None and after.arbitration_id == 0x201
    finally:
        for bus in (sender, slow, fast):
            bus.shutdown()


def test_a_frame_batch_goes_out_as_encoded_and_recv_frames_returns_it_undecoded(bus_dir: Path) -> None:
    """The hot path: a FrameBatch encoded once, its payloads rewritten in place between sends (the
    datagram is never re-encoded); recv_frames returns what recv would hand out frame by frame
    (identifier, data, FD flag, the sender), in order; a classical bus drops the FD frames."""
    sender, fd_rx, classic_rx = IpcBus(bus_dir, fd=True), IpcBus(bus_dir, fd=True), IpcBus(bus_dir)
    try:
        batch = FrameBatch([_msg(0x201 + i, bytes(12), is_fd=True) for i in range(3)] + [_msg(0x80, b"\x01")])
        for cycle in (1, 2):
            for i, payload in enumerate(batch.payloads[:3]):
                payload[:] = bytes([cycle * 10 + i]) * 12
            batch.payloads[3][0] = cycle
            sender.send_frames(batch)
            got = fd_rx.recv_frames(2.0)
            assert got is not None
            who, frames = got
            assert who is not None and who.pid == os.getpid()
            assert frames == [(0x201 + i, bytes([cycle * 10 + i]) * 12, True) for i in range(3)] + [
                (0x80, bytes([cycle]), False)
            ]
            classic = classic_rx.recv_frames(2.0)
            assert classic is not None and classic[1] == [(0x80, bytes([cycle]), False)]
        assert fd_rx.recv_frames(0.05) is None
        assert fd_rx.stats.frames_received == 8 and classic_rx.stats.fd_frames_ignored == 6
        assert sender.stats.frames_sent == 8
        with pytest.raises(can.CanOperationError):
            IpcBus(bus_dir).send_frames(batch)  # FD frames on a classical bus
    finally:
        for bus in (sender, fd_rx, classic_rx):
            bus.shutdown()


def test_recv_frames_first_hands_out_what_recv_left_of_a_batch(pair: tuple[IpcBus, IpcBus]) -> None:
    a, b = pair
    a.send_batch([_msg(0x181, b"\x01"), _msg(0x182, b"\x02"), _msg(0x183, b"\x03")])
    a.send(_msg(0x184, b"\x04"))
    assert _recv(b, 2.0).arbitration_id == 0x181
    rest = [b.recv_frames(1.0), b.recv_frames(1.0), b.recv_frames(1.0)]
    assert [frames for _, frames in filter(None, rest)] == [
        [(0x182, b"\x02", False)],
        [(0x183, b"\x03", False)],
        [(0x184, b"\x04", False)],
    ]
