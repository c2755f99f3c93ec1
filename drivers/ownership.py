"""Who owns a path, who is at the other end of a Unix socket: the checks that keep the ipc bus and
the control sockets to their owner (docs/security.md, "The CAN bus (ipc) and the control sockets").

- :func:`private_directory`: create or accept a directory only its owner (and, with ``group``,
  that group) can enter: the ipc bus directory. One created by another user first (a squatter in
  a shared directory) or writable by others is refused, never joined.
- :func:`check_socket_owner`: before a client talks to a control socket, the socket file must be
  the current user's or root's, or its owner's in a directory chain nobody else can write to (a
  service's ``RuntimeDirectory=``); a socket another user put at the configured path is refused.
- :func:`peer_credentials` (``SO_PEERCRED``) and :func:`peer_allowed`: the uid at the other end of a
  connected socket, checked by the ipc bus for every peer and by the control clients.

Root (uid 0) is always trusted: it can read and write every file and socket anyway.
"""

from __future__ import annotations

import grp
import os
import socket
import stat
import struct
from dataclasses import dataclass
from pathlib import Path

_UCRED = struct.Struct("3i")  # struct ucred {pid_t pid; uid_t uid; gid_t gid;}


class OwnershipError(PermissionError):
    """A path or a peer that is not the current user's: the message says whose and why."""


@dataclass(frozen=True)
class PeerCredentials:
    """The process at the other end of a Unix socket, as the kernel recorded it at connect/listen."""

    pid: int
    uid: int
    gid: int


def peer_credentials(sock: socket.socket) -> PeerCredentials:
    """``SO_PEERCRED`` of a connected Unix socket."""
    raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size)
    pid, uid, gid = _UCRED.unpack(raw)
    return PeerCredentials(pid, uid, gid)


def group_id(group: str | int | None) -> int | None:
    """The gid of a group given by name or number (None stays None); KeyError if unknown."""
    if group is None or isinstance(group, int):
        return group
    if group.isdigit():
        return int(group)
    return grp.getgrnam(group).gr_gid


def _in_group(uid: int, gid: int, group_gid: int) -> bool:
    if gid == group_gid:
        return True
    try:
        import pwd

        name = pwd.getpwuid(uid).pw_name
        return group_gid in os.getgrouplist(name, gid)
    except (KeyError, OSError):
        return False


def peer_allowed(creds: PeerCredentials, group_gid: int | None = None) -> bool:
    """The current user, root, or (with ``group_gid``) a member of that group."""
    if creds.uid in (os.geteuid(), 0):
        return True
    return group_gid is not None and _in_group(creds.uid, creds.gid, group_gid)


def _owner_name(uid: int) -> str:
    try:
        import pwd

        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def _check_private(path: Path, st: os.stat_result, group_gid: int | None) -> None:
    me = os.geteuid()
    if not stat.S_ISDIR(st.st_mode):
        raise OwnershipError(f"{path} is not a directory")
    group_ok = group_gid is not None and st.st_gid == group_gid
    if st.st_uid != me and not (group_ok and me != 0 and _in_group(me, os.getegid(), group_gid or -1)):
        raise OwnershipError(f"{path} belongs to {_owner_name(st.st_uid)}, not to this user; not joined")
    if st.st_mode & stat.S_IWOTH:
        raise OwnershipError(f"{path} is writable by every user (mode {stat.S_IMODE(st.st_mode):04o}); not joined")
    if st.st_mode & stat.S_IWGRP and not group_ok:
        raise OwnershipError(
            f"{path} is writable by its group (mode {stat.S_IMODE(st.st_mode):04o}) and no bus group is configured"
        )


def check_ancestors(path: Path) -> None:
    """Every directory above ``path`` must be root's or ours and not writable by others, unless
    sticky (as /tmp): otherwise another user could rename ``path`` away and put her own there."""
    me = os.geteuid()
    for parent in path.absolute().parents:
        st = os.stat(parent)
        if st.st_uid not in (0, me) and not st.st_mode & stat.S_ISVTX:
            raise OwnershipError(f"{parent} (above {path}) belongs to {_owner_name(st.st_uid)}")
        if st.st_mode & (stat.S_IWOTH | stat.S_IWGRP) and not st.st_mode & stat.S_ISVTX:
            raise OwnershipError(f"{parent} (above {path}) is writable by others (mode {stat.S_IMODE(st.st_mode):04o})")


def private_directory(path: Path, group_gid: int | None = None) -> None:
    """Make ``path`` a directory of the current user, mode 0700 (0770 and group ``group_gid``
    with a group), or accept an existing one that is such; :class:`OwnershipError` otherwise
    (another owner, writable by others, a symlink, an unsafe parent)."""
    mode = 0o770 if group_gid is not None else 0o700
    missing = [p for p in (path, *path.parents) if not os.path.lexists(p)]
    for directory in reversed(missing):
        try:
            os.mkdir(directory, mode)
        except FileExistsError:
            continue  # made meanwhile by someone: checked below like any existing directory
        os.chmod(directory, mode)  # mkdir's mode is cut by the umask
        if group_gid is not None and directory == path:
            os.chown(directory, -1, group_gid)
    check_existing_directory(path, group_gid)


def check_existing_directory(path: Path, group_gid: int | None = None) -> None:
    """The checks of :func:`private_directory` on a directory that exists, creating nothing."""
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        raise OwnershipError(f"{path} is a symbolic link; not followed")
    _check_private(path, st, group_gid)
    check_ancestors(path)


def check_socket_owner(path: Path) -> None:
    """Refuse to talk to a socket at ``path`` that another user could have put there (see module
    doc): its owner must be us, root, or the owner of a directory chain only it can write to."""
    st = os.lstat(path)
    if not stat.S_ISSOCK(st.st_mode):
        raise OwnershipError(f"{path} is not a socket")
    me = os.geteuid()
    if st.st_uid in (me, 0):
        return
    # A service's socket (User=hil, RuntimeDirectory=hil): trusted when only that owner (or root)
    # could have created it: every directory above is its or root's (or ours) and writable by no
    # one else, except a sticky one (/tmp) whose entry on the way is root's or ours.
    child_uid = st.st_uid
    for parent in path.absolute().parents:
        pst = os.stat(parent)
        open_to_others = pst.st_mode & (stat.S_IWOTH | stat.S_IWGRP)
        sticky_ok = pst.st_mode & stat.S_ISVTX and child_uid in (0, me)
        if pst.st_uid not in (0, me, st.st_uid) or (open_to_others and not sticky_ok):
            raise OwnershipError(
                f"{path} belongs to {_owner_name(st.st_uid)}, not to this user, under {parent} that others "
                "can write to; refused"
            )
        child_uid = pst.st_uid


def check_server_peer(sock: socket.socket, path: Path) -> None:
    """After connecting to ``path``: the listening process must be the socket file's owner, us or root."""
    creds = peer_credentials(sock)
    owner = os.lstat(path).st_uid
    if creds.uid not in (os.geteuid(), 0, owner):
        raise OwnershipError(f"{path} is served by {_owner_name(creds.uid)} (pid {creds.pid}); refused")


__all__ = [
    "OwnershipError",
    "PeerCredentials",
    "check_ancestors",
    "check_existing_directory",
    "check_server_peer",
    "check_socket_owner",
    "group_id",
    "peer_allowed",
    "peer_credentials",
    "private_directory",
]
