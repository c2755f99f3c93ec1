"""``hil telemetry``: watch, record, plot and query a runtime's Zenoh telemetry (docs/telemetry.md).

hil telemetry watch [--robot R] [--connect tcp/127.0.0.1:7447]
hil telemetry record --seconds 10 --out run.npz
hil telemetry plot run.npz
hil telemetry query schema|config|bundle
hil telemetry control stop|reset          # only when the runtime enables controls
"""

from __future__ import annotations

import collections
import json
import math
import sys
import threading
import time
from collections.abc import Callable
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer

from hil_runtime.telemetry.config import DEFAULT_LISTEN

telemetry_app = typer.Typer(
    name="telemetry", help="Watch, record, plot and query a runtime's Zenoh telemetry.", no_args_is_help=True
)

RobotOption = Annotated[
    str | None, typer.Option("--robot", help="the robot's key chunk (hil/<robot>/); default: the one alive")
]
ConnectOption = Annotated[
    list[str] | None,
    typer.Option("--connect", help=f"the runtime's Zenoh endpoint (repeatable) [default: {DEFAULT_LISTEN}]"),
]


def _seconds(low: float, high: float) -> Callable[[typer.Context, typer.CallbackParam, float | None], float | None]:
    """A callback refusing a duration outside (low, high]: NaN passes typer's own min/max checks
    (every comparison with it is false) and then hangs a wait (issue 20)."""

    def check(ctx: typer.Context, param: typer.CallbackParam, value: float | None) -> float | None:
        if value is not None and not low < value <= high:  # False for NaN too
            raise typer.BadParameter(f"{value!r}: must be a number of seconds in ({low:g}, {high:g}]")
        return value

    return check


def _between(low: float, high: float) -> Callable[[typer.Context, typer.CallbackParam, float], float]:
    def check(ctx: typer.Context, param: typer.CallbackParam, value: float) -> float:
        if not low <= value <= high:  # False for NaN too
            raise typer.BadParameter(f"{value!r}: must be in [{low:g}, {high:g}]")
        return value

    return check


TimeoutOption = Annotated[
    float,
    typer.Option("--timeout", help="seconds to wait for the runtime's replies", callback=_seconds(0.0, 3600.0)),
]
ZenohConfigOption = Annotated[
    Path | None, typer.Option("--zenoh-config", help="a Zenoh json5 file (TLS, access control, routers)")
]


class Queryable(str, Enum):
    schema = "schema"
    config = "config"
    bundle = "bundle"


class Control(str, Enum):
    stop = "stop"
    reset = "reset"


def _client(robot: str | None, connect: list[str] | None, timeout_s: float, zenoh_config: Path | None) -> Any:
    from hil_runtime.telemetry.config import TelemetryConfigError, _endpoint_host
    from hil_runtime.telemetry.subscriber import TelemetryClient

    endpoints = connect or [DEFAULT_LISTEN]
    for endpoint in endpoints:
        try:
            _endpoint_host(endpoint)
        except ValueError as exc:
            raise TelemetryConfigError(f"--connect: {exc}") from None
    if zenoh_config is not None and not zenoh_config.is_file():
        raise TelemetryConfigError(f"--zenoh-config: {zenoh_config} is not a file")
    return TelemetryClient.open(endpoints, robot, timeout_s, zenoh_config)


@telemetry_app.command()
def query(
    name: Annotated[Queryable, typer.Argument(help="which document")],
    robot: RobotOption = None,
    connect: ConnectOption = None,
    timeout: TimeoutOption = 3.0,
    zenoh_config: ZenohConfigOption = None,
) -> None:
    """Print the runtime's schema (payload layouts), config, or bundle (manifest summary, hashes) as JSON."""
    with _client(robot, connect, timeout, zenoh_config) as client:
        print(json.dumps(client.query_json(name.value), indent=2, sort_keys=True))


@telemetry_app.command()
def control(
    name: Annotated[Control, typer.Argument(help="stop: as SIGTERM; reset: clear a FAULT")],
    robot: RobotOption = None,
    connect: ConnectOption = None,
    timeout: TimeoutOption = 3.0,
    zenoh_config: ZenohConfigOption = None,
) -> None:
    """Ask the runtime to stop or reset (its telemetry config must set controls_enabled: true)."""
    from hil_runtime.telemetry.subscriber import TelemetryUnavailable

    with _client(robot, connect, timeout, zenoh_config) as client:
        try:
            reply = client.query_json(name.value)
        except TelemetryUnavailable as exc:
            raise TelemetryUnavailable(f"{exc}; controls exist only with telemetry.controls_enabled: true") from None
    if not reply.get("ok"):
        raise TelemetryUnavailable(f"{name.value} refused by the runtime: {reply.get('error')}")
    print(f"{name.value} requested")


