"""The CLI's exit codes and error path (issue 9, items 2 and 3): the process exits with the code
the command returned, Ctrl-C is 130 with a message and leaves no half-written file, and an
unexpected error is a traceback of that error (not of a missing ``click``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import typer

from hil_runtime import cli


def _app(monkeypatch: pytest.MonkeyPatch) -> typer.Typer:
    app = typer.Typer(pretty_exceptions_enable=False, add_completion=False)
    monkeypatch.setattr(cli, "app", app)
    monkeypatch.setattr(cli, "_load_plugins", lambda: None)
    return app


def test_typer_exit_codes_become_the_return_code(monkeypatch: pytest.MonkeyPatch) -> None:
    app = _app(monkeypatch)

    @app.command()
    def refuse() -> None:
        raise typer.Exit(3)

    @app.command()
    def fine() -> None:
        pass

    assert cli.main(["refuse"]) == 3
    assert cli.main(["fine"]) == 0


def test_ctrl_c_inside_a_command_is_130_with_a_message(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    app = _app(monkeypatch)

    @app.command()
    def work() -> None:
        raise KeyboardInterrupt

    @app.command()
    def other() -> None:
        pass

    assert cli.main(["work"]) == 130
    assert "interrupted (Ctrl-C)" in capsys.readouterr().err


def test_an_unexpected_error_is_its_own_traceback_not_a_missing_click(monkeypatch: pytest.MonkeyPatch) -> None:
    app = _app(monkeypatch)

    @app.command()
    def bug() -> None:
        raise RuntimeError("a real bug")

    @app.command()
    def other() -> None:
        pass

    with pytest.raises(RuntimeError, match="a real bug"):
        cli.main(["bug"])


def test_user_errors_and_usage_errors_are_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    app = _app(monkeypatch)

    class UserError(ValueError):
        exit_code = 2

    @app.command()
    def bad(count: int = 1) -> None:
        raise UserError("file.yaml: field: wrong\nsecond line")

    @app.command()
    def other() -> None:
        pass

    assert cli.main(["bad"]) == 2
    assert capsys.readouterr().err == "error: file.yaml: field: wrong second line\n"
    assert cli.main(["bad", "--count", "x"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--count" in err


def test_sigint_during_the_main_job_exits_130_and_leaves_no_partial_file(
    tmp_path: Path, hil_command: list[str]
) -> None:
    out = tmp_path / "out"
    # PYTHONFAULTHANDLER: should it ever hang, the SIGABRT below prints every thread's stack
    process = subprocess.Popen(
        [*hil_command, "experiment", "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "120", "PYTHONFAULTHANDLER": "1"},
    )
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and not out.is_dir():  # the run has started its work
            time.sleep(0.2)
        time.sleep(2.0)
        process.send_signal(signal.SIGINT)
        try:
            _, err = process.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGABRT)
            _, err = process.communicate(timeout=30)
            pytest.fail(f"hil experiment did not end 120 s after SIGINT; its threads:\n{err[-8000:]}")
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, err[-1000:]
    assert "interrupted (Ctrl-C)" in err and "Traceback" not in err
    leftovers = [p.name for p in out.rglob("*") if ".partial-" in p.name] if out.exists() else []
    assert leftovers == []
    assert not (out / "results.json").exists()  # results.json is written last: absent means incomplete


def test_help_shows_flags_without_a_bool_type_and_lists_the_robots(hil_command: list[str]) -> None:
    done = subprocess.run(
        [*hil_command, "experiment", "--help"],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert done.returncode == 0
    assert "--no-plots" in done.stdout and "<bool>" not in done.stdout
    assert "ur5_paper, ur5, panda" in done.stdout


STUCK = """
import sys, time, typer
from hil_runtime import cli
cli.INTERRUPT_GRACE_S = float(sys.argv[1])
app = typer.Typer(add_completion=False)
cli.app, cli._load_plugins = app, lambda: None

@app.command()
def stuck() -> None:
    ready = False
    while True:  # a native call or helper thread that never returns, as far as Ctrl-C is concerned
        try:  # "ready" is printed inside the try: a Ctrl-C right after it must land in the swallowing loop
            if not ready:
                print("ready", flush=True)
                ready = True
            time.sleep(0.05)
        except KeyboardInterrupt:
            pass

@app.command()
def other() -> None:
    pass

sys.exit(cli.main(["stuck"]))
"""


@pytest.mark.parametrize("second_ctrl_c", [False, True])
def test_ctrl_c_ends_even_work_that_does_not_unwind(second_ctrl_c: bool) -> None:
    grace_s = 2.0
    process = subprocess.Popen(
        [sys.executable, "-c", STUCK, str(grace_s)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert process.stdout is not None and process.stdout.readline().strip() == "ready"
        start = time.monotonic()
        process.send_signal(signal.SIGINT)
        if second_ctrl_c:
            time.sleep(0.3)
            process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=30)
        elapsed = time.monotonic() - start
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130 and "interrupted (Ctrl-C)" in err and "forced exit" in err
    assert elapsed < (1.5 if second_ctrl_c else grace_s + 3.0)
    assert second_ctrl_c or elapsed >= grace_s - 0.1
