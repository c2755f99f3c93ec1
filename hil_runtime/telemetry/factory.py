"""``make_sink``: the one place the runtime turns its ``telemetry:`` config into a sink."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from hil_runtime.telemetry.config import TelemetryConfig, TelemetryConfigError
from hil_runtime.telemetry.sink import NullTelemetry, TelemetrySink


def make_sink(
    config: TelemetryConfig,
    robot: str,
    info: Mapping[str, Any],
    controls: Any | None = None,
) -> TelemetrySink:
    """The sink the loop calls: :class:`NullTelemetry` when disabled, else a Zenoh publisher.

    ``robot``: the runtime's robot name (the key chunk in ``hil/<robot>/``, unless the config
    names one). ``info``: ``joints`` (names, in the bus's order; required), ``config`` (a JSON-able
    summary of the runtime's config), ``bundle`` (manifest summary and sha256 of its files;
    ``bundle_id`` goes into status), optional ``stats_fields`` (stats names beyond
    :data:`~hil_runtime.telemetry.codec.STATS_FIELDS`). ``controls``: an object with
    ``request_stop()`` and ``request_reset()`` (thread-safe: called from a Zenoh thread); used only
    when ``config.controls_enabled``. Nothing is opened until ``sink.start()``.
    """
    if not config.enabled:
        return NullTelemetry()
    from hil_runtime.telemetry.publisher import TelemetryControls, ZenohTelemetry

    if config.controls_enabled:
        if not isinstance(controls, TelemetryControls):
            raise TelemetryConfigError(
                "telemetry.controls_enabled: the runtime passed no controls (request_stop/request_reset)"
            )
        return ZenohTelemetry(config, robot, info, controls)
    return ZenohTelemetry(config, robot, info, None)
