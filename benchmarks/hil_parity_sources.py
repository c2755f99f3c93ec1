"""Where HIL and the simulation part: each candidate cause of a difference measured alone.

For a few (law, mode, condition) runs, every variant below is compared with the simulation twin
of ``hil experiment --plant hil`` (models simulator: RK4, 2 substeps, pinocchio; exact 20 µs
pulse): trajectory RMS difference (deg, over time and joints) and composite-metric differences.

- ``sim_rk4_16``: the simulator with 16 RK4 substeps: the twin's own integration error.
- ``sim_rounded``: the twin with the bus's quantization in the loop (torque set-points rounded to
  1 ‰ of each drive's rated torque, positions to one encoder count, velocities to one count/s),
  nothing else changed; ``sim_rounded_torque_only``: the torque rounding alone.
- ``sim_carried_1``, ``sim_carried_2``: the same, each torque rounding error added to the set-point
  one (noise transfer 1 - z⁻¹) or two (1 - z⁻², what DriveBus does since this study) cycles later.
- ``sim_nudged_1e-9``: torques rounded to 1e-9 N·m: the law's own sensitivity (chaos).
- ``sim_delayed``: the twin with a one-cycle feedback delay (the law sees the state of the period
  before): what the bus would add if set-points were applied one SYNC late.
- ``hil_substeps_N``: the real HIL run (runtime + target over the virtual bus) with N pybullet
  steps per period.
- ``hil_pulse_spread``: HIL (32 substeps) with the disturbance spread evenly over its 1 ms period,
  as the target did before its impulses were resolved to substeps (same impulse, N·m·s).

    python benchmarks/hil_parity_sources.py                      # prints JSON
    python benchmarks/hil_parity_sources.py --plot docs/figures/hil_parity_sources.png
    python benchmarks/hil_parity_sources.py --runs "" --floor smc --sim-results results/experiment/sim/results.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

from models.conditions import load_conditions
from models.feedback import make_law
from models.hil_experiment import HilOptions, conditions_yaml, run_on_target
from models.modes import make_controller
from models.robots import load_robot
from models.scoring import run_metrics
from models.sim import SimConfig, simulate
from sim_target.launch import launch_target, target_config_dict

PERIOD_S = 1e-3
COUNTS_PER_RAD = (1 << 20) / (2 * np.pi)  # the drives' 0x608F


class Quantized:
    """A simulator controller behind the bus's quantization: encoder counts in, 1 ‰ torque out.
    ``carry``: the rounding error of set-point k added to set-point k + ``carry`` (0: plain
    rounding; 1: error feedback 1 - z⁻¹; 2: 1 - z⁻², what DriveBus does)."""

    def __init__(self, inner: Any, torque_step_nm: np.ndarray, carry: int, encoder: bool = True) -> None:
        self.inner, self.step, self.carry, self.encoder = inner, torque_step_nm, carry, encoder
        self.name, self.cycle_times_s = inner.name, inner.cycle_times_s
        self.errors = [np.zeros_like(torque_step_nm) for _ in range(max(carry, 1))]

    def reset(self, q0: np.ndarray) -> None:
        self.inner.reset(q0)
        self.errors = [np.zeros_like(self.step) for _ in range(max(self.carry, 1))]

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        if self.encoder:
            q = np.rint(q * COUNTS_PER_RAD) / COUNTS_PER_RAD
            qd = np.rint(qd * COUNTS_PER_RAD) / COUNTS_PER_RAD
        wanted = np.asarray(self.inner(t_s, q, qd, q_d, qd_d, qdd_d), float) + (self.errors[-1] if self.carry else 0.0)
        self.last_tau_fb = getattr(self.inner, "last_tau_fb", None)
        sent = np.rint(wanted / self.step) * self.step
        self.errors = [wanted - sent] + self.errors[:-1]
        return sent


class Delayed:
    """A simulator controller that sees the previous period's state (a one-cycle feedback delay)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.name, self.cycle_times_s = inner.name, inner.cycle_times_s
        self.previous: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self, q0: np.ndarray) -> None:
        self.inner.reset(q0)
        self.previous = None

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        seen = self.previous or (q, qd)
        self.previous = (q.copy(), qd.copy())
        tau = self.inner(t_s, seen[0], seen[1], q_d, qd_d, qdd_d)
        self.last_tau_fb = getattr(self.inner, "last_tau_fb", None)
        return tau


