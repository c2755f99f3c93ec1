"""A second, unprivileged local user for the multi-user security tests (docs/security.md).

``other_user`` (session fixture) creates ``hil-squatter`` with ``useradd`` (no home, no login) and
removes it at the end if it made it; it skips, saying why, when the suite does not run as root.
:func:`run_as` runs a stdlib-only Python snippet as that user (the system interpreter: the venv's
lives under /root, which the user cannot enter), returning the process: the hostile side.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

USER_NAME = "hil-squatter"
SYSTEM_PYTHON = "/usr/bin/python3"


@dataclass(frozen=True)
class OtherUser:
    name: str
    uid: int
    gid: int


@pytest.fixture(scope="session")
def other_user() -> Iterator[OtherUser]:
    if os.geteuid() != 0:
        pytest.skip("multi-user cases need root to create a second user (useradd)")
    if shutil.which("useradd") is None or not os.path.exists(SYSTEM_PYTHON):
        pytest.skip("multi-user cases need useradd and /usr/bin/python3")
    import pwd

    created = False
    try:
        entry = pwd.getpwnam(USER_NAME)
    except KeyError:
        subprocess.run(
            ["useradd", "--system", "--no-create-home", "--shell", "/usr/sbin/nologin", "--user-group", USER_NAME],
            check=True,
            capture_output=True,
        )
        created = True
        entry = pwd.getpwnam(USER_NAME)
    try:
        yield OtherUser(USER_NAME, entry.pw_uid, entry.pw_gid)
    finally:
        if created:
            subprocess.run(["userdel", USER_NAME], check=False, capture_output=True)


def run_as(user: OtherUser, code: str, *args: str) -> subprocess.Popen[str]:
    """``python3 -c code args...`` as ``user`` (uid, gid, no supplementary groups), stdout piped."""
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


@pytest.fixture
def shared_dir() -> Iterator[Path]:
    """A directory every user may create entries in (mode 1777, as /tmp): where a squatter works."""
    path = Path(tempfile.mkdtemp(prefix="hil-shared-", dir="/tmp"))
    os.chmod(path, 0o1777)
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)
