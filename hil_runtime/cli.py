"""The ``hil`` command line.

The root app lives here, in the light runtime package. Command groups from the heavier packages
(``models``: experiments, stability; ``sim_target``: the emulated arm) are discovered as plugins
through the ``hil.commands`` entry-point group, so the runtime never imports them itself.

Error convention: any exception carrying an integer ``exit_code`` attribute is a user-facing error.
It is printed as one line (no traceback) and the process exits with that code (2 for bad input).
"""

from __future__ import annotations

import sys
from importlib.metadata import entry_points

import typer

from hil_runtime.commands import register as _register_runtime_commands

app = typer.Typer(
    name="hil",
    help="HIL runtime for learned hybrid MPC-feedback arm controllers.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

# The runtime's own commands: run (the daemon), status, reset, stop (hil_runtime/commands.py).
_register_runtime_commands(app)


def _load_plugins() -> None:
    for entry in entry_points(group="hil.commands"):
        try:
            register = entry.load()
        except ImportError as exc:  # an extra is not installed: its commands are simply absent
            missing = getattr(exc, "name", None) or str(exc)
            print(f"note: '{entry.name}' commands unavailable (missing {missing})", file=sys.stderr)
            continue
        register(app)


def main(argv: list[str] | None = None) -> int:
    _load_plugins()
    try:
        app(args=argv, standalone_mode=False)
    except SystemExit as exc:
        return int(exc.code or 0)
    except Exception as exc:  # noqa: BLE001 - the one place user errors become exit codes
        code = getattr(exc, "exit_code", None)
        if isinstance(code, int):
            print(f"error: {exc}", file=sys.stderr)
            return code
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            return exc.exit_code
        if isinstance(exc, click.exceptions.Abort):
            print("aborted", file=sys.stderr)
            return 130
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
