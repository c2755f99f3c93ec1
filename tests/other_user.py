"""Pytest fixtures for the multi-user security tests: ``other_user`` (session) is the second,
unprivileged local user of :mod:`models.lab.faults.other_user` (created with ``useradd``; the test
is skipped, saying why, when the suite does not run as root); ``shared_dir`` a 1777 directory."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from models.lab.faults.other_user import OtherUser, OtherUserUnavailable, run_as, shared_directory
from models.lab.faults.other_user import other_user as _other_user

__all__ = ["OtherUser", "other_user", "run_as", "shared_dir"]


@pytest.fixture(scope="session")
def other_user() -> OtherUser:
    try:
        return _other_user()
    except OtherUserUnavailable as exc:
        pytest.skip(f"multi-user case: {exc}")


@pytest.fixture
def shared_dir() -> Iterator[Path]:
    with shared_directory() as path:
        yield path
