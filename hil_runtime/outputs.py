"""Output directories and files that are either complete or absent.

``prepare_output_dir`` runs before any work: it creates the directory and proves it writable (a
probe file, because ``os.access`` says yes to root on a read-only directory and knows nothing of a
full or read-only file system). ``atomic_path`` hands out a temporary name beside the target and
renames it into place only when the writer finished: an interrupt (Ctrl-C), a full disk or any
error leaves the previous file, or none, never half of one.

    out = prepare_output_dir(Path("results/experiment"), option="--out")
    write_text_atomic(out / "results.json", text)
    with atomic_path(out / "plot.png") as tmp:
        figure.savefig(tmp)            # the temporary name keeps the suffix, so formats still work

``json_safe`` turns a results structure into plain JSON values (numpy scalars and arrays included,
non-finite floats as null) before it is written.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any


class OutputError(ValueError):
    """An output location that cannot be used (bad input): one line, exit code 2."""

    exit_code = 2


class OutputWriteError(OSError):
    """Writing an output failed midway (disk full, I/O error): one line, exit code 1, no partial file."""

    exit_code = 1

    def __str__(self) -> str:
        return str(self.strerror or super().__str__())


def _reason(exc: OSError) -> str:
    return exc.strerror or errno.errorcode.get(exc.errno or 0, "") or type(exc).__name__


def prepare_output_dir(path: str | Path, option: str = "--out") -> Path:
    """Create ``path`` (and its parents) if needed and prove it writable; OutputError otherwise."""
    path = Path(path)
    where = f"{option} {path}"
    if path.exists() and not path.is_dir():
        raise OutputError(f"{where}: a file is in the way (not a directory)")
    for parent in path.parents:
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                raise OutputError(f"{where}: {parent} is a file, not a directory")
            break
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{where}: cannot create the directory ({_reason(exc)})") from None
    try:
        handle, probe = tempfile.mkstemp(dir=path, prefix=".hil-write-probe-")
        try:
            os.write(handle, b"probe")
        finally:
            os.close(handle)
            os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{where}: not writable ({_reason(exc)})") from None
    return path


def partial_name(path: Path) -> Path:
    """The temporary name for ``path``: hidden, with the pid, and the same suffix (numpy and
    matplotlib choose the format from it; np.savez would otherwise append '.npz')."""
    return path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success rename it to ``path``, on any failure delete it."""
    path = Path(path)
    tmp = partial_name(path)
    try:
        yield tmp
        if not tmp.exists():
            raise OutputWriteError(errno.ENOENT, f"{path}: the writer produced no file")
        os.replace(tmp, path)
    except BaseException as exc:  # KeyboardInterrupt too: never leave the partial file behind
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, OutputWriteError):
            raise OutputWriteError(exc.errno or errno.EIO, f"{path}: cannot write ({_reason(exc)})") from None
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` completely (flushed to disk) or not at all."""
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


def write_text_atomic(path: str | Path, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def remove_if_empty(path: Path) -> None:
    """Remove a directory this run created and never filled (after an interrupt or an error)."""
    with contextlib.suppress(OSError):
        path.rmdir()


def json_safe(value: Any) -> Any:
    """``value`` as plain JSON values: dict keys as strings, tuples as lists, numpy scalars and arrays
    as Python numbers and lists, non-finite floats as None (strict JSON has no NaN or Infinity).

    numpy values are converted through their ``tolist()``, so this module does not import numpy
    (the daemon's light imports, tested)."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    if isinstance(value, float):  # np.float64 too (a float subclass)
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (str, bytes)):
        return value
    tolist = getattr(value, "tolist", None)  # numpy arrays and scalars (np.float32, np.int64, np.bool_)
    if callable(tolist):
        return json_safe(tolist())
    return value
