"""Telemetry out of the runtime (ARCHITECTURE.md, contract 3).

The loop talks to a :class:`TelemetrySink` only; every call is made from the loop thread and must
return in microseconds without blocking (a bounded queue to one publisher thread, drop-oldest).
:class:`NullTelemetry` is the sink when telemetry is off.
"""

from hil_runtime.telemetry.sink import NullTelemetry, TelemetrySink

__all__ = ["NullTelemetry", "TelemetrySink"]