def _torque_steps_nm(robot: Any) -> np.ndarray:
    """1 ‰ of each drive's rated torque as the runtime configures it (drivers.config default)."""
    from drivers.config import JointDriveConfig

    joints = zip(robot.joint_names, robot.torque_limit_nm, strict=True)
    return np.array(
        [
            JointDriveConfig(name=n, node_id=i + 1, max_torque_nm=float(t)).effective_rated_torque_mnm * 1e-6
            for i, (n, t) in enumerate(joints)
        ]
    )


def _simulate(robot: Any, law: str, mode: str, condition: Any, sim: SimConfig, wrap: str | None = None) -> dict:
    controller = make_controller(mode, make_law(law, robot, PERIOD_S), robot)
    steps = _torque_steps_nm(robot)
    if wrap == "rounded":
        controller = Quantized(controller, steps, carry=0)
    elif wrap == "rounded_torque_only":
        controller = Quantized(controller, steps, carry=0, encoder=False)
    elif wrap == "carried_1":
        controller = Quantized(controller, steps, carry=1)
    elif wrap == "carried_2":
        controller = Quantized(controller, steps, carry=2)
    elif wrap is not None and wrap.startswith("nudged_"):  # a tiny rounding: how chaotic is the law itself?
        controller = Quantized(controller, np.full_like(steps, float(wrap[7:])), carry=0, encoder=False)
    elif wrap == "delayed":
        controller = Delayed(controller)
    elif wrap is not None:
        raise ValueError(f"unknown variant {wrap!r}")
    traj = simulate(robot, controller, [condition], sim)
    return {
        "t": traj.t_s,
        "q": traj.q[0],
        "q_ref": traj.q_ref[0],
        "tau": traj.tau[0],
        "within_limits": bool(traj.within_limits[0]),
    }


