"""``hil drives scan | check | jog``: commissioning real (or emulated) CiA 402 drives.

- ``scan``: every node answering on the bus, its NMT state, device type (CiA 402?), identity and
  supported modes (cyclic synchronous torque?), as a table; writes nothing.
- ``check``: the config's drives against their own EDS/DCF offline (objects, access, PDO mapping,
  CST, scaling, reactions, SDO init entries, COB-IDs), then, unless ``--offline``, the start-up
  ``hil run`` does (configuration, no drive enabled) and what the drives hold afterwards.
- ``jog``: one joint, a small torque for a few seconds, the supervisor's position and velocity
  limits checked every cycle; a quick stop at the end, on a limit and on Ctrl-C.

Bad input (config, EDS, a drive that is not what the config says) is one line naming the file,
node and object, exit 2, and no drive is enabled.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer

drives_app = typer.Typer(
    help="Commission CiA 402 drives: scan the bus, check a config, jog a joint.", no_args_is_help=True
)

ConfigOption = Annotated[
    Path, typer.Option("--config", "--bus", help="runtime config (bus: section) or a drive-bus config")
]
JOG_MAX_FRACTION = 0.25  # a jog's torque is at most this fraction of the joint's max torque
JOG_MAX_S = 30.0


class JogError(RuntimeError):
    """The jog stopped on a limit or a drive error (the drive was quick-stopped first)."""

    exit_code = 3


def _load_bus(path: Path) -> tuple[Any, Any]:
    """(DriveBusConfig, the runtime config or None) from either kind of file."""
    from drivers.config import parse_drive_bus_config, read_yaml_config
    from drivers.errors import DriveConfigError

    data = read_yaml_config(path, DriveConfigError, "a config")
    if isinstance(data, dict) and "bus" in data:
        from hil_runtime.config import load_runtime_config

        runtime = load_runtime_config(path)
        return runtime.bus, runtime
    if not isinstance(data, dict):
        raise DriveConfigError(f"{path}: expected a mapping (a runtime config or a drive-bus config)")
    return parse_drive_bus_config(data, str(path), path.resolve().parent), None


def _console(console_type: Any) -> Any:
    """A console at least 150 columns wide: the tables stay readable when piped to a file."""
    return console_type(width=max(150, console_type().width))


def _hex(value: int | None, width: int = 8) -> str:
    return "-" if value is None else f"0x{value:0{width}X}"


@drives_app.command("scan")
def scan(
    config: Annotated[
        Path | None, typer.Option("--config", "--bus", help="take the bus (transport) from this config")
    ] = None,
    interface: Annotated[str | None, typer.Option(help="python-can interface (virtual, ipc, socketcan, ...)")] = None,
    channel: Annotated[str | None, typer.Option(help="its channel (ipc: the bus directory)")] = None,
    first: Annotated[int, typer.Option(help="first node id to ask", min=1, max=127)] = 1,
    last: Annotated[int, typer.Option(help="last node id to ask", min=1, max=127)] = 127,
    wait_s: Annotated[float, typer.Option(help="how long answers are awaited", min=0.05, max=10.0)] = 0.5,
) -> None:
    """Every node on the bus: NMT state, device type (CiA 402?), identity 0x1018, modes 0x6502."""
    from rich.console import Console
    from rich.table import Table

    from drivers.config import TransportConfig
    from drivers.errors import DriveConfigError
    from drivers.scan import scan_nodes
    from drivers.transport import open_bus

    if config is not None:
        transport = _load_bus(config)[0].transport
    elif interface is not None:
        try:
            transport = TransportConfig.model_validate({"interface": interface, "channel": channel or "hil"})
        except ValueError as exc:
            raise DriveConfigError(f"--interface/--channel: {' '.join(str(exc).split())}") from None
    else:
        raise typer.BadParameter("give --config FILE or --interface NAME [--channel CHANNEL]")
    if last < first:
        raise typer.BadParameter(f"--last {last} is below --first {first}")
    bus = open_bus(transport)
    try:
        nodes = scan_nodes(bus, range(first, last + 1), wait_s)
    finally:
        bus.shutdown()
    table = Table(title=f"nodes on {transport.interface}:{transport.channel} (ids {first}-{last})")
    for column in ("node", "NMT", "device type", "CiA 402", "vendor", "product", "revision", "serial", "CST"):
        table.add_column(column)
    for n in nodes:
        cst = "-" if n.cst is None else ("yes" if n.cst else "no")
        table.add_row(
            str(n.node_id),
            n.nmt_state,
            _hex(n.device_type),
            "yes" if n.is_402 else f"no (profile {n.profile})",
            _hex(n.vendor_id),
            _hex(n.product_code),
            _hex(n.revision),
            _hex(n.serial),
            cst,
        )
    _console(Console).print(table)
    print(f"{len(nodes)} node(s) answered")


@drives_app.command("check")
def check(
    config: ConfigOption,
    offline: Annotated[bool, typer.Option("--offline", help="the EDS checks only: touch no bus")] = False,
) -> None:
    """Each drive against its EDS (objects, access, PDO mapping, CST, scaling, reactions), then on the bus."""
    from rich.console import Console
    from rich.table import Table

    from drivers.eds_check import check_bus, errors, raise_first_error

    bus_config, _ = _load_bus(config)
    findings = check_bus(bus_config, str(config))
    console = _console(Console)
    _print_findings(console, Table, "EDS (offline)", findings)
    raise_first_error(findings)  # nothing was written to any drive
    if offline:
        print(f"{len(bus_config.joints)} drive(s): the EDS checks passed (offline)")
        return
    from drivers.drive_bus import DriveBus
    from drivers.scan import read_back

    bus = DriveBus(bus_config)
    try:
        bus.connect()  # the start-up hil run does: configured, NMT operational, none enabled
        online = read_back(bus)
    finally:
        bus.close()
    _print_findings(console, Table, "on the bus (after start-up, no drive enabled)", online)
    raise_first_error(online)
    bad = errors(findings)
    print(f"{len(bus_config.joints)} drive(s) checked: {len(bad)} error(s)")


def _print_findings(console: Any, table_type: Any, title: str, findings: list[Any]) -> None:
    """One table: a row per finding, drives in node order (the EDS named once per drive)."""
    table = table_type(title=title)
    for column in ("node", "EDS/DCF", "", "object", "finding"):
        table.add_column(column)
    last = None
    for f in sorted(findings, key=lambda f: f.node_id):
        first = f.node_id != last
        last = f.node_id
        mark = {"ok": "ok", "warning": "warn", "error": "ERROR"}[f.level]
        table.add_row(str(f.node_id) if first else "", Path(f.source).name if first else "", mark, f.obj, f.message)
    console.print(table)


@drives_app.command("jog")
def jog(
    config: Annotated[Path, typer.Option("--config", help="runtime config (its bundle gives the limits)")],
    joint: Annotated[str, typer.Option("--joint", help="joint name (or its 0-based index)")],
    torque_nm: Annotated[float, typer.Option("--torque-nm", help="constant torque, N·m")],
    seconds: Annotated[float, typer.Option("--seconds", help="how long, s")] = 1.0,
) -> None:
    """One joint, a small torque, the supervisor's limits active; quick stop at the end or on Ctrl-C."""
    import math

    import numpy as np

    from drivers.drive_bus import DriveBus
    from drivers.eds_check import check_bus, raise_first_error
    from hil_runtime.config import RuntimeConfigError, load_runtime_config
    from hil_runtime.loading import load_bundle_for, safety_limits_for
    from hil_runtime.supervisor import SafetyLimits, Supervisor

    runtime = load_runtime_config(config)
    names = runtime.joint_names
    index = names.index(joint) if joint in names else (int(joint) if joint.isdigit() else -1)
    if not 0 <= index < len(names):
        raise RuntimeConfigError(f"{config}: --joint {joint!r}: not one of {', '.join(names)}")
    drive = runtime.bus.joints[index]
    limit_nm = JOG_MAX_FRACTION * drive.max_torque_nm
    if not math.isfinite(torque_nm) or abs(torque_nm) > limit_nm:
        raise RuntimeConfigError(
            f"{config}: --torque-nm {torque_nm}: a jog takes at most {limit_nm:g} N·m on {drive.name} "
            f"({JOG_MAX_FRACTION:.0%} of its max_torque_nm)"
        )
    if not (math.isfinite(seconds) and 0 < seconds <= JOG_MAX_S):
        raise RuntimeConfigError(f"{config}: --seconds {seconds}: must be in (0, {JOG_MAX_S:g}]")
    raise_first_error(check_bus(runtime.bus, str(config)))  # every drive of the config, before any is touched
    full = safety_limits_for(runtime, load_bundle_for(runtime))
    one = slice(index, index + 1)
    limits = SafetyLimits(
        full.position_lower_rad[one],
        full.position_upper_rad[one],
        full.velocity_limit_rad_s[one],
        full.torque_limit_nm[one],
        full.max_stale_cycles,
    )
    supervisor = Supervisor(limits, (drive.name,))
    bus = DriveBus(runtime.bus.model_copy(update={"joints": (drive,)}))  # only this drive is touched
    period_s = runtime.period_s
    cycles = max(1, round(seconds / period_s))
    command = np.array([torque_nm])
    try:
        bus.connect()
        feedback = bus.enable(np.zeros(1))
        start_rad = float(feedback.position_rad[0])
        peak_rad_s = 0.0
        deadline = time.monotonic()
        for _ in range(cycles):
            feedback = bus.exchange(command)
            fault = supervisor.check_feedback(feedback.position_rad, feedback.velocity_rad_s, feedback.fresh)
            if fault is not None:
                bus.quick_stop()
                raise JogError(f"{drive.name}: {fault}: quick-stopped")
            peak_rad_s = max(peak_rad_s, abs(float(feedback.velocity_rad_s[0])))
            deadline += period_s
            pause = deadline - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        states = bus.quick_stop()
        end_rad = float(feedback.position_rad[0])
    finally:
        if bus.enabled:  # Ctrl-C or a drive error: stop before anything else
            bus.quick_stop()
        bus.close()
    print(
        f"{drive.name} (node {drive.node_id}): {torque_nm:g} N·m for {cycles} cycles: "
        f"{math.degrees(start_rad):.3f}° -> {math.degrees(end_rad):.3f}°, peak {math.degrees(peak_rad_s):.2f}°/s; "
        f"quick-stopped ({states[0].value})"
    )


def register(app: typer.Typer) -> None:
    app.add_typer(drives_app, name="drives")
