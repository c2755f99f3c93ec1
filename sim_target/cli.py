"""``hil target``: serve the emulated arm, inject faults into a running one.

hil target serve --config deploy/target.virtual.yaml
hil target inject --socket /run/hil/target.sock '{"kind": "payload", "mass_kg": 2.0}'
"""

from __future__ import annotations

import json
import logging
import signal
import sys
from pathlib import Path
from typing import Annotated

import typer

target_app = typer.Typer(name="target", help="The pybullet arm behind emulated CiA 402 drives.", no_args_is_help=True)


@target_app.command()
def serve(
    config: Annotated[Path, typer.Option("--config", help="target config, YAML or TOML")],
    can_log: Annotated[
        Path | None, typer.Option("--can-log", help="capture the drives' CAN traffic (.blf .asc .log .csv)")
    ] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Run the target until SIGINT/SIGTERM; the drives then go to a safe state and the bus closes."""
    from sim_target.config import load_target_config

    if can_log is not None:
        from drivers.capture import check_capture_path

        check_capture_path(can_log)  # before anything starts

    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(asctime)s %(message)s")
    target_config = load_target_config(config)  # before pybullet is imported: a bad config is one line
    from sim_target.server import build_server

    server, close = build_server(target_config, can_log)

    def _stop(signum: int, _frame: object) -> None:
        server.stop()

    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    bridge = f", bridge {server.bridge_url}" if server.bridge_url else ""
    print(
        f"target serving {server.plant.n_joints} drives on {target_config.bus.interface}:"
        f"{target_config.bus.channel}{bridge}, clock {target_config.clock}, "
        f"period {target_config.period_s * 1e3:g} ms",
        file=sys.stderr,
        flush=True,
    )
    try:
        server.run()
    finally:
        close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    stats = server.stats
    lateness = ""
    if target_config.clock == "realtime":  # what kept (or did not keep) real time, for the log
        lateness = (
            f"; late ticks {stats.late_ticks}, skipped periods {stats.skipped_periods}, "
            f"worst lag {stats.worst_lag_s * 1e6:.0f} µs"
        )
    print(f"target stopped after {stats.steps} steps{lateness}", file=sys.stderr)


@target_app.command()
def inject(
    command: Annotated[
        str,
        typer.Argument(
            help='one JSON fault, e.g. \'{"kind": "payload", "mass_kg": 2}\', {"kind": "status"}, '
            'or a run start {"kind": "start", ...}'
        ),
    ],
    socket_path: Annotated[Path, typer.Option("--socket", help="the target's control_socket")],
) -> None:
    """Send a fault (or a status request) to a running target; exit 2 if it refuses the fault."""
    from sim_target.config import (  # light: no pybullet for a client
        TargetConfigError,
        parse_fault,
        parse_run_start,
    )
    from sim_target.control import send_control

    try:
        data = json.loads(command)
    except json.JSONDecodeError as exc:
        raise TargetConfigError(f"inject: not JSON ({exc.msg})") from None
    if isinstance(data, dict) and data.get("kind") == "start":
        parse_run_start(data, "inject")  # a run start (sim_target.config.RunStart)
    elif not (isinstance(data, dict) and data.get("kind") == "status"):
        parse_fault(data, "inject")  # the schema here; joint count and node ids at the target
    try:
        reply = send_control(socket_path, data)
    except OSError as exc:
        raise TargetConfigError(f"{socket_path}: cannot reach the target ({exc.strerror or exc})") from None
    except ValueError:
        raise TargetConfigError(f"{socket_path}: the target's reply is not JSON") from None
    print(json.dumps(reply))
    if not reply.get("ok"):
        raise TargetConfigError(f"{socket_path}: target refused: {reply.get('error', 'no reason given')}")


def register(app: typer.Typer) -> None:
    app.add_typer(target_app, name="target")
