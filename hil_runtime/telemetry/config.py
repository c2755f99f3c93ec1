"""Telemetry configuration: the ``telemetry:`` section of the runtime's config (docs/telemetry.md).

    telemetry:
      enabled: true
      listen: ["tcp/127.0.0.1:7447"]      # where subscribers connect (peer mode)
      connect: []                         # e.g. a router: ["tcp/192.0.2.5:7447"] (allow_remote: true)
      zenoh_config: null                  # optional json5 file (access control, TLS, routers)
      state_decimation: 1                 # publish every k-th cycle's state
      queue_size: 1024                    # state samples held for the publisher thread
      stats_period_s: 1.0                 # stats and status republished at this period
      controls_enabled: false             # the stop/reset queryables exist only when true (needs auth)
      auth: null                          # {users_file, control_users}: Zenoh user/password (auth.py)
      remote_reset_activates: false       # a Zenoh reset stays INACTIVE unless true (and loop.activate_on_reset)
      express: false                      # true: no batching (lower latency, loses samples under load)
      lease_s: 1.0                        # subscribers see a hung runtime lost after this long

Bad input raises :class:`TelemetryConfigError` (exit code 2) with one line naming the source and
field. Endpoints must be loopback unless ``allow_remote`` is set: nothing leaves the machine by
accident, and multicast and gossip scouting are always off (peers are named, never discovered).
The endpoints checked are those of the merged configuration (a ``zenoh_config`` file's included,
and Zenoh's own default when nothing names any). Controls need authenticated peers: ``auth``, or a
``zenoh_config`` file with a usrpwd dictionary (docs/security.md, "Zenoh").
"""

from __future__ import annotations

import ipaddress
import json
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from drivers.strict_input import config_relative_path
from hil_runtime.telemetry.auth import TelemetryAuth, read_users_file

if TYPE_CHECKING:
    import zenoh

DEFAULT_PORT = 7447
DEFAULT_LISTEN = f"tcp/127.0.0.1:{DEFAULT_PORT}"
KEY_PREFIX = "hil"
DROP_WAIT_US = 50  # zenoh's default is 1000 µs
TX_QUEUE_BATCHES = 16  # data_high queue, batches (zenoh's default 2, its maximum 16)
# Zenoh key-expression chunks may not contain these (wildcards, selectors, separators).
_FORBIDDEN_CHUNK_CHARS = frozenset("/*$?#")
_IP_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
_LOCAL_PROTOCOLS = frozenset({"unixsock-stream", "unixpipe"})


class TelemetryConfigError(ValueError):
    """A telemetry config the runtime refuses; the message is one line naming source and field."""

    exit_code = 2


def zenoh_reason(exc: BaseException) -> str:
    """Zenoh's error text in one line, without its Rust source locations."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", text).strip()


def _endpoint_host(endpoint: str) -> str | None:
    """The host of an ``proto/host:port`` endpoint (None for local-only transports)."""
    proto, sep, address = endpoint.partition("/")
    if not sep or not address:
        raise ValueError(f"endpoint {endpoint!r} is not 'proto/host:port' (e.g. {DEFAULT_LISTEN!r})")
    if proto in _LOCAL_PROTOCOLS:
        return None
    if proto not in _IP_PROTOCOLS:
        raise ValueError(f"endpoint {endpoint!r}: unknown protocol {proto!r}")
    address = address.split("#", 1)[0].split("?", 1)[0]  # zenoh endpoint metadata follows '?', config '#'
    host, colon, port = address.rpartition(":")
    if not colon or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"endpoint {endpoint!r}: missing or bad port")
    return host.strip("[]")


def is_loopback_endpoint(endpoint: str) -> bool:
    host = _endpoint_host(endpoint)
    if host is None:
        return True
    if host.lower() in {"localhost", "ip6-localhost"}:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a DNS name other than localhost: could resolve anywhere


def check_key_chunk(name: str, what: str) -> str:
    if not name or any(char in _FORBIDDEN_CHUNK_CHARS for char in name) or name != name.strip():
        raise TelemetryConfigError(f"{what} {name!r} cannot be a Zenoh key chunk (no '/', '*', '$', '?', '#', blanks)")
    return name


_ROS_NAME = r"^[A-Za-z_][A-Za-z0-9_]*$"
_ROS_PATH = r"^/([A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*)?$"


class Ros2Section(BaseModel):
    """Opt-in ``sensor_msgs/msg/JointState`` on ROS 2's ``/joint_states`` over this Zenoh session,
    as rmw_zenoh publishes it (hil_runtime/formats/rmw_zenoh.py, docs/formats.md)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = False
    domain_id: int = Field(0, ge=0, le=232)  # ROS_DOMAIN_ID
    namespace: str = Field("/", pattern=_ROS_PATH)
    node: str = Field("hil_runtime", pattern=_ROS_NAME)
    topic: str = Field("/joint_states", pattern=_ROS_PATH)
    frame_id: str = ""
    decimation: int = Field(1, ge=1, le=1_000_000)  # every k-th published state (10: 100 Hz at 1 kHz)


