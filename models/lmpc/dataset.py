"""D_input (Sec. III-C, IV-C): feedback-only closed-loop runs logged as emulator inputs.

Seeded random operating conditions (``models.conditions.random_conditions``, with the paper's
disturbance pulse at 2 s) run under each of the six laws on the batched simulator. Every
``stride``-th control period of every run is logged with all the expert needs to relabel it:

    t_s, run, q, qd, q_d, qd_d, qdd_d, law_state (before the step), tau_fb

The emulator input s = (q, e, qd, e_dot, tau_fb) (Eq. 22) is derived from these (``features``).
File: HDF5, one group per law, a ``manifest`` attribute (JSON: seeds, git commit, law parameters,
conditions, simulator settings) also written next to it as ``<file>.manifest.json``. Files are
written to a temporary name and renamed, so a failed run never leaves a half file or overwrites one.

    path = generate_raw_dataset(RawDatasetSpec(), Path("data/lmpc/raw.h5"))
    raw = load_raw_dataset(path)          # one-line ModelInputError on a corrupt/truncated file
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.conditions import Condition, load_conditions, random_conditions
from models.errors import ModelInputError
from models.executors import Executor, SerialExecutor
from models.feedback import DEFAULT_GAIN_SET, LAW_NAMES, make_law
from models.lmpc.h5file import read_h5, write_h5, write_manifest
from models.robots import RobotModel, load_robot
from models.sim import ControllerStack, SimConfig, simulate

SCHEMA = "hil-lmpc-raw/1"
ARRAYS = ("t_s", "run", "q", "qd", "q_d", "qd_d", "qdd_d", "law_state", "tau_fb")


@dataclass(frozen=True)
class RawDatasetSpec:
    robot: str = "ur5_paper"
    laws: tuple[str, ...] = LAW_NAMES
    gain_set: str = DEFAULT_GAIN_SET  # models.feedback.GAIN_SETS; the bundles carry the same gains
    conditions: int = 100
    seed: int = 20240601  # random_conditions seed; names R<seed>-<k>
    stride: int = 5  # log every 5th 1 ms period: 1000 samples per 5 s run, 600,000 in all
    period_s: float = 1e-3
    substeps: int = 2
    duration_s: float = 5.0
    chunks: int = 4  # tasks handed to the executor (conditions split across them)


def git_commit() -> str:
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "models"], cwd=root, capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def make_conditions(spec: RawDatasetSpec, robot: RobotModel) -> list[Condition]:
    """The seeded random conditions, checked disjoint from the paper's five."""
    from dataclasses import replace

    conditions = [replace(c, duration_s=spec.duration_s) for c in random_conditions(robot, spec.conditions, spec.seed)]
    paper = {tuple(np.round(c.amplitude_rad, 9)) for c in load_conditions()}
    if any(tuple(np.round(c.amplitude_rad, 9)) in paper for c in conditions):
        raise ModelInputError(f"dataset: seed {spec.seed} reproduces one of the paper's conditions; pick another")
    return conditions


class _LoggingController:
    """The feedback law alone (FB mode), logging every ``stride``-th period with the law's state."""

    def __init__(self, law: Any, batch: int, steps: int, stride: int) -> None:
        self.law, self.stride = law, stride
        self.name = f"{law.name}/fb-log"
        self.cycle_times_s: list[float] = []
        self.last_tau_fb: np.ndarray | None = None
        rows, n, s = (steps + stride - 1) // stride, law.n_joints, law.state_size
        self.log = {k: np.empty((batch, rows, n)) for k in ("q", "qd", "q_d", "qd_d", "qdd_d", "tau_fb")}
        self.log["law_state"] = np.empty((batch, rows, s))
        self.log["t_s"] = np.empty(rows)

    def reset(self, q0: np.ndarray) -> None:
        self.state = self.law.initial_state(np.atleast_2d(q0))
        self.k = 0

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        state_before = self.state
        tau, self.state = self.law.step(np, self.state, q, qd, q_d, qd_d, qdd_d)
        if self.k % self.stride == 0:
            row, log = self.k // self.stride, self.log
            log["t_s"][row] = t_s
            for key, value in (
                ("q", q),
                ("qd", qd),
                ("q_d", q_d),
                ("qd_d", qd_d),
                ("qdd_d", qdd_d),
                ("tau_fb", tau),
                ("law_state", state_before),
            ):
                log[key][:, row] = value
        self.k += 1
        self.last_tau_fb = tau
        return tau


def _simulate_chunk(task: tuple) -> dict[str, Any]:
    """Worker: every law on a slice of the conditions, in one vectorized plant."""
    robot_name, laws, gain_set, conditions, first_index, sim, stride = task
    robot = load_robot(robot_name)
    steps = int(round(conditions[0].duration_s / sim.period_s))
    loggers = [
        _LoggingController(make_law(law, robot, sim.period_s, gain_set), len(conditions), steps, stride) for law in laws
    ]
    stack = ControllerStack(loggers, [len(conditions)] * len(laws))
    traj = simulate(robot, stack, [c for _ in laws for c in conditions], sim)
    out: dict[str, Any] = {"first_index": first_index, "laws": {}}
    for j, (law, logger) in enumerate(zip(laws, loggers, strict=True)):
        rows = logger.log["t_s"].size
        part = slice(j * len(conditions), (j + 1) * len(conditions))
        out["laws"][law] = {
            "t_s": np.tile(logger.log["t_s"], len(conditions)),
            "run": np.repeat(np.arange(first_index, first_index + len(conditions)), rows),
            **{k: v.reshape(len(conditions) * rows, -1) for k, v in logger.log.items() if k != "t_s"},
            "finite": traj.finite[part],
            "within_limits": traj.within_limits[part],
        }
    return out


