"""systemd's notify protocol (sd_notify(3)): a datagram to ``$NOTIFY_SOCKET``, a few lines.

    notifier = Notifier.from_environment()      # inert when not started by systemd
    notifier.ready("ACTIVE 1000 Hz")            # READY=1 + STATUS=
    notifier.status("FAULT: heartbeat_lost ...")
    notifier.watchdog_if_due(now_s)             # from the loop thread, every cycle: cheap
    notifier.stopping()

A leading ``@`` in the socket path is the abstract namespace. The watchdog is armed only when
``$WATCHDOG_USEC`` is set and ``$WATCHDOG_PID`` is unset or ours; pings go out every
``WATCHDOG_USEC / 2``, and only from the loop thread while it makes progress, so a hung loop stops
them and systemd restarts the service (``Restart=on-failure``). Sending never blocks and never
raises: a missing or full socket costs a counted failure, not the loop.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping


class Notifier:
    def __init__(self, address: str | None, watchdog_usec: int | None = None) -> None:
        self.address = address
        self._sock: socket.socket | None = None
        if address:
            self._target = "\0" + address[1:] if address.startswith("@") else address
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        self.watchdog_interval_s = watchdog_usec / 2e6 if (watchdog_usec and address) else None
        self._next_watchdog_s = 0.0
        self.sent = 0
        self.failed = 0
        self.watchdog_pings = 0

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] | None = None) -> Notifier:
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET") or None
        usec: int | None = None
        pid = env.get("WATCHDOG_PID")
        if env.get("WATCHDOG_USEC") and (not pid or pid == str(os.getpid())):
            try:
                usec = int(env["WATCHDOG_USEC"])
            except ValueError:
                usec = None
            if usec is not None and usec <= 0:
                usec = None
        return cls(address, usec)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, **fields: object) -> bool:
        """One datagram of ``KEY=value`` lines (keys upper-cased)."""
        if self._sock is None:
            return False
        text = "\n".join(f"{key.upper()}={value}" for key, value in fields.items())
        try:
            self._sock.sendto(text.encode(), self._target)
        except OSError:
            self.failed += 1
            return False
        self.sent += 1
        return True

    def ready(self, status: str) -> bool:
        return self.send(ready=1, status=status, mainpid=os.getpid())

    def status(self, text: str) -> bool:
        return self.send(status=text)

    def stopping(self, status: str = "stopping") -> bool:
        return self.send(stopping=1, status=status)

    def watchdog_if_due(self, now_s: float) -> None:
        """WATCHDOG=1 when at least WATCHDOG_USEC / 2 has passed since the last ping."""
        interval = self.watchdog_interval_s
        if interval is None or now_s < self._next_watchdog_s:
            return
        self._next_watchdog_s = now_s + interval
        if self.send(watchdog=1):
            self.watchdog_pings += 1

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
