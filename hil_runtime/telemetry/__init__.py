"""Telemetry out of the runtime (docs/architecture.md, contract 3; docs/telemetry.md).

The loop talks to a :class:`TelemetrySink` only; every call is made from the loop thread and must
return in microseconds without blocking (a bounded queue to one publisher thread, drop-oldest).
:class:`NullTelemetry` is the sink when telemetry is off. :func:`make_sink` builds the sink from
the ``telemetry:`` section of the runtime's config (:class:`TelemetryConfig`); the wire format and
its one public decoder are in :mod:`hil_runtime.telemetry.codec`.
"""

from hil_runtime.telemetry.config import TelemetryConfig, TelemetryConfigError, parse_telemetry_config
from hil_runtime.telemetry.factory import make_sink
from hil_runtime.telemetry.sink import CycleState, NullTelemetry, TelemetrySink

__all__ = [
    "NullTelemetry",
    "CycleState",
    "TelemetryConfig",
    "TelemetryConfigError",
    "TelemetrySink",
    "make_sink",
    "parse_telemetry_config",
]
