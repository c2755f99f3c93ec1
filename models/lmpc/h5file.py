"""The LMPC pipeline's HDF5 files (raw dataset, labels), written and read one way.

Each file carries a JSON manifest in its root attribute ``manifest`` with a ``schema`` string. A
writer fills a temporary file and renames it into place, so a crash never leaves a half-written file
under the final name. A reader checks the schema and turns any missing, unreadable, truncated or
inconsistent file into one ``ModelInputError`` naming the file.

    with write_h5(path) as h5:
        h5.create_group(...)
        write_manifest(h5, {"schema": SCHEMA, ...})
    with read_h5(path, "dataset", SCHEMA) as (h5, manifest):
        arrays = h5[law]["t_s"][...]
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from models.errors import ModelInputError

MANIFEST_ATTRIBUTE = "manifest"


@contextmanager
def write_h5(path: Path) -> Iterator[Any]:
    """An ``h5py.File`` open for writing at a temporary name, renamed to ``path`` on success."""
    import h5py

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as h5:
            yield h5
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_manifest(h5: Any, manifest: dict[str, Any]) -> None:
    """Store ``manifest`` (with its ``schema``) as the file's JSON root attribute."""
    h5.attrs[MANIFEST_ATTRIBUTE] = json.dumps(manifest)


@contextmanager
def read_h5(path: Path, what: str, schema: str, missing: str = "no such file") -> Iterator[tuple[Any, dict[str, Any]]]:
    """The open file and its manifest; ``what`` names the file in errors ("dataset", "labels").

    Errors raised while the caller reads inside the ``with`` block (a missing group or array, a
    truncated dataset) become the same one-line ``ModelInputError``.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise ModelInputError(f"{what} {path}: {missing}")
    try:
        with h5py.File(path, "r") as h5:
            manifest = json.loads(h5.attrs[MANIFEST_ATTRIBUTE])
            if not isinstance(manifest, dict) or manifest.get("schema") != schema:
                found = manifest.get("schema") if isinstance(manifest, dict) else None
                raise ModelInputError(f"{what} {path}: unknown schema {found!r} (expected {schema})")
            yield h5, manifest
    except ModelInputError:
        raise
    except (OSError, KeyError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ModelInputError(f"{what} {path}: unreadable or truncated HDF5 ({reason})") from None
