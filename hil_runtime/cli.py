"""The ``hil`` command line.

The root app lives here, in the light runtime package. Command groups from the heavier packages
(``models``: experiments, stability; ``sim_target``: the emulated arm) are discovered as plugins
through the ``hil.commands`` entry-point group, so the runtime never imports them itself.

Error convention: any exception carrying an integer ``exit_code`` attribute is a user-facing error.
It is printed as one line (no traceback) and the process exits with that code (2 for bad input).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable
from importlib.metadata import entry_points
from types import FrameType
from typing import Any

import typer

from hil_runtime.bundle_cli import register as _register_bundle_commands
from hil_runtime.bus_cli import register as _register_bus_commands
from hil_runtime.commands import register as _register_runtime_commands
from hil_runtime.drives_cli import register as _register_drives_commands
from hil_runtime.telemetry.cli import register as _register_telemetry_commands

app = typer.Typer(
    name="hil",
    help="HIL runtime for learned hybrid MPC-feedback arm controllers.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

# The runtime's own commands: run (the daemon), status, reset, stop (hil_runtime/commands.py).
_register_runtime_commands(app)
# hil telemetry watch | record | plot | query | control (hil_runtime/telemetry/cli.py).
_register_telemetry_commands(app)
# hil bundle keygen | sign | check: Ed25519 signatures of policy bundles (hil_runtime/bundle_cli.py).
_register_bundle_commands(app)
# hil bus decode (hil_runtime/bus_cli.py).
_register_bus_commands(app)
# hil drives scan | check | jog (hil_runtime/drives_cli.py).
_register_drives_commands(app)


def _flags_show_no_type() -> None:
    """typer's rich help prints ``<bool>`` in the type column of an on/off flag (``--no-plots``,
    ``--help``), which reads as if it took a value: show nothing there, as click does."""
    try:
        from typer.core import TyperOption
    except ImportError:  # another typer layout: keep its help as it is
        return
    original = getattr(TyperOption, "display_type_rich", None)
    if original is None or getattr(original, "__module__", None) == __name__:  # None, or patched already
        return

    def display_type_rich(self: TyperOption, ctx: object) -> str | None:
        if getattr(self, "is_flag", False) and not getattr(self, "count", False) and self.metavar is None:
            return None
        shown: str | None = original(self, ctx)
        return shown

    # A patched method, by design: assigned through Any (mypy refuses a method assignment).
    patched: Any = TyperOption
    patched.display_type_rich = display_type_rich


def _load_plugins() -> None:
    for entry in entry_points(group="hil.commands"):
        try:
            register = entry.load()
        except ImportError as exc:  # an extra is not installed: its commands are simply absent
            missing = getattr(exc, "name", None) or str(exc)
            print(f"note: '{entry.name}' commands unavailable (missing {missing})", file=sys.stderr)
            continue
        register(app)


INTERRUPTED = 130  # 128 + SIGINT, what shells report for Ctrl-C
INTERRUPT_GRACE_S = 15.0  # after Ctrl-C, the longest we wait for the work to unwind before leaving
INTERRUPTED_MESSAGE = "interrupted (Ctrl-C): stopped; files already written are complete, none is half-written"


def _leave_now() -> None:
    print(f"{INTERRUPTED_MESSAGE} (forced exit)", file=sys.stderr, flush=True)
    os._exit(INTERRUPTED)


# What signal.signal() returns and accepts (typeshed's own alias is private).
_SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None
_sigint_armed = False  # a first Ctrl-C was seen: the next one leaves at once


def _on_sigint(_signum: int, _frame: object) -> None:
    """First Ctrl-C: KeyboardInterrupt, the work unwinds (outputs are atomic, nothing is half
    written) and a daemon timer ends the process if that takes longer than INTERRUPT_GRACE_S (a
    native call or a helper thread that does not return). A second Ctrl-C leaves at once."""
    global _sigint_armed
    if _sigint_armed:
        _leave_now()
    _sigint_armed = True
    timer = threading.Timer(INTERRUPT_GRACE_S, _leave_now)
    timer.daemon = True
    timer.start()
    raise KeyboardInterrupt


def _install_sigint_handler() -> _SignalHandler:
    """Our handler, returning the one it replaced; None where it stays as it is: outside the main
    thread, or where Ctrl-C is ignored or already owned. Commands that own SIGINT (``hil run``:
    quick stop, exit 0) install their own handler over this one."""
    main_thread = threading.current_thread() is threading.main_thread()
    if not main_thread or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return None
    global _sigint_armed
    _sigint_armed = False
    return signal.signal(signal.SIGINT, _on_sigint)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; return the process exit code (the console script does ``sys.exit(main())``)."""
    previous = _install_sigint_handler()
    try:
        return _main(argv)
    finally:
        if previous is not None and signal.getsignal(signal.SIGINT) is _on_sigint:
            signal.signal(signal.SIGINT, previous)


def _main(argv: list[str] | None) -> int:
    try:
        _flags_show_no_type()
        _load_plugins()
        # Non-standalone: typer returns the code of an explicit typer.Exit (and 130 for Ctrl-C, which
        # it turns into Exit(130)) instead of calling sys.exit, so the code must be passed on here.
        result = app(args=argv, standalone_mode=False)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except KeyboardInterrupt:  # outside typer's own handling (plugin import, teardown)
        result = INTERRUPTED
    except Exception as exc:  # noqa: BLE001 - the one place user errors become exit codes
        return _report(exc)
    code = result if isinstance(result, int) and not isinstance(result, bool) else 0
    if code == INTERRUPTED:
        print(INTERRUPTED_MESSAGE, file=sys.stderr, flush=True)
    return code


def _report(exc: Exception) -> int:
    """A user-facing error as one line (or the usage message) and its exit code; a bug re-raises.

    typer vendors click and no longer installs it, so its exceptions are recognised by their
    interface (``format_message`` and an integer ``exit_code``) and by typer's re-exports, never by
    importing click. Usage errors are one line too, like every other user error.
    """
    code = getattr(exc, "exit_code", None)
    format_message = getattr(exc, "format_message", None)
    if isinstance(code, int) and callable(format_message):  # usage: bad option or value
        command_path = getattr(getattr(exc, "ctx", None), "command_path", None)
        where = f" (see '{command_path} --help')" if command_path else ""
        print(f"error: {' '.join(str(format_message()).split())}{where}", file=sys.stderr)
        return code
    if isinstance(code, int):
        print(f"error: {' '.join(str(exc).split()) or type(exc).__name__}", file=sys.stderr)
        return code
    if isinstance(exc, typer.Abort):
        print("aborted", file=sys.stderr)
        return 1
    raise exc


if __name__ == "__main__":
    sys.exit(main())
