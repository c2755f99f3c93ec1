"""The demo's live view: ``hil telemetry watch``'s view (one view, models/../telemetry/cli.py), under
a line of the demo's own (phase, the run's time against the condition, the disturbance), and
optionally pybullet's own viewer mirroring the arm from the telemetry (``--gui``). Without a
terminal (piped, a log file) a live view cannot redraw: each phase is then one line."""

from __future__ import annotations

import os
from types import TracebackType
from typing import Any

from models.demo.session import DemoPhase
from models.lab.processes import DemoError


class NoDisplayError(ValueError):
    """``--gui`` without a display: one line, exit code 2, before anything starts."""

    exit_code = 2


def check_display() -> None:
    if not os.environ.get("DISPLAY"):
        raise NoDisplayError(
            "--gui: no display (DISPLAY is not set), so pybullet cannot open its viewer; "
            "run without --gui (or with --headless)"
        )


def render(phase: DemoPhase, disturbance_s: float | None) -> Any:
    from rich.console import Group
    from rich.progress_bar import ProgressBar
    from rich.table import Table
    from rich.text import Text

    from hil_runtime.telemetry.cli import render_watch

    head = Table.grid(padding=(0, 1))
    bar = ProgressBar(total=max(phase.duration_s, 1e-9), completed=min(phase.t_s, phase.duration_s), width=40)
    marker = (
        ""
        if disturbance_s is None
        else f"  disturbance at {disturbance_s:g} s" + (" ✓" if phase.t_s >= disturbance_s else "")
    )
    head.add_row(Text("hil demo", style="bold cyan"), Text(phase.text))
    head.add_row(Text(""), Text.assemble(f"t {phase.t_s:6.3f} / {phase.duration_s:g} s ", marker))
    head.add_row(Text(""), bar)
    parts: list[Any] = [head]
    if phase.watch is not None:
        parts.append(render_watch(phase.watch, phase.robot, phase.joints))
    for note in phase.notes[-3:]:
        parts.append(Text(note, style="dim"))
    return Group(*parts)


class ArmMirror:
    """pybullet's GUI showing the arm at the positions the telemetry reports (not the plant itself:
    the target steps physics headless, so drawing never slows the loop it serves)."""

    def __init__(self, robot_name: str, connection: int | None = None) -> None:
        import pybullet

        from models.robots import urdf_path
        from sim_target.plant import load_arm

        self._pb = pybullet
        try:
            self._client = pybullet.connect(pybullet.GUI if connection is None else connection)
        except pybullet.error as exc:
            raise DemoError(f"--gui: pybullet could not open its viewer ({exc})") from None
        if self._client < 0:
            raise DemoError("--gui: pybullet could not open its viewer (no OpenGL on this display?)")
        self._body = load_arm(self._client, urdf_path(robot_name))  # the target's own loader (quiet)
        self._joints: list[int] = []
        for index in range(pybullet.getNumJoints(self._body, physicsClientId=self._client)):
            if pybullet.getJointInfo(self._body, index, physicsClientId=self._client)[2] == pybullet.JOINT_REVOLUTE:
                self._joints.append(index)
        if connection is None:
            pybullet.resetDebugVisualizerCamera(1.6, 45, -25, [0, 0, 0.4], physicsClientId=self._client)

    def show(self, watch: Any) -> None:
        sample = getattr(watch, "sample", None)
        if sample is None or not sample.values:
            return
        for j, index in enumerate(self._joints):
            self._pb.resetJointState(self._body, index, float(sample["q"][j]), physicsClientId=self._client)

    def close(self) -> None:
        try:
            self._pb.disconnect(self._client)
        except self._pb.error:
            pass


class LiveView:
    """The view while the HIL run goes: ``on_phase`` and ``tick`` are what ``run_hil`` calls.

    Used as a context manager: the live display and the mirror are closed however the run ends."""

    def __init__(
        self,
        console: Any,  # rich.console.Console
        duration_s: float,
        disturbance_s: float | None,
        say_phases: bool,
        mirror: ArmMirror | None = None,
    ) -> None:
        from rich.live import Live

        self._console = console
        self._say_phases = say_phases
        self._mirror = mirror
        self._phase = DemoPhase(duration_s=duration_s)
        self._live = (
            None
            if say_phases
            else Live(get_renderable=lambda: render(self._phase, disturbance_s), console=console, refresh_per_second=8)
        )

    def on_phase(self, phase: DemoPhase) -> None:
        self._phase = phase
        if self._say_phases:
            self._console.print(f"hil demo: {phase.text}", soft_wrap=True)

    def tick(self) -> None:
        if self._mirror is not None and self._phase.watch is not None:
            self._mirror.show(self._phase.watch)

    def __enter__(self) -> LiveView:
        try:
            if self._live is not None:
                self._live.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, traceback: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        try:
            if self._live is not None:
                self._live.stop()
        finally:
            if self._mirror is not None:
                self._mirror.close()


__all__ = ["ArmMirror", "LiveView", "NoDisplayError", "check_display", "render"]
