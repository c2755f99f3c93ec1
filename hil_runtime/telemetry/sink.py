"""The contract between the control loop and telemetry: :class:`TelemetrySink` and the one
per-cycle :class:`CycleState` that the loop hands on (to telemetry and to its run record).

Call order, all from the loop's thread:

    sink.start()                                   # before ACTIVE: session open, publishers warm
    sink.set_status("ACTIVE", fault=None)          # on every lifecycle change
    sink.offer_state(sample)                       # per cycle (a CycleState)
    sink.offer_stats(stats)                        # about 1 Hz
    sink.event("fault", cycle, "heartbeat lost: node 3")
    sink.close()                                   # on shutdown (drains briefly, never hangs)

``offer_state`` copies what it keeps (the loop reuses one sample and its buffers) and never
blocks: when the publisher falls behind, the oldest sample is dropped and counted.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(slots=True)
class CycleState:
    """One cycle's state as the loop hands it on. Arrays: float64, one value per joint (the
    telemetry ``state`` layout, hil_runtime.telemetry.codec.STATE_FIELDS)."""

    seq: int  # state samples offered since start (activation rows included)
    t_ns: int  # monotonic clock when the sample was made
    q: np.ndarray  # measured position [rad]
    qd: np.ndarray  # measured velocity [rad/s]
    q_ref: np.ndarray  # reference position [rad]
    qd_ref: np.ndarray  # reference velocity [rad/s]
    tau: np.ndarray  # the torque command the supervisor chose [N*m]
    tau_fb: np.ndarray  # the feedback law's torque [N*m]
    fallback: float  # share of joints on the law's torque (emulator not trusted)
    compute_s: float  # the cycle's work up to the hand-off

    @classmethod
    def zeros(cls, n_joints: int) -> CycleState:
        z = np.zeros(n_joints)
        return cls(0, 0, z, z, z, z, z, z, 0.0, 0.0)


@runtime_checkable
class TelemetrySink(Protocol):
    def start(self) -> None: ...

    def offer_state(self, sample: CycleState) -> None: ...

    def offer_stats(self, stats: Mapping[str, float]) -> None: ...

    def set_status(self, state: str, fault: str | None) -> None: ...

    def event(self, kind: str, cycle: int, detail: str) -> None: ...

    def close(self) -> None: ...


class NullTelemetry:
    """Telemetry off: every call is a no-op."""

    def start(self) -> None:
        pass

    def offer_state(self, sample: CycleState) -> None:
        pass

    def offer_stats(self, stats: Mapping[str, float]) -> None:
        pass

    def set_status(self, state: str, fault: str | None) -> None:
        pass

    def event(self, kind: str, cycle: int, detail: str) -> None:
        pass

    def close(self) -> None:
        pass


class FanOutTelemetry:
    """Several sinks as one (the Zenoh publisher and an MCAP recorder): each call goes to each in
    turn. A sink's close failing does not keep the others from closing; the first error is raised."""

    def __init__(self, *sinks: TelemetrySink) -> None:
        self.sinks = sinks

    def start(self) -> None:
        for sink in self.sinks:
            sink.start()

    def offer_state(self, sample: CycleState) -> None:
        for sink in self.sinks:
            sink.offer_state(sample)

    def offer_stats(self, stats: Mapping[str, float]) -> None:
        for sink in self.sinks:
            sink.offer_stats(stats)

    def set_status(self, state: str, fault: str | None) -> None:
        for sink in self.sinks:
            sink.set_status(state, fault)

    def event(self, kind: str, cycle: int, detail: str) -> None:
        for sink in self.sinks:
            sink.event(kind, cycle, detail)

    def close(self) -> None:
        first: Exception | None = None
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:  # noqa: BLE001 - every sink gets closed; the first error is raised
                first = first or exc
        if first is not None:
            raise first
