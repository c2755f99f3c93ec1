"""A second, unprivileged local user for the multi-user security cases (docs/security.md): the
fault campaign's squatter and the tests' (tests/other_user.py).

:func:`other_user` makes sure ``hil-squatter`` exists (``useradd --system``, no home, no login; it
is left in place for the next run); :func:`run_as` runs a stdlib-only Python snippet as that user
with the system interpreter (a venv under /root is out of her reach); :func:`shared_directory`
gives a directory every user may create entries in (mode 1777, as /tmp).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

USER_NAME = "hil-squatter"
SYSTEM_PYTHON = "/usr/bin/python3"


class OtherUserUnavailable(RuntimeError):
    """The cases cannot act as another user here (not root, no useradd); the message says why."""


@dataclass(frozen=True)
class OtherUser:
    name: str
    uid: int
    gid: int


def other_user(create: bool = True) -> OtherUser:
    """The squatter's account, created when missing (needs root)."""
    import pwd

    try:
        entry = pwd.getpwnam(USER_NAME)
    except KeyError:
        if os.geteuid() != 0:
            raise OtherUserUnavailable("needs root to create a second user (useradd)") from None
        if not create or shutil.which("useradd") is None:
            raise OtherUserUnavailable("no useradd on this machine") from None
        subprocess.run(
            ["useradd", "--system", "--no-create-home", "--shell", "/usr/sbin/nologin", "--user-group", USER_NAME],
            check=True,
            capture_output=True,
        )
        entry = pwd.getpwnam(USER_NAME)
    if os.geteuid() != 0:
        raise OtherUserUnavailable("needs root to run a process as another user")
    if not os.path.exists(SYSTEM_PYTHON):
        raise OtherUserUnavailable(f"no {SYSTEM_PYTHON} for the other user's side")
    return OtherUser(USER_NAME, entry.pw_uid, entry.pw_gid)


def run_as(user: OtherUser, code: str, *args: str) -> subprocess.Popen[str]:
    """``python3 -c code args...`` as ``user`` (her uid and gid, no supplementary groups)."""
    return subprocess.Popen(
        [SYSTEM_PYTHON, "-c", code, *args],
        user=user.uid,
        group=user.gid,
        extra_groups=[],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd="/",
        env={"PATH": "/usr/bin:/bin"},
    )


@contextmanager
def shared_directory() -> Iterator[Path]:
    """A fresh directory with mode 1777 under /tmp (where every user can reach it), removed after."""
    path = Path(tempfile.mkdtemp(prefix="hil-shared-", dir="/tmp"))
    os.chmod(path, 0o1777)
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


__all__ = ["OtherUser", "OtherUserUnavailable", "other_user", "run_as", "shared_directory"]