def _compare(run: dict, twin: dict, condition: Any) -> dict[str, Any]:
    diff = np.degrees(run["q"] - twin["q"])
    dist = condition.disturbance.time_s if condition.disturbance is not None else None
    m_run = run_metrics(run["t"], run["q"], run["q_ref"], dist)
    m_twin = run_metrics(twin["t"], twin["q"], twin["q_ref"], dist)
    return {
        "trajectory_rms_diff_deg": round(float(np.sqrt(np.mean(diff**2))), 6),
        "trajectory_max_diff_deg": round(float(np.abs(diff).max()), 5),
        "metrics_rel_pct": {k: round(100 * (m_run[k] - m_twin[k]) / m_twin[k], 2) if m_twin[k] else 0.0 for k in m_run},
        "within_limits": run.get("within_limits", True),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", default="pd/fb/C1,adrc/fb/C1,hinf/fb/C2,mrac/fb/C4,smc/fb/C1")
    parser.add_argument("--substeps", default="8,16,32,64")
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--floor", default="smc", help="laws whose own score spread under a nudge is measured")
    parser.add_argument(
        "--sim-results",
        type=Path,
        default=None,
        help="an `hil experiment` results.json: score the floor on its scale (the parity table's)",
    )
    args = parser.parse_args()
    robot = load_robot("ur5_paper")
    conditions = {c.name: c for c in load_conditions(robot=robot)}
    out: dict[str, Any] = {
        "machine": benchinfo.machine("pybullet", "pin", "numpy"),
        "load_average_start": os.getloadavg(),
        "runs": {},
    }
    started = time.monotonic()
    work = Path(os.environ.get("TMPDIR", "/tmp")) / f"hil-parity-{os.getpid()}.yaml"
    work.write_text(conditions_yaml(list(conditions.values())))
    twin_config = SimConfig(period_s=PERIOD_S, substeps=2, plant_backend="pinocchio")
    for spec in [x for x in args.runs.split(",") if x]:
        law, mode, cname = spec.split("/")
        condition = conditions[cname]
        twin = _simulate(robot, law, mode, condition, twin_config)
        row: dict[str, Any] = {}
        row["sim_rk4_16"] = _compare(
            _simulate(robot, law, mode, condition, replace(twin_config, substeps=16)), twin, condition
        )
        for wrap in ("rounded", "rounded_torque_only", "carried_1", "carried_2", "nudged_1e-9", "delayed"):
            row[f"sim_{wrap}"] = _compare(_simulate(robot, law, mode, condition, twin_config, wrap), twin, condition)
        variants: list[tuple[str, int, Any]] = [
            (f"hil_substeps_{n}", int(n), condition) for n in args.substeps.split(",")
        ]
        d = condition.disturbance
        spread = replace(d, torque_nm=tuple(t * d.duration_s / PERIOD_S for t in d.torque_nm), duration_s=PERIOD_S)
        variants.append(("hil_pulse_spread", 32, replace(condition, disturbance=spread)))
        for name, substeps, cond in variants:
            with launch_target(target_config_dict("ur5_paper", PERIOD_S, substeps), "virtual") as target:
                run = run_on_target(target, robot, law, mode, cond, PERIOD_S, HilOptions(parity=False), work)
            arrays = {**run.arrays, "within_limits": run.fault is None}
            row[name] = _compare(arrays, twin, condition)
        out["runs"][spec] = row
    work.unlink(missing_ok=True)
    out["floor"] = _floor(
        robot, list(conditions.values()), [x for x in args.floor.split(",") if x], twin_config, args.sim_results
    )
    out["wall_s"] = round(time.monotonic() - started, 1)
    out["load_average_end"] = os.getloadavg()
    print(json.dumps(out, indent=1))
    if args.plot is not None and out["runs"]:
        _plot(out, args.plot)


def _floor(
    robot: Any, conditions: list[Any], laws: list[str], sim: SimConfig, sim_results: Path | None
) -> dict[str, Any]:
    """The simulation's own reproducibility: each law and mode on every condition with its torques
    rounded to 1e-9 or 1e-6 N·m (a nudge) or quantized as the drives do (``carried_2``), scored
    against the plain simulation. On the scale of ``sim_results`` (an ``hil experiment``
    results.json: the parity table's scale) when given, else each pair on its own."""
    from models.hil_experiment.parity import per_run_scores

    scale = json.loads(sim_results.read_text())["runs"] if sim_results is not None else None
    out: dict[str, Any] = {}
    for law in laws:
        for mode in ("fb", "lmpc"):
            runs: dict[str | None, list[dict[str, Any]]] = {}
            for wrap in (None, "nudged_1e-9", "nudged_1e-6", "carried_2"):
                runs[wrap] = []
                for c in conditions:
                    dist = c.disturbance.time_s if c.disturbance is not None else None
                    r = _simulate(robot, law, mode, c, sim, wrap)
                    runs[wrap].append(
                        {
                            "law": law,
                            "mode": mode,
                            "condition": c.name,
                            "finite": True,
                            "within_limits": r["within_limits"],
                            "metrics": run_metrics(r["t"], r["q"], r["q_ref"], dist),
                        }
                    )
            for wrap in ("nudged_1e-9", "nudged_1e-6", "carried_2"):
                pair = runs[None] + runs[wrap]
                base = per_run_scores(runs[None], scale=scale or pair)
                moved = per_run_scores(runs[wrap], scale=scale or pair)
                per_condition = {
                    c.name: round(100 * (moved[(law, mode, c.name)] / base[(law, mode, c.name)] - 1), 1)
                    for c in conditions
                }
                a, b = float(np.mean(list(base.values()))), float(np.mean(list(moved.values())))
                out[f"{law}/{mode}/{wrap}"] = {
                    "score_sim": round(a, 4),
                    "score": round(b, 4),
                    "rel_pct": round(100 * (b - a) / a, 1),
                    "per_condition_pct": per_condition,
                }
    return out


def _plot(out: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    specs = list(out["runs"])
    variants = list(out["runs"][specs[0]])
    fig, ax = plt.subplots(figsize=(10, 4))
    width = 0.8 / len(specs)
    for i, spec in enumerate(specs):
        x = np.arange(len(variants)) + (i - (len(specs) - 1) / 2) * width
        ax.bar(x, [out["runs"][spec][v]["trajectory_rms_diff_deg"] for v in variants], width, label=spec)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(variants)), variants, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("trajectory RMS difference vs twin (deg)")
    ax.set_title("Sources of HIL-vs-simulation difference, each alone", fontsize=10)
    ax.grid(alpha=0.3, axis="y", which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
