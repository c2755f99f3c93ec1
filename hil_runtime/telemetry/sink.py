"""The contract between the control loop and telemetry: :class:`TelemetrySink`.

Call order, all from the loop's thread:

    sink.start()                                   # before ACTIVE: session open, publishers warm
    sink.set_status("ACTIVE", fault=None)          # on every lifecycle change
    sink.offer_state(seq, t_ns, q, qd, q_ref, qd_ref, tau, tau_fb, fallback, compute_s)  # per cycle
    sink.offer_stats(stats)                        # about 1 Hz
    sink.event("fault", cycle, "heartbeat lost: node 3")
    sink.close()                                   # on shutdown (drains briefly, never hangs)

``offer_state`` copies the arrays (the caller reuses its buffers) and never blocks: when the
publisher falls behind, the oldest sample is dropped and counted.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class TelemetrySink(Protocol):
    def start(self) -> None: ...

    def offer_state(
        self,
        seq: int,
        t_ns: int,
        q: np.ndarray,
        qd: np.ndarray,
        q_ref: np.ndarray,
        qd_ref: np.ndarray,
        tau: np.ndarray,
        tau_fb: np.ndarray,
        fallback: float,
        compute_s: float,
    ) -> None: ...

    def offer_stats(self, stats: Mapping[str, float]) -> None: ...

    def set_status(self, state: str, fault: str | None) -> None: ...

    def event(self, kind: str, cycle: int, detail: str) -> None: ...

    def close(self) -> None: ...


class NullTelemetry:
    """Telemetry off: every call is a no-op."""

    def start(self) -> None:
        pass

    def offer_state(
        self,
        seq: int,
        t_ns: int,
        q: np.ndarray,
        qd: np.ndarray,
        q_ref: np.ndarray,
        qd_ref: np.ndarray,
        tau: np.ndarray,
        tau_fb: np.ndarray,
        fallback: float,
        compute_s: float,
    ) -> None:
        pass

    def offer_stats(self, stats: Mapping[str, float]) -> None:
        pass

    def set_status(self, state: str, fault: str | None) -> None:
        pass

    def event(self, kind: str, cycle: int, detail: str) -> None:
        pass

    def close(self) -> None:
        pass
