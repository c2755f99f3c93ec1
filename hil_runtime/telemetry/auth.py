"""Who may talk to the runtime over Zenoh: ``telemetry.auth`` (docs/security.md, "Zenoh").

    telemetry:
      controls_enabled: true
      auth:
        users_file: /etc/hil/zenoh-users       # Zenoh usrpwd dictionary: one "user:password" a line, mode 0600
        control_users: [operator]              # may query stop/reset; null: every user of the file

With ``users_file`` the runtime's Zenoh session authenticates every peer that connects to it
(Zenoh's ``transport/auth/usrpwd``): a session without a user and password of the file, or with a
wrong one, is refused at the handshake and sees nothing, neither telemetry nor controls. With
``control_users``, an access-control rule (Zenoh's ``access_control``, subjects by ``usernames``)
refuses the stop/reset queries of the other users, who keep reading telemetry.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator, model_validator

from drivers.strict_input import config_relative_path

# The controls' key expressions for the access-control rule (every robot of this session).
CONTROL_KEY_EXPRS = ("hil/*/stop", "hil/*/reset")


class TelemetryAuth(BaseModel):
    """Zenoh user/password authentication of the runtime's peers. Frozen, validated at load."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # Zenoh's usrpwd dictionary file: "user:password" lines; readable by its owner only.
    users_file: Path
    # Users whose stop/reset queries are accepted; None: every user of users_file.
    control_users: tuple[str, ...] | None = None

    @field_validator("users_file", mode="after")
    @classmethod
    def _resolve(cls, value: Path, info: ValidationInfo) -> Path:
        return config_relative_path(value, info)

    @model_validator(mode="after")
    def _check(self) -> TelemetryAuth:
        users = read_users_file(self.users_file)
        if self.control_users is not None:
            unknown = [name for name in self.control_users if name not in users]
            if unknown:
                raise ValueError(
                    f"control_users: {', '.join(map(repr, unknown))} not in users_file {str(self.users_file)!r}"
                )
        return self

    def users(self) -> tuple[str, ...]:
        return read_users_file(self.users_file)

    def access_control(self) -> dict[str, object] | None:
        """The Zenoh access_control section refusing other users' control queries (None: none needed)."""
        if self.control_users is None:
            return None
        others = [name for name in self.users() if name not in self.control_users]
        if not others:
            return None
        return {
            "enabled": True,
            "default_permission": "allow",
            "rules": [
                {
                    "id": "hil-controls",
                    "permission": "deny",
                    "flows": ["ingress"],
                    "messages": ["query"],
                    "key_exprs": list(CONTROL_KEY_EXPRS),
                }
            ],
            "subjects": [{"id": "hil-not-control-users", "usernames": others}],
            "policies": [{"rules": ["hil-controls"], "subjects": ["hil-not-control-users"]}],
        }


def read_users_file(path: Path) -> tuple[str, ...]:
    """The user names of a Zenoh usrpwd dictionary; refuses a file others may read or write."""
    try:
        mode = path.stat()
        if not stat.S_ISREG(mode.st_mode):
            raise ValueError(f"users_file {str(path)!r} is not a regular file")
        if mode.st_mode & 0o077:
            raise ValueError(
                f"users_file {str(path)!r} is readable or writable by others (mode {stat.S_IMODE(mode.st_mode):04o}); "
                "chmod 600 it"
            )
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"users_file {str(path)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"users_file {str(path)!r}: cannot read it ({type(exc).__name__})") from None
    users: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        user, colon, password = line.partition(":")
        if not colon or not user or not password or user != user.strip():
            raise ValueError(f"users_file {str(path)!r} line {number}: not 'user:password'")
        users.append(user)
    if not users:
        raise ValueError(f"users_file {str(path)!r}: no 'user:password' line")
    return tuple(users)


def write_users_file(path: Path, users: dict[str, str]) -> Path:
    """A Zenoh usrpwd dictionary readable by its owner only (created 0600, never widened)."""
    text = "".join(f"{user}:{password}\n" for user, password in users.items())
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
        handle.write(text)
    return path


def write_client_config(path: Path, user: str, password: str) -> Path:
    """A Zenoh json5 file carrying one user's credentials (``hil telemetry --zenoh-config``), 0600."""
    text = json.dumps({"transport": {"auth": {"usrpwd": {"user": user, "password": password}}}}, indent=2)
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
        handle.write(text + "\n")
    return path
