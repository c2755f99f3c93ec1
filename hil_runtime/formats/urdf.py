"""The robot's URDF for recordings and live views, found without importing ``models``.

A bundle's manifest names its robot's URDF (``robot.urdf_file``) and pins its sha256; the file
ships in ``models/robots/data``. :func:`find_urdf` looks there (by the package's location, not by
importing it: the runtime never imports ``models``) and beside the bundle, and accepts a file only
when its sha256 is the manifest's: a recording never carries another arm's description.
"""

from __future__ import annotations

import hashlib
import importlib.util
from collections.abc import Iterator
from pathlib import Path


class UrdfError(ValueError):
    """An explicit URDF that cannot be read or is not the bundle's; one line, exit code 2."""

    exit_code = 2


def _shipped_dirs() -> Iterator[Path]:
    spec = importlib.util.find_spec("models")  # locates the package without running it
    for location in (spec.submodule_search_locations or []) if spec is not None else []:
        yield Path(location) / "robots" / "data"


def find_urdf(
    urdf_file: str,
    sha256: str | None = None,
    bundle_dir: Path | None = None,
    explicit: Path | None = None,
) -> Path | None:
    """The URDF named ``urdf_file`` (a bare file name, e.g. ``ur5_paper.urdf``) whose sha256 is
    ``sha256`` (unchecked when None); ``explicit`` first (UrdfError if it does not match), then
    beside the bundle and in the shipped robot data. None when no file matches."""
    if explicit is not None:
        try:
            data = explicit.read_bytes()
        except OSError as exc:
            raise UrdfError(f"--urdf {explicit}: {exc.strerror or exc}") from None
        if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
            raise UrdfError(f"--urdf {explicit}: sha256 differs from the bundle's robot.urdf_sha256 ({sha256[:12]}…)")
        return explicit
    name = Path(urdf_file).name
    candidates = [bundle_dir / name, bundle_dir.parent / name] if bundle_dir is not None else []
    candidates += [directory / name for directory in _shipped_dirs()]
    for candidate in candidates:
        if candidate.is_file() and (sha256 is None or hashlib.sha256(candidate.read_bytes()).hexdigest() == sha256):
            return candidate
    return None