@telemetry_app.command()
def record(
    out: Annotated[Path, typer.Option("--out", help="the record to write (.npz, or .mcap: docs/formats.md)")],
    seconds: Annotated[
        float, typer.Option("--seconds", help="how long to record", callback=_seconds(0.0, 7 * 86400.0))
    ] = 10.0,
    robot: RobotOption = None,
    connect: ConnectOption = None,
    timeout: TimeoutOption = 3.0,
    zenoh_config: ZenohConfigOption = None,
    urdf: Annotated[Path | None, typer.Option("--urdf", help="the URDF attached to an .mcap record")] = None,
) -> None:
    """Record the state stream for N seconds into an npz (columns per field, the schema embedded) or an MCAP file."""
    from hil_runtime.record import check_record_path
    from hil_runtime.telemetry.subscriber import TelemetryUnavailable, missing_samples, save_record, start_recording

    kind = check_record_path(out, option="--out")
    with _client(robot, connect, timeout, zenoh_config) as client:
        started_s = time.monotonic()
        recording = start_recording(client)  # before the queries: nothing is missed meanwhile
        stats_payloads: list[bytes] = []
        if kind == "mcap":  # the MCAP record has a stats channel (docs/formats.md)
            client.subscribe("stats", stats_payloads.append)
        schema = client.schema()
        recording.schema = schema
        repliers = client.schema_repliers()
        extra: dict[str, Any] = {}
        for name in ("config", "bundle"):
            try:
                extra[name] = client.query_json(name)
            except TelemetryUnavailable:
                extra[name] = None
        print(
            f"recording hil/{client.robot}/state for {seconds:g} s (schema from {', '.join(repliers) or '-'}) ...",
            file=sys.stderr,
            flush=True,
        )
        time.sleep(max(0.0, started_s + seconds - time.monotonic()))
        publishers = dict(client.publishers)
        warning = client.impersonation_warning(repliers)
    if warning is not None:
        print(warning, file=sys.stderr, flush=True)
    extra["publishers"] = {"samples": publishers, "schema_repliers": repliers}
    arrays = recording.arrays()
    if len(arrays["seq"]) == 0:
        raise TelemetryUnavailable(
            f"no state samples from hil/{schema.robot}/state in {seconds:g} s (is the runtime ACTIVE?); nothing written"
        )
    config = extra.get("config") or {}
    decimation = int(config.get("telemetry", {}).get("state_decimation", 1) or 1)
    period_s = config.get("period_s") or (config.get("bus") or {}).get("period_s")
    if isinstance(period_s, (int, float)) and period_s > 0:
        extra["period_s"] = float(period_s)  # plot: time = cycle x period (lock-step runs are not wall time)
    if kind == "mcap":
        from hil_runtime.formats.mcap_record import save_mcap_record, urdf_of_bundle_document

        urdf_path = urdf_of_bundle_document(extra.get("bundle"), schema.robot, urdf)
        stats = []
        for payload in stats_payloads:
            try:
                header, values = schema.decode_stats(payload)
            except ValueError:  # TelemetryDecodeError: counted nowhere, as refused status payloads
                continue
            if not header.warmup:
                stats.append({"t_ns": header.t_ns, **values})
        count = save_mcap_record(
            out, arrays, schema.joints, schema.robot, recording.status, recording.events, extra, urdf_path, stats
        )
    else:
        count = save_record(recording, out, extra)
    lost = missing_samples(arrays["seq"], decimation)
    gaps = int((arrays["flags"] & 1).astype(bool).sum())
    refused = f", {recording.refused} refused ({recording.first_refusal})" if recording.refused else ""
    print(
        f"wrote {out}: {count} state samples, seq {int(arrays['seq'][0])}..{int(arrays['seq'][-1])}, "
        f"{lost} missing, {gaps} after publisher drops{refused}; published by {', '.join(sorted(publishers)) or '-'}"
    )