class TelemetryConfig(BaseModel):
    """Zenoh telemetry of one runtime (one arm). Frozen, validated once at load."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = False
    mode: Literal["peer", "client"] = "peer"  # client: through a Zenoh router (fleets of arms)
    # Overrides the runtime's robot name as the key chunk: hil/<robot>/...
    robot: str | None = None
    listen: tuple[str, ...] = (DEFAULT_LISTEN,)
    connect: tuple[str, ...] = ()
    # Non-loopback endpoints are refused unless set: telemetry to another machine is a decision.
    allow_remote: bool = False
    # Optional Zenoh json5 file loaded first (access control, TLS, ...); the fields above win.
    zenoh_config: Path | None = None
    state_decimation: int = Field(1, ge=1, le=1_000_000)  # publish every k-th offered state
    queue_size: int = Field(1024, ge=2, le=1 << 20)  # state ring capacity, samples
    event_queue_size: int = Field(256, ge=2, le=1 << 16)
    stats_period_s: float = Field(1.0, gt=0.0, le=3600.0)  # stats + status republish period
    # How often the publisher thread drains: every wake-up takes the GIL from the control loop's
    # process; at 1 ms the free-running loop's send p90 was 486-567 µs, at 10 ms 143-179 µs
    # (docs/telemetry.md). Every state is still published (state_decimation), in batches.
    publish_period_s: float = Field(0.01, gt=0.0, le=1.0)
    controls_enabled: bool = False  # declare hil/<robot>/stop and /reset queryables (needs authentication)
    # Zenoh user/password authentication of every peer (and who may query the controls).
    auth: TelemetryAuth | None = None
    # A reset over Zenoh clears a FAULT to INACTIVE; re-enabling the drives is a local decision
    # (the control socket, or loop.activate_on_reset for a local reset) unless this is true.
    remote_reset_activates: bool = False
    # express: each sample leaves at once in its own batch. Off (default), Zenoh batches samples
    # for up to 1 ms, so its 16-batch queue holds seconds of samples instead of 16: on a loaded
    # 2-core machine express lost 0.6-6 % of 1 kHz samples, batching none, at the same loop cost
    # (docs/telemetry.md, "Measured").
    express: bool = False
    close_timeout_s: float = Field(1.0, gt=0.0, le=30.0)  # close() drains at most this long
    # Zenoh link lease this runtime declares: a peer that hears nothing for this long (a hung or
    # unplugged runtime, no TCP FIN) drops its liveliness token. Zenoh's default is 10 s.
    lease_s: float = Field(1.0, ge=0.2, le=600.0)
    ros2: Ros2Section = Ros2Section()

    @field_validator("robot")
    @classmethod
    def _robot_chunk(cls, value: str | None) -> str | None:
        return None if value is None else check_key_chunk(value, "robot")

    @field_validator("zenoh_config", mode="after")
    @classmethod
    def _resolve(cls, value: Path | None, info: ValidationInfo) -> Path | None:
        return None if value is None else config_relative_path(value, info)

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for endpoint in value:
            _endpoint_host(endpoint)
        return value

    @model_validator(mode="after")
    def _check(self) -> TelemetryConfig:
        if not self.allow_remote:
            for endpoint in (*self.listen, *self.connect):
                if not is_loopback_endpoint(endpoint):
                    raise ValueError(
                        f"endpoint {endpoint!r} is not loopback (127.0.0.1/::1); set allow_remote: true "
                        "to publish beyond this machine"
                    )
        if self.mode == "peer" and not self.listen and not self.connect:
            raise ValueError("peer mode needs a listen or connect endpoint, or no subscriber can reach it")
        if self.mode == "client" and not self.connect:
            raise ValueError("client mode needs connect endpoints (the router)")
        if self.zenoh_config is not None and not self.zenoh_config.is_file():
            raise ValueError(f"zenoh_config {str(self.zenoh_config)!r} is not a file")
        if self.zenoh_config is not None or self.controls_enabled:
            check_merged(self)
        return self

    def key_prefix(self, robot: str) -> str:
        """``hil/<robot>``: the config's robot wins over the runtime's robot name."""
        return f"{KEY_PREFIX}/{check_key_chunk(self.robot or robot, 'telemetry: robot')}"

    def summary(self) -> dict[str, Any]:
        summary: dict[str, Any] = json.loads(self.model_dump_json())
        return summary


def parse_telemetry_config(data: Any, source: str = "config", base_dir: Path | None = None) -> TelemetryConfig:
    """Validate a mapping (the ``telemetry:`` section of a larger config); relative paths are taken
    relative to ``base_dir`` (the config file's folder)."""
    from drivers.config import format_validation_error

    try:
        return TelemetryConfig.model_validate({} if data is None else data, context={"base_dir": base_dir})
    except ValidationError as exc:
        raise TelemetryConfigError(format_validation_error(source, exc)) from None


def zenoh_config(
    mode: str,
    listen: tuple[str, ...] | list[str] | None,
    connect: tuple[str, ...] | list[str] | None,
    base_file: Path | None = None,
) -> zenoh.Config:
    """A Zenoh config: no multicast or gossip scouting, only the named endpoints.

    Used by the publisher and by subscribers. ``None`` endpoints keep what ``base_file`` says.
    """
    import zenoh

    try:
        conf = zenoh.Config.from_file(str(base_file)) if base_file is not None else zenoh.Config()
    except zenoh.ZError as exc:
        raise TelemetryConfigError(f"{base_file}: not a valid Zenoh json5 config ({zenoh_reason(exc)})") from None
    conf.insert_json5("mode", json.dumps(mode))
    # Peers are named, never discovered: nothing is sent to a multicast group or gossiped on.
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    if listen is not None:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect is not None:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


def _json_at(conf: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - zenoh raises its own untyped error for a key it lacks
        return None


def merged_endpoints(conf: zenoh.Config, mode: str, field: str) -> list[str]:
    """``listen``/``connect`` endpoints of a Zenoh config: a list, or one list per mode."""
    value = _json_at(conf, f"{field}/endpoints")
    if isinstance(value, dict):
        value = value.get(mode, [])
    return [str(endpoint) for endpoint in value or []]


def check_merged(config: TelemetryConfig) -> None:
    """What the runtime's Zenoh session will really do, file and fields merged: loopback endpoints
    only (unless ``allow_remote``), and authenticated peers when the controls are enabled."""
    try:
        conf = publisher_zenoh_config(config)
    except ImportError:
        raise ValueError("zenoh_config and controls_enabled need eclipse-zenoh installed") from None
    except TelemetryConfigError as exc:
        raise ValueError(str(exc)) from None
    where = f"zenoh_config {str(config.zenoh_config)!r}: " if config.zenoh_config is not None else ""
    if not config.allow_remote:
        for field in ("listen", "connect"):
            for endpoint in merged_endpoints(conf, config.mode, field):
                try:
                    loopback = is_loopback_endpoint(endpoint)
                except ValueError as exc:
                    raise ValueError(f"{where}{field}/endpoints: {exc}") from None
                if not loopback:
                    default = "" if _file_sets(config, field) else " (Zenoh's default: the file sets none)"
                    raise ValueError(
                        f"{where}{field}/endpoints {endpoint!r}{default} is not loopback (127.0.0.1/::1); "
                        "set allow_remote: true to publish beyond this machine"
                    )
    dictionary = _json_at(conf, "transport/auth/usrpwd/dictionary_file")
    if dictionary and config.auth is None:  # the file's own dictionary: held to the same rules
        read_users_file(Path(str(dictionary)))
    if config.controls_enabled and not dictionary:
        raise ValueError(
            "controls_enabled: the stop/reset queryables need authenticated peers: set auth.users_file "
            "(Zenoh user/password), or a zenoh_config with transport/auth/usrpwd/dictionary_file"
        )
    if config.auth is not None and config.auth.access_control() is not None and _file_has_access_control(config):
        raise ValueError(
            f"{where}access_control is set and so is auth.control_users: keep one (put the rule in the file)"
        )


def _file_has_access_control(config: TelemetryConfig) -> bool:
    if config.zenoh_config is None:
        return False
    import zenoh

    return bool(_json_at(zenoh.Config.from_file(str(config.zenoh_config)), "access_control/enabled"))


def _file_sets(config: TelemetryConfig, field: str) -> bool:
    """Whether the endpoints come from the runtime config or the json5 file (not Zenoh's default)."""
    if config.zenoh_config is None or field in config.model_fields_set:
        return True
    import zenoh

    return bool(
        _json_at(zenoh.Config.from_file(str(config.zenoh_config)), f"{field}/endpoints")
        != _json_at(zenoh.Config(), f"{field}/endpoints")
    )


def publisher_zenoh_config(config: TelemetryConfig) -> zenoh.Config:
    """The runtime's session: with a json5 file, only endpoints set explicitly override the file's."""
    explicit = config.model_fields_set
    from_file = config.zenoh_config is not None
    listen = config.listen if (not from_file or "listen" in explicit) else None
    connect = config.connect if (not from_file or "connect" in explicit) else None
    conf = zenoh_config(config.mode, listen, connect, config.zenoh_config)
    if not from_file or "lease_s" in explicit:
        conf.insert_json5("transport/link/tx/lease", str(round(config.lease_s * 1000)))
    # A congested link (a stalled subscriber, a slow network): zenoh-python's put waits up to
    # wait_before_drop holding the GIL, which delays the loop thread's wake-up. Drop at once
    # instead, with a deeper queue to ride out short scheduling hiccups (docs/telemetry.md).
    conf.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop", str(DROP_WAIT_US))
    conf.insert_json5("transport/link/tx/queue/size/data_high", str(TX_QUEUE_BATCHES))
    if config.auth is not None:
        # Every peer that opens a link to this session must present a user:password of the file.
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(config.auth.users_file)))
        access_control = config.auth.access_control()
        if access_control is not None:
            conf.insert_json5("access_control", json.dumps(access_control))
    return conf
