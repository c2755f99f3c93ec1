"""The lock-step demo's two processes take SCHED_FIFO for their loop threads (docs/runtime.md, "The
lock-step demo's rate"); the free-running demo keeps its own settings (its CPUs apart)."""

from __future__ import annotations

from pathlib import Path

from models.demo import configs
from models.demo.options import DemoOptions
from models.lab.configs import FIFO_PRIORITY
from sim_target.config import parse_target_config


def test_lockstep_demo_asks_for_sched_fifo_in_both_processes(tmp_path: Path) -> None:
    for realtime in (False, True):
        options = DemoOptions(law="pd", mode="fb", realtime=realtime, cpus="none")
        target = parse_target_config(configs.target_config(options, 0.001, tmp_path / "bus", tmp_path / "t.sock"))
        assert target.clock == ("realtime" if realtime else "lockstep")
        assert target.realtime.in_lockstep is (not realtime)
        assert target.realtime.fifo_priority == FIFO_PRIORITY
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    condition = type("Condition", (), {"duration_s": 5.0, "name": "C1"})()
    data = configs.runtime_config(
        DemoOptions(law="pd", mode="fb"),
        robot,
        condition,
        0.001,
        tmp_path / "bus",
        tmp_path / "conditions.yaml",
        tmp_path / "r.sock",
        "tcp/127.0.0.1:7447",
    )
    assert data["loop"]["pacing"] == "bus" and data["loop"]["fifo_priority"] == FIFO_PRIORITY