@telemetry_app.command()
def foxglove(
    host: Annotated[str, typer.Option("--host", help="where the Foxglove WebSocket server listens")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", min=0, max=65535, help="its port (0: any free one)")] = 8765,
    rate_hz: Annotated[
        float, typer.Option("--rate-hz", help="states republished per s", callback=_between(1.0, 1000.0))
    ] = 50.0,
    seconds: Annotated[
        float | None,
        typer.Option(
            "--seconds", help="stop after this long (default: at Ctrl-C)", callback=_seconds(0.0, 7 * 86400.0)
        ),
    ] = None,
    urdf: Annotated[
        Path | None, typer.Option("--urdf", help="the arm's URDF (default: the bundle's robot, found by its sha256)")
    ] = None,
    allow_remote: Annotated[bool, typer.Option("--allow-remote", help="listen beyond loopback")] = False,
    robot: RobotOption = None,
    connect: ConnectOption = None,
    timeout: TimeoutOption = 3.0,
    zenoh_config: ZenohConfigOption = None,
) -> None:
    """Republish the telemetry live to Foxglove (ws://HOST:PORT) with the arm's URDF (docs/formats.md)."""
    from hil_runtime.formats.foxglove_live import FoxgloveBridge, FoxgloveError, run_bridge, urdf_text_for
    from hil_runtime.telemetry.config import is_loopback_endpoint

    if not allow_remote and not is_loopback_endpoint(f"tcp/{host}:{port}"):
        raise FoxgloveError(f"--host {host}: not loopback (127.0.0.1/::1); pass --allow-remote to serve beyond it")
    with _client(robot, connect, timeout, zenoh_config) as client:
        schema = client.schema()
        bridge = FoxgloveBridge(schema.joints, urdf_text_for(client, schema.robot, urdf), host, port, rate_hz)
        try:
            print(
                f"Foxglove: open ws://{host}:{bridge.port} (hil/{client.robot}, "
                f"{'URDF attached' if bridge.urdf_text else 'no URDF found'}); Ctrl-C to stop",
                file=sys.stderr,
                flush=True,
            )
            run_bridge(client, bridge, seconds)
        finally:
            bridge.close()
    print(f"republished {bridge.states_out} of {bridge.states_in} states", file=sys.stderr)


@telemetry_app.command()
def plot(
    path: Annotated[Path, typer.Argument(help="a record from 'hil telemetry record' (or 'hil run --record')")],
    out_dir: Annotated[Path | None, typer.Option("--out-dir", help="where the PNGs go [default: beside FILE]")] = None,
) -> None:
    """Per-joint tracking error and torque PNGs from a record."""
    from hil_runtime.telemetry.plot import plot_record

    for written in plot_record(path, out_dir):
        print(f"wrote {written}")


class _WatchState:
    """What the callbacks saw last (assignments are atomic under the GIL; the view only reads)."""

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_s = window_s
        self.sample: Any = None
        self.arrivals: collections.deque[tuple[float, bool]] = collections.deque(maxlen=20_000)
        self.stats: dict[str, float] = {}
        self.status: dict[str, Any] = {}
        self.events: collections.deque[str] = collections.deque(maxlen=5)
        self.alive: bool | None = None
        self.alive_changed_s = time.monotonic()
        self.refused = 0
        self.last_refusal = ""
        self.gaps = 0
        self.publishers: dict[str, int] = {}  # samples per publishing Zenoh session (the client's)
        self.repliers: list[str] = []  # sessions that answered the schema query

    def rates(self) -> tuple[float, float]:
        """(samples per second received, share of them with any fallback) over the window."""
        now = time.monotonic()
        recent = [fallback for arrival, fallback in list(self.arrivals) if now - arrival <= self.window_s]
        if not recent:
            return 0.0, float("nan")
        return len(recent) / self.window_s, sum(recent) / len(recent)


def _render(state: _WatchState, robot: str, joints: tuple[str, ...]) -> Any:
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    rate, fallback_share = state.rates()
    if state.alive is None:
        alive = Text("waiting", style="yellow")
    elif state.alive:
        alive = Text("alive", style="green")
    else:
        alive = Text(f"LOST {time.monotonic() - state.alive_changed_s:.0f} s ago", style="bold red")
    lifecycle = str(state.status.get("state", "?"))
    fault = state.status.get("fault")
    head = Table.grid(padding=(0, 2))
    head.add_row(
        Text(f"hil/{robot}", style="bold"),
        alive,
        Text(lifecycle, style="bold red" if lifecycle == "FAULT" else "bold"),
        Text(f"fault: {fault}", style="red") if fault else Text(""),
    )
    loop_rate = state.stats.get("rate_hz", float("nan"))
    compute_p99 = state.stats.get("compute_p99_s", float("nan"))
    dropped = state.stats.get("telemetry_dropped", float("nan"))
    head.add_row(
        Text(f"received {rate:6.0f} /s"),
        Text(f"loop {loop_rate:7.1f} Hz"),
        Text("fallback -" if math.isnan(fallback_share) else f"fallback {100 * fallback_share:5.1f} %"),
        Text(f"compute p99 {compute_p99 * 1e6:6.0f} µs, telemetry dropped {dropped:.0f}, gaps {state.gaps}"),
    )
    if state.status.get("bundle_id"):
        head.add_row(Text(f"bundle {state.status['bundle_id']}"), Text(""), Text(""), Text(""))
    table = Table(expand=False)
    for column in ("joint", "q [rad]", "q_ref [rad]", "error [rad]", "tau [N m]", "tau_fb [N m]"):
        table.add_column(Text(column), justify="right" if column != "joint" else "left")  # Text: "[rad]" is no markup
    sample = state.sample
    for j, name in enumerate(joints):
        if sample is None or not sample.values:
            table.add_row(name, "-", "-", "-", "-", "-")
            continue
        q, q_ref = float(sample["q"][j]), float(sample["q_ref"][j])
        table.add_row(
            name,
            f"{q:+.4f}",
            f"{q_ref:+.4f}",
            f"{q_ref - q:+.2e}",
            f"{float(sample['tau'][j]):+8.3f}",
            f"{float(sample['tau_fb'][j]):+8.3f}",
        )
    parts: list[Any] = [head, table]
    if sample is not None and sample.values:
        parts.append(Text(f"cycle {sample.header.seq}, compute {float(sample['compute_s']) * 1e6:.0f} µs"))
    for line in state.events:
        parts.append(Text(line, style="dim"))
    if state.refused:
        parts.append(Text(f"{state.refused} payloads refused: {state.last_refusal}", style="red"))
    from hil_runtime.telemetry.subscriber import impersonation_warning

    warning = impersonation_warning(f"hil/{robot}", list(state.publishers), state.repliers)
    if warning is not None:
        parts.append(Text(warning.replace("warning:", "WARNING:", 1), style="bold red"))
    elif state.publishers or state.repliers:
        parts.append(Text(f"published by Zenoh session {next(iter(state.publishers or state.repliers))}", style="dim"))
    return Group(*parts)


def attach_watch(client: Any, schema: Any) -> _WatchState:
    """Subscribe a watch state to ``client``'s state, stats, status, events and liveliness; the
    callbacks (Zenoh's threads) only assign. ``render_watch(state, client.robot, schema.joints)``
    draws it: ``hil telemetry watch`` and ``hil demo`` share this view."""
    from hil_runtime.telemetry.codec import TelemetryDecodeError

    state = _WatchState()
    state.publishers = client.publishers  # the client counts each sample's session
    state.repliers = client.schema_repliers()

    def subscribe(key: str, decode: Callable[[bytes], tuple[Any, Any]], use: Callable[[Any], None]) -> None:
        # One handler shape for every key: decode, count a refusal, skip WARMUP puts, hand on.
        def on_payload(payload: bytes) -> None:
            try:
                header, body = decode(payload)
            except TelemetryDecodeError as exc:
                state.refused += 1
                state.last_refusal = str(exc)
                return
            if not header.warmup:
                use(body)

        client.subscribe(key, on_payload)

    def decode_state(payload: bytes) -> tuple[Any, Any]:
        sample = schema.decode_state(payload)
        return sample.header, sample

    def on_sample(sample: Any) -> None:
        state.gaps += sample.header.gap
        state.sample = sample
        state.arrivals.append((time.monotonic(), float(sample["fallback"]) > 0.0))

    def on_stats(values: dict[str, float]) -> None:
        state.stats = values

    def on_status(body: dict[str, Any]) -> None:
        state.status = body

    def on_event(body: dict[str, Any]) -> None:
        state.events.append(f"{time.strftime('%H:%M:%S')} cycle {body['cycle']}: {body['kind']} {body['detail']}")

    def on_alive(alive: bool) -> None:
        if alive != state.alive:
            state.alive = alive
            state.alive_changed_s = time.monotonic()

    subscribe("state", decode_state, on_sample)
    subscribe("stats", schema.decode_stats, on_stats)
    subscribe("status", schema.decode_status, on_status)
    subscribe("events", schema.decode_event, on_event)
    client.watch_alive(on_alive)
    return state


render_watch = _render


@telemetry_app.command()
def watch(
    robot: RobotOption = None,
    connect: ConnectOption = None,
    timeout: TimeoutOption = 3.0,
    zenoh_config: ZenohConfigOption = None,
    refresh_hz: Annotated[float, typer.Option("--refresh-hz", callback=_between(0.5, 60.0))] = 10.0,
    seconds: Annotated[
        float | None, typer.Option("--seconds", help="exit after this long", callback=_seconds(0.0, 7 * 86400.0))
    ] = None,
) -> None:
    """A live view: each joint's q, q_ref, error and torque; rate, fallback share, state, fault, alive/lost."""
    from rich.console import Console
    from rich.live import Live

    with _client(robot, connect, timeout, zenoh_config) as client:
        schema = client.schema()
        state = attach_watch(client, schema)
        stop = threading.Event()
        end_s = None if seconds is None else time.monotonic() + seconds
        console = Console()
        try:
            with Live(
                _render(state, client.robot, schema.joints),
                console=console,
                refresh_per_second=refresh_hz,
                transient=False,
            ) as live:
                while not stop.wait(1.0 / refresh_hz):
                    live.update(_render(state, client.robot, schema.joints))
                    if end_s is not None and time.monotonic() >= end_s:
                        break
        except KeyboardInterrupt:
            pass


def register(app: typer.Typer) -> None:
    app.add_typer(telemetry_app, name="telemetry")
