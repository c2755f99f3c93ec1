"""``hil run`` (the daemon) and ``hil status`` / ``hil reset`` / ``hil stop`` (its control socket)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated

import typer


def _socket_of(socket_path: Path | None, config: Path | None) -> Path:
    if socket_path is not None:
        return socket_path
    if config is not None:
        from hil_runtime.config import RuntimeConfigError, load_runtime_config

        path = load_runtime_config(config).control_socket
        if path is None:
            raise RuntimeConfigError(f"{config}: control_socket: not set, so the daemon has no control socket")
        return path
    raise typer.BadParameter("give --socket PATH or --config FILE")


SocketOption = Annotated[Path | None, typer.Option("--socket", help="the daemon's control_socket")]
ConfigOption = Annotated[Path | None, typer.Option("--config", help="the daemon's config (names the socket)")]


def run(
    config: Annotated[Path, typer.Option("--config", help="runtime config, YAML (deploy/*.yaml)")],
    record: Annotated[
        Path | None, typer.Option("--record", help="write the run's per-cycle record (.npz, or .mcap: docs/formats.md)")
    ] = None,
    record_cycles: Annotated[
        int, typer.Option(min=1, max=3_600_000, help="rows kept for a .npz --record (~330 B each)")
    ] = 60_000,
    urdf: Annotated[Path | None, typer.Option("--urdf", help="the URDF attached to an .mcap record")] = None,
    can_log: Annotated[
        Path | None, typer.Option("--can-log", help="capture the drive bus's frames (.blf .asc .log .csv)")
    ] = None,
    check: Annotated[bool, typer.Option("--check", help="validate config, bundle and condition; touch no bus")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Run the control loop on the arm's drives until SIGTERM/SIGINT (a systemd Type=notify service)."""
    from hil_runtime.daemon import check as check_config
    from hil_runtime.daemon import serve
    from hil_runtime.record import check_record_path

    if record is not None:
        check_record_path(record)  # before anything runs: suffix known, directory writable
    if can_log is not None:
        from drivers.capture import check_capture_path

        check_capture_path(can_log)
    if check:
        print(check_config(config))
        return

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(asctime)s %(levelname)s %(message)s"
    )
    code = serve(config, record, record_cycles if record is not None else 0, urdf, can_log)
    if code:
        raise typer.Exit(code)


def status(socket_path: SocketOption = None, config: ConfigOption = None) -> None:
    """Print the running daemon's state, fault and figures (JSON)."""
    from hil_runtime.control import send_command

    print(json.dumps(send_command(_socket_of(socket_path, config), "status"), indent=2))


def reset(socket_path: SocketOption = None, config: ConfigOption = None) -> None:
    """Clear a FAULT: drives fault-reset, then ACTIVE again with a ramp from the measured pose."""
    from hil_runtime.control import send_command

    reply = send_command(_socket_of(socket_path, config), "reset")
    print(
        f"reset requested (state was {reply.get('state')}"
        + (f", fault: {reply['fault']})" if reply.get("fault") else ")")
    )


def activate(socket_path: SocketOption = None, config: ConfigOption = None) -> None:
    """INACTIVE -> ACTIVE: enable the drives (e.g. after a reset over Zenoh, which stops at INACTIVE)."""
    from hil_runtime.control import send_command

    reply = send_command(_socket_of(socket_path, config), "activate")
    print(f"activation requested (state was {reply.get('state')})")


def stop(socket_path: SocketOption = None, config: ConfigOption = None) -> None:
    """Stop the daemon's loop as SIGTERM does (quick stop, disable, exit 0)."""
    from hil_runtime.control import send_command

    send_command(_socket_of(socket_path, config), "stop")
    print("stop requested")


def register(app: typer.Typer) -> None:
    app.command("run")(run)
    app.command("status")(status)
    app.command("reset")(reset)
    app.command("activate")(activate)
    app.command("stop")(stop)
