"""What a fault case observes besides the runtime itself: the telemetry as a subscriber sees it
(:class:`TelemetryWatch`) and the torque the driver puts on the bus (:class:`RpdoTap`)."""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

import numpy as np

# --- telemetry, as a subscriber sees it -----------------------------------------------------------


class TelemetryWatch:
    """A subscriber on the runtime's ``events``, ``status`` and ``state`` (counts only)."""

    def __init__(self, port: int, robot: str = "ur5_paper") -> None:
        from hil_runtime.telemetry.subscriber import TelemetryClient

        self.client = TelemetryClient.open(connect=[f"tcp/127.0.0.1:{port}"], robot=robot, timeout_s=10.0)
        self.schema = self.client.schema()
        self.events: list[dict[str, Any]] = []
        self.statuses: list[dict[str, Any]] = []
        self.states = 0
        self._lock = threading.Lock()
        self.client.subscribe("events", self._on_event)
        self.client.subscribe("status", self._on_status)
        self.client.subscribe("state", self._on_state)
        # Zenoh routes a new subscription within milliseconds, not at once: an event published
        # before then would not reach it. The status is republished every stats period: once one
        # has arrived, so will everything after it.
        deadline = time.monotonic() + 5.0
        while not self.statuses and time.monotonic() < deadline:
            time.sleep(0.01)

    def _on_event(self, payload: bytes) -> None:
        _, body = self.schema.decode_event(payload)
        with self._lock:
            self.events.append({**body, "t": time.monotonic()})

    def _on_status(self, payload: bytes) -> None:
        _, body = self.schema.decode_status(payload)
        with self._lock:
            self.statuses.append(body)

    def _on_state(self, _payload: bytes) -> None:
        self.states += 1

    def find_event(self, kinds: tuple[str, ...], since_s: float, text: str = "") -> dict[str, Any] | None:
        with self._lock:
            for event in self.events:
                if event["t"] >= since_s and event.get("kind") in kinds and text in str(event.get("detail", "")):
                    return event
        return None

    def wait_event(
        self, kinds: tuple[str, ...], since_s: float, timeout_s: float, text: str = ""
    ) -> dict[str, Any] | None:
        deadline = time.monotonic() + timeout_s
        while True:
            found = self.find_event(kinds, since_s, text)
            if found is not None or time.monotonic() >= deadline:
                return found
            time.sleep(0.02)

    def saw_status(self, state: str) -> bool:
        with self._lock:
            return any(s.get("state") == state for s in self.statuses)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.client.close()


# --- the torque on the bus ---------------------------------------------------------------------------


class RpdoTap:
    """Every RPDO on a python-can virtual channel: the largest |torque| / limit after a mark."""

    def __init__(self, channel: str, permille_per_nm: np.ndarray, limit_nm: np.ndarray) -> None:
        import can

        self._bus = can.Bus(interface="virtual", channel=channel)
        self._permille_per_nm = permille_per_nm
        self._limit = limit_nm
        self.mark_s = float("inf")
        self.frames_after = 0
        self.max_ratio_after = 0.0
        self.max_nm_after = np.zeros(len(limit_nm))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rpdo-tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from drivers.cia402 import frames as fr

        n = len(self._limit)
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(0.05)
            except Exception:  # noqa: BLE001 - the channel closed under us: nothing more to see
                return
            if msg is None:
                continue
            node = msg.arbitration_id - fr.RPDO1_BASE
            if not 1 <= node <= n:
                continue
            if time.monotonic() < self.mark_s:
                continue
            try:
                permille = fr.decode_rpdo(bytes(msg.data)).target_torque_permille
            except Exception:  # noqa: BLE001 - a wrong-length frame of a fault case
                continue
            torque = abs(permille / self._permille_per_nm[node - 1])
            self.frames_after += 1
            self.max_nm_after[node - 1] = max(self.max_nm_after[node - 1], torque)
            self.max_ratio_after = max(self.max_ratio_after, torque / self._limit[node - 1])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        with contextlib.suppress(Exception):
            self._bus.shutdown()