def generate_raw_dataset(
    spec: RawDatasetSpec,
    out_path: Path,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Simulate, log and write D_input to ``out_path`` (HDF5). ``progress(chunks_done)``."""
    robot = load_robot(spec.robot)
    conditions = make_conditions(spec, robot)
    sim = SimConfig(period_s=spec.period_s, substeps=spec.substeps)
    bounds = np.linspace(0, len(conditions), min(spec.chunks, len(conditions)) + 1).astype(int)
    tasks = [
        (spec.robot, spec.laws, spec.gain_set, conditions[a:b], int(a), sim, spec.stride)
        for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]
    started = time.perf_counter()
    parts: list[dict[str, Any]] = []
    for part in (executor or SerialExecutor()).map(_simulate_chunk, tasks):
        parts.append(part)
        if progress is not None:
            progress(1)
    built = {law: make_law(law, robot, spec.period_s, spec.gain_set) for law in spec.laws}
    laws_params = {
        law: {"state_size": built[law].state_size, "params": jsonable(built[law].params)} for law in spec.laws
    }
    manifest = {
        "schema": SCHEMA,
        "spec": asdict(spec),
        "git_commit": git_commit(),
        "robot": robot.name,
        "urdf_sha256": _sha256(robot.urdf_path),
        "joint_names": list(robot.joint_names),
        "sim": asdict(sim),
        "laws": laws_params,
        "conditions": [
            {
                "name": c.name,
                "amplitude_rad": list(c.amplitude_rad),
                "frequency_hz": list(c.frequency_hz),
                "phase_s": c.phase_s,
                "duration_s": c.duration_s,
                "disturbance": None if c.disturbance is None else asdict(c.disturbance),
            }
            for c in conditions
        ],
        "generation_wall_s": round(time.perf_counter() - started, 2),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    out_path = Path(out_path)
    with write_h5(out_path) as h5:
        write_manifest(h5, manifest)
        for law in spec.laws:
            group = h5.create_group(law)
            for key in ARRAYS:
                data = np.concatenate([p["laws"][law][key] for p in parts])
                group.create_dataset(key, data=data.astype(np.int32 if key == "run" else np.float64))
            for key in ("finite", "within_limits"):
                group.attrs[key] = int(np.concatenate([p["laws"][law][key] for p in parts]).sum())
    manifest["samples_per_law"] = {law: sum(len(p["laws"][law]["t_s"]) for p in parts) for law in spec.laws}
    Path(str(out_path) + ".manifest.json").write_text(json.dumps(manifest, indent=2))
    return out_path


@dataclass
class RawLaw:
    """One law's logged samples (M rows)."""

    t_s: np.ndarray
    run: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    q_d: np.ndarray
    qd_d: np.ndarray
    qdd_d: np.ndarray
    law_state: np.ndarray
    tau_fb: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.size)

    def take(self, index: np.ndarray) -> RawLaw:
        return RawLaw(*(getattr(self, k)[index] for k in ARRAYS))

    def features(self, feature_set: str = "eq22") -> np.ndarray:
        """s = (q, e, qd, e_dot, tau_fb) (Eq. 22), (M, 5N); e = q_d - q. ``feature_set="eq22+qdd_d"``:
        (q, e, qd, e_dot, qdd_d, tau_fb), (M, 6N) (hil_runtime.bundle.FEATURE_SETS)."""
        if feature_set == "eq22":
            return features(self.q, self.qd, self.q_d, self.qd_d, self.tau_fb)
        from hil_runtime.trust_region import emulator_features

        return emulator_features(feature_set, self.q, self.qd, self.q_d, self.qd_d, self.qdd_d, self.tau_fb)


def features(q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, tau_fb: np.ndarray) -> np.ndarray:
    return np.concatenate([q, q_d - q, qd, qd_d - qd, tau_fb], axis=-1)


@dataclass
class RawDataset:
    path: Path
    manifest: dict[str, Any]
    laws: dict[str, RawLaw] = field(default_factory=dict)


def load_raw_dataset(path: Path, laws: tuple[str, ...] | None = None) -> RawDataset:
    """Read D_input; any unreadable, truncated or inconsistent file is one ModelInputError naming it."""
    path = Path(path)
    with read_h5(path, "dataset", SCHEMA) as (h5, manifest):
        out = RawDataset(path, manifest)
        for law in laws or tuple(manifest["spec"]["laws"]):
            if law not in h5:
                raise ModelInputError(f"dataset {path}: no group for law '{law}'")
            arrays = {k: h5[law][k][...] for k in ARRAYS}
            rows = {a.shape[0] for a in arrays.values()}
            if len(rows) != 1:
                raise ModelInputError(f"dataset {path}: law '{law}' arrays have different lengths {sorted(rows)}")
            out.laws[law] = RawLaw(**arrays)
    return out


def _sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def jsonable(value: Any) -> Any:
    """Plain JSON types from nested dicts, lists, numpy arrays and scalars (non-finite floats: None)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
