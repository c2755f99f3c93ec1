"""CAN captures with python-can's own writers and readers (docs/formats.md).

``hil run --can-log FILE`` and ``hil target serve --can-log FILE`` wrap their bus in a
:class:`CaptureBus`: every frame sent or received is copied (a tuple of its fields: the driver
reuses its frames' buffers) into a bounded deque on the caller's thread; a writer thread builds
``can.Message`` objects and hands them to ``can.Logger``, which picks the format by suffix:
``.blf`` (Vector binary logging), ``.asc`` (Vector ASCII), ``.log`` (candump -L), ``.csv``.
A full deque drops the frame and counts it (``dropped``): the loop never waits for the disk.
Timestamps are the wall clock when this process sent or received the frame.

:func:`read_capture` reads one back with ``can.LogReader`` and refuses, with one line
(:class:`CaptureError`, exit code 2), what python-can would read silently wrong: a file cut short
(a BLF whose header counts more bytes or objects, a text capture without its last newline, an ASC
without ``End TriggerBlock``), one of another format, or one without frames.
"""

from __future__ import annotations

import collections
import logging
import os
import struct
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import can

from drivers.draining import DrainingWriter

log = logging.getLogger(__name__)

CAPTURE_SUFFIXES = {".blf": "Vector BLF", ".asc": "Vector ASC", ".log": "candump -L", ".csv": "python-can CSV"}

# (time.time(), arbitration id, extended, remote, error, FD, BRS, ESI, data, is_rx)
_Frame = tuple[float, int, bool, bool, bool, bool, bool, bool, bytes, bool]


class CaptureError(ValueError):
    """A capture path or file that cannot be used; one line naming the file, exit code 2."""

    exit_code = 2


def check_capture_path(path: Path, option: str = "--can-log") -> Path:
    """Before the run: a known suffix, a directory that exists and is writable, no directory in the way."""
    if path.suffix.lower() not in CAPTURE_SUFFIXES:
        known = ", ".join(CAPTURE_SUFFIXES)
        raise CaptureError(f"{option} {path}: unknown capture format {path.suffix or '(no suffix)'!r} (use {known})")
    if path.is_dir():
        raise CaptureError(f"{option} {path}: a directory is in the way")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise CaptureError(f"{option} {path}: no directory {parent}")
    probe = parent / f".{path.name}.{os.getpid()}.probe"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise CaptureError(f"{option} {path}: cannot write in {parent} ({exc.strerror or exc})") from None
    return path


