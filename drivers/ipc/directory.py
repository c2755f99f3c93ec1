"""The ipc bus's directory and who sent a frame: the parts of :mod:`drivers.ipc.bus` that concern
ownership (docs/security.md): where a channel name points, why an existing directory cannot be
joined, and the sender each received frame carries."""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from drivers.ownership import OwnershipError, check_existing_directory, group_id


def bus_directory(channel: str | os.PathLike[str]) -> Path:
    """The directory a channel names: a path as given; a bare name under ``$XDG_RUNTIME_DIR/hil-can``
    (the user's private runtime directory), or ``/run/hil/can`` without one (a service's
    ``RuntimeDirectory=hil``). Never a fixed name in a shared directory such as /tmp."""
    text = os.fspath(channel)
    if not text:
        raise ValueError("ipc bus channel is empty")
    if os.sep in text or text.startswith("."):
        return Path(text)
    runtime_dir = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime_dir) / "hil-can" if runtime_dir else Path("/run/hil/can")
    return base / text


class IpcPathError(can.CanInitializationError):
    """The bus directory cannot be used: not a directory, another user's, writable by others."""


@dataclass(frozen=True)
class Sender:
    """Who sent a received frame: the connection it came on (unique within the receiving bus, one
    per other bus instance) and that process's credentials (SO_PEERCRED)."""

    peer: int
    pid: int
    uid: int


class IpcMessage(can.Message):
    """A received frame with its :class:`Sender` (``None`` on frames built locally)."""

    __slots__ = ("sender",)

    def __init__(self, *args: Any, sender: Sender | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sender = sender


def channel_problem(channel: str, group: str | None = None) -> str | None:
    """Why an existing bus directory could not be joined (a file, another user's, writable by
    others), or None: for config checks, before anything is opened. Creates nothing."""
    try:
        directory = bus_directory(channel).absolute()
    except ValueError as exc:
        return str(exc)
    if not os.path.lexists(directory):
        return None
    try:
        check_existing_directory(directory, group_id(group))
    except KeyError:
        return f"no such group {group!r}"
    except OSError as exc:
        return str(exc) if isinstance(exc, OwnershipError) else f"{directory}: {exc.strerror or exc}"
    return None


def remove_socket_if_ours(path: Path, inode: tuple[int, int]) -> None:
    """Remove the socket file at ``path`` only if it is still the one bound there, (st_dev,
    st_ino) ``inode``: a later bus may have replaced it; files that are not sockets stay."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISSOCK(st.st_mode) and (st.st_dev, st.st_ino) == inode:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass


__all__ = ["IpcMessage", "IpcPathError", "Sender", "bus_directory", "channel_problem"]
