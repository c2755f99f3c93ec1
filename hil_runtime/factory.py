"""The public way to build a :class:`~hil_runtime.runtime.Runtime`: on the config's drive bus (or a
given one), with what it reports to wired at construction (the Zenoh telemetry of the config, an
optional second sink such as an MCAP recording), never swapped in afterwards.

``hil run`` (:mod:`hil_runtime.daemon`), the lab (``models/lab``: the HIL experiment, the fault
campaign) and the tests build their runtimes here, as ros2_control's node is the one place that
builds its controller manager::

    runtime = build_runtime(config)                        # DriveBus from config.bus, telemetry per config
    runtime = build_runtime(config, bus, telemetry=False)  # a JointBus of the caller's, no telemetry
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from drivers.joint_bus import JointBus
from hil_runtime.config import RuntimeConfig
from hil_runtime.runtime import Runtime
from hil_runtime.telemetry.sink import FanOutTelemetry, NullTelemetry, TelemetrySink

if TYPE_CHECKING:
    from drivers.drive_bus import DriveBus


def telemetry_sink(config: RuntimeConfig, runtime: Runtime) -> TelemetrySink:
    """The config's telemetry for ``runtime`` (:func:`hil_runtime.telemetry.factory.make_sink`): its
    joints, config and bundle for the queryables, its stats names, the runtime as the controls."""
    from hil_runtime.telemetry.codec import STATS_FIELDS
    from hil_runtime.telemetry.factory import make_sink

    bundle = runtime.bundle
    digest = next(iter(bundle.manifest.files.values()), "")
    info = {
        "joints": list(config.joint_names),
        "config": config.model_dump(mode="json"),
        "bundle": {**bundle.describe(), "bundle_id": f"{bundle.law_name}:{str(digest)[:12]}"},
        "stats_fields": [name for name in runtime.stats() if name not in STATS_FIELDS],  # beyond the standard
    }
    return make_sink(config.telemetry, config.robot, info, controls=runtime)


def runtime_drive_bus(config: RuntimeConfig, can_bus: Any = None) -> DriveBus:
    """The runtime's :class:`drivers.drive_bus.DriveBus` on ``config.bus`` (over ``can_bus`` when
    given). Stale feedback has one budget in the runtime, the supervisor's
    ``safety.max_stale_cycles`` (FAULT stale_feedback): the driver counts none of its own, so which
    fault fires never depends on which of two budgets runs out first."""
    from drivers.drive_bus import DriveBus

    return DriveBus(config.bus.model_copy(update={"max_missed_cycles": None}), bus=can_bus)


def build_runtime(
    config: RuntimeConfig,
    bus: JointBus | None = None,
    *,
    can_bus: Any = None,
    telemetry: bool = True,
    recording: Callable[[Runtime], TelemetrySink] | None = None,
    **kwargs: Any,
) -> Runtime:
    """A runtime for ``config``; no I/O yet (``configure()`` connects).

    ``bus``: the joint bus (default: :func:`runtime_drive_bus`, over ``can_bus`` when given, an open
    python-can bus such as a capture). ``telemetry``: the config's
    telemetry section (off when it is disabled); False: none (``hil run --check``). ``recording``:
    a second sink made for the runtime (it needs its bundle), fed the same calls. ``kwargs``: the
    rest of :class:`Runtime`'s (bundle, notifier, record_cycles, clock, sleep)."""
    if bus is None:
        bus = runtime_drive_bus(config, can_bus)

    def sinks(runtime: Runtime) -> TelemetrySink:
        made = [telemetry_sink(config, runtime)] if telemetry else []
        if recording is not None:
            made.append(recording(runtime))
        if not made:
            return NullTelemetry()
        return made[0] if len(made) == 1 else FanOutTelemetry(*made)

    return Runtime(config, bus, telemetry_for=sinks, **kwargs)


__all__ = ["build_runtime", "runtime_drive_bus", "telemetry_sink"]