class CanCapture(DrainingWriter):
    """A capture file being written by python-can's writer for its suffix, fed by :meth:`tap`.

    Written under a temporary name (same suffix) and renamed into place by :meth:`close`.
    """

    def __init__(self, path: Path | str, queue_size: int = 65_536, drain_period_s: float = 0.01) -> None:
        self.path = check_capture_path(Path(path))
        super().__init__(drain_period_s, "hil-can-log", "CAN capture")
        self.queue_size = queue_size
        self.captured = 0
        self.written = 0
        self.dropped = 0
        self._tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.partial{self.path.suffix}")
        self._logger: Any = can.Logger(str(self._tmp))
        self._frames: collections.deque[_Frame] = collections.deque()
        self._closed = False
        self._start_draining()

    def tap(self, msg: can.Message, is_rx: bool) -> None:
        """Copy one frame (caller's thread: a tuple append, never a wait)."""
        if len(self._frames) >= self.queue_size:
            self.dropped += 1
            return
        self.captured += 1
        self._frames.append(
            (
                time.time(),
                msg.arbitration_id,
                msg.is_extended_id,
                msg.is_remote_frame,
                msg.is_error_frame,
                msg.is_fd,
                msg.bitrate_switch,
                msg.error_state_indicator,
                bytes(msg.data),
                is_rx,
            )
        )

    def _drain(self) -> None:
        frames = self._frames
        write = self._logger.on_message_received
        while frames:
            t, cob_id, extended, remote, error, fd, brs, esi, data, is_rx = frames.popleft()
            write(
                can.Message(
                    timestamp=t,
                    arbitration_id=cob_id,
                    is_extended_id=extended,
                    is_remote_frame=remote,
                    is_error_frame=error,
                    is_fd=fd,
                    bitrate_switch=brs,
                    error_state_indicator=esi,
                    data=data,
                    dlc=len(data),
                    is_rx=is_rx,
                    channel=0,
                    check=False,
                )
            )
            self.written += 1

    def close(self) -> None:
        """Write what is queued, close the writer, rename into place. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._stop_draining()
        finally:
            self._logger.stop()
        os.replace(self._tmp, self.path)
        if self.dropped or self.error is not None:
            log.warning(
                "CAN capture %s: %d frames written, %d dropped%s",
                self.path,
                self.written,
                self.dropped,
                f", writer failed: {self.error!r}" if self.error is not None else "",
            )

    def abandon(self) -> None:
        """Stop without keeping anything (a run refused before it started)."""
        if self._closed:
            return
        self._closed = True
        self._stop_draining(write_rest=False)
        self._logger.stop()
        self._tmp.unlink(missing_ok=True)


class CaptureBus(can.BusABC):
    """A python-can bus that copies every frame it sends or receives to a :class:`CanCapture`.

    Only the public ``send``/``recv`` of the wrapped bus are used; ``send_batch`` is passed on
    where the wrapped bus has one (the bridge, the ipc bus). :meth:`shutdown` shuts both down.
    """

    def __init__(self, bus: can.BusABC, capture: CanCapture) -> None:
        self.bus = bus
        self.capture = capture
        self.channel_info = f"capture of {bus.channel_info}"
        super().__init__(channel=self.channel_info)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.bus.send(msg, timeout)
        self.capture.tap(msg, False)

    def send_batch(self, msgs: Sequence[can.Message]) -> None:
        send_batch = getattr(self.bus, "send_batch", None)
        if send_batch is not None:
            send_batch(msgs)
        else:
            for msg in msgs:
                self.bus.send(msg)
        tap = self.capture.tap
        for msg in msgs:
            tap(msg, False)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self.bus.recv(timeout)
        if msg is not None:
            self.capture.tap(msg, True)
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.bus.recv(timeout), True  # unused: recv above is the one entry

    @property
    def protocol(self) -> can.CanProtocol:
        return self.bus.protocol

    def shutdown(self) -> None:
        try:
            self.bus.shutdown()
        finally:
            self.capture.close()
            super().shutdown()


# --- reading ---------------------------------------------------------------------------------------

_BLF_HEADER = struct.Struct("<4sLBBBBBBBBQQLL")  # python-can's FILE_HEADER prefix: signature .. object count


def _check_complete(path: Path, data: bytes) -> None:
    """What python-can's readers accept silently: a file cut short or of another format."""
    suffix = path.suffix.lower()
    name = CAPTURE_SUFFIXES[suffix]
    if suffix == ".blf":
        if len(data) < _BLF_HEADER.size or data[:4] != b"LOGG":
            raise CaptureError(f"{path}: not a {name} capture (no LOGG header)")
        file_size = _BLF_HEADER.unpack_from(data)[10]
        if file_size != len(data):
            raise CaptureError(f"{path}: truncated {name} capture ({len(data)} of {file_size} bytes)")
        return
    if not data:
        raise CaptureError(f"{path}: empty file")
    if b"\x00" in data[:4096]:
        raise CaptureError(f"{path}: not a {name} capture (binary data)")
    if not data.endswith(b"\n"):
        raise CaptureError(f"{path}: truncated {name} capture (its last line is cut)")
    if suffix == ".asc" and b"End TriggerBlock" not in data[-64:]:
        raise CaptureError(f"{path}: truncated {name} capture (no 'End TriggerBlock')")
    if suffix == ".csv" and not data.startswith(b"timestamp,arbitration_id,"):
        raise CaptureError(f"{path}: not a {name} capture (no header line)")


def read_capture(path: Path) -> Iterator[can.Message]:
    """The frames of a capture, in file order; CaptureError (one line) when it cannot be trusted."""
    if path.suffix.lower() not in CAPTURE_SUFFIXES:
        known = ", ".join(CAPTURE_SUFFIXES)
        raise CaptureError(f"{path}: unknown capture format {path.suffix or '(no suffix)'!r} (use {known})")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such file") from None
    except OSError as exc:
        raise CaptureError(f"{path}: cannot read ({exc.strerror or exc})") from None
    _check_complete(path, data)
    name = CAPTURE_SUFFIXES[path.suffix.lower()]
    count = 0
    try:
        reader = can.LogReader(str(path))
        try:
            for msg in reader:
                count += 1
                yield msg
        finally:
            reader.stop()
    except CaptureError:
        raise
    except Exception as exc:  # noqa: BLE001 - python-can's readers raise many kinds on bad input
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CaptureError(f"{path}: not a readable {name} capture (frame {count + 1}: {reason})") from None
    if count == 0:
        raise CaptureError(f"{path}: no CAN frames (not a {name} capture?)")
