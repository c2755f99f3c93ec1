"""A stand-in for systemd's ``$NOTIFY_SOCKET``: a Unix datagram socket that keeps every message
the runtime sends (READY=1, STATUS=..., WATCHDOG=1, STOPPING=1) with its arrival time."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path


class NotifyListener:
    """Bound at ``path`` on construction; a thread receives until :meth:`close`."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, str]] = []  # (monotonic arrival, the datagram's text)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="notify", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.messages.append((time.monotonic(), data.decode(errors="replace")))

    def with_key(self, key: str) -> list[tuple[float, dict[str, str]]]:
        """(arrival, fields) of the messages that carry ``key`` (``STATUS``, ``WATCHDOG``, ...)."""
        out = []
        for t, text in list(self.messages):
            fields = dict(line.split("=", 1) for line in text.splitlines() if "=" in line)
            if key in fields:
                out.append((t, fields))
        return out

    def watchdog_times(self) -> list[float]:
        return [t for t, fields in self.with_key("WATCHDOG") if fields["WATCHDOG"] == "1"]

    def saw(self, item: str) -> bool:
        """Whether any message carried the line ``item`` (e.g. ``STOPPING=1``)."""
        return any(item in text.splitlines() for _, text in list(self.messages))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()
