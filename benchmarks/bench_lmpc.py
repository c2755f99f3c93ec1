"""t_L: per-cycle wall time of LMPC (law + emulator in one onnxruntime call), one arm, Python included.

Runs the shipped bundles' controller (models.lmpc.LMPCController, which is hil_runtime.bundle's
single-row path) in a closed loop on the paper's condition C1 and reports the per-call time, plus
the bare ``PolicyBundle.step`` time. Prints JSON.

    python benchmarks/bench_lmpc.py [--cycles 3000] [--bundles models/bundles]
    python benchmarks/bench_lmpc.py --fallbacks      # + trust-region counters on the paper's 5 conditions
    python benchmarks/bench_lmpc.py --session-sweep  # + each graph under onnxruntime's optimization levels

``--fallbacks``: every law's LMPC on the paper's five conditions (5 s, nominal plant, the
experiment's settings); per law and condition the cycles outside the trust box (torque = the
feedback law's) and the cycles with a clamped residual (hil_runtime.bundle documents the rule).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from dataclasses import replace
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--cycles", type=int, default=3000)
    parser.add_argument("--bundles", type=Path, default=None)
    parser.add_argument("--laws", default="pd,pid,adrc,hinf,smc,mrac")
    parser.add_argument(
        "--fallbacks", action="store_true", help="also count trust-region fallbacks on the paper's conditions"
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument(
        "--session-sweep",
        action="store_true",
        help="also time each graph under onnxruntime's optimization levels / execution modes",
    )
    args = parser.parse_args()

    from hil_runtime.bundle import PolicyBundle
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.lmpc import make_lmpc_controller
    from models.lmpc.controller import bundle_path
    from models.robots import load_robot
    from models.sim import SimConfig, simulate

    robot = load_robot("ur5_paper")
    condition = load_conditions()[0]
    sim = SimConfig()
    short = replace(condition, duration_s=args.cycles * sim.period_s)
    out: dict = {
        "what": "t_L per control cycle, one arm, onnxruntime 1 intra-op thread",
        "cycles": args.cycles,
        "laws": {},
    }
    for law_name in args.laws.split(","):
        law = make_law(law_name, robot, sim.period_s)
        controller = make_lmpc_controller(law, robot, bundle_dir=args.bundles)
        simulate(robot, controller, [short], sim)
        closed = np.asarray(controller.cycle_times_s[100:]) * 1e6
        bundle = PolicyBundle.load(bundle_path(robot.name, law_name, args.bundles))
        state = bundle.initial_state(np.zeros(6))
        q = np.full(6, 0.1)
        import time

        bare = []
        for _ in range(args.cycles):
            start = time.perf_counter()
            bundle.step(q, q, q, q, q, state)
            bare.append(time.perf_counter() - start)
        bare_us = np.asarray(bare[100:]) * 1e6
        out["laws"][law_name] = {
            "controller_call_us": {
                "median": float(np.median(closed)),
                "p99": float(np.percentile(closed, 99)),
                "max": float(closed.max()),
            },
            "bundle_step_us": {"median": float(np.median(bare_us)), "p99": float(np.percentile(bare_us, 99))},
            "graph_nodes": _nodes(bundle.path / bundle.manifest["graph"]["file"]),
            "compute_nodes": _nodes(bundle.path / bundle.manifest["graph"]["file"], compute_only=True),
            "design": bundle.manifest.get("training", {}).get("design", "mlp"),
        }
        if args.session_sweep:
            out["laws"][law_name]["session_sweep_us"] = session_sweep(bundle, args.cycles)
    if args.fallbacks:
        out["trust_region"] = trust_counts(args.laws.split(","), args.bundles)
    import onnxruntime

    out["load_average"] = os.getloadavg()
    out["machine"] = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "onnxruntime": onnxruntime.__version__,
    }
    print(json.dumps(out, indent=2))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=2))


def trust_counts(laws: list[str], bundles: Path | None) -> dict:
    """Per law: fallback and clamp cycles of the LMPC on each of the paper's five conditions."""
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.lmpc import make_lmpc_controller
    from models.robots import load_robot
    from models.sim import SimConfig, simulate

    robot = load_robot("ur5_paper")
    conditions = load_conditions()
    sim = SimConfig()
    out = {}
    for law_name in laws:
        controller = make_lmpc_controller(make_law(law_name, robot, sim.period_s), robot, bundle_dir=bundles)
        with np.errstate(all="ignore"):
            traj = simulate(robot, controller, conditions, sim)
        counts = controller.trust_counters()
        out[law_name] = {
            "cycles_per_run": counts["cycles"],
            "fallback_cycles": dict(zip([c.name for c in conditions], counts["fallback_cycles"], strict=True)),
            "clamped_cycles": dict(zip([c.name for c in conditions], counts["clamped_cycles"], strict=True)),
            "within_limits": [bool(v) for v in traj.within_limits],
        }
    return out


def _nodes(path: Path, compute_only: bool = False) -> int:
    import onnx

    nodes = onnx.load(str(path)).graph.node
    return sum(1 for n in nodes if not compute_only or n.op_type != "Constant")


def session_sweep(bundle, cycles: int) -> dict:  # type: ignore[no-untyped-def]
    """Bare single-row run time (us, median / p99) of the bundle's graph per onnxruntime session option."""
    import time

    import onnxruntime as ort

    levels = {
        "disable_all": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
        "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
    }
    path = str(bundle.path / bundle.manifest["graph"]["file"])
    x = np.zeros((1, bundle.input_width))
    x[0, : 5 * bundle.n_joints] = 0.1
    out = {}
    for name, level in levels.items():
        for mode_name, mode in (
            ("sequential", ort.ExecutionMode.ORT_SEQUENTIAL),
            ("parallel", ort.ExecutionMode.ORT_PARALLEL),
        ):
            options = ort.SessionOptions()
            options.intra_op_num_threads, options.inter_op_num_threads = 1, 1
            options.execution_mode, options.graph_optimization_level, options.log_severity_level = mode, level, 3
            session = ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])
            y = np.zeros((1, session.get_outputs()[0].shape[-1]))
            binding = session.io_binding()
            binding.bind_ortvalue_input("x", ort.OrtValue.ortvalue_from_numpy(x))
            binding.bind_ortvalue_output("y", ort.OrtValue.ortvalue_from_numpy(y))
            times = []
            for _ in range(cycles):
                start = time.perf_counter()
                session.run_with_iobinding(binding)
                times.append(time.perf_counter() - start)
            us = np.asarray(times[100:]) * 1e6
            out[f"{name}/{mode_name}"] = [round(float(np.median(us)), 1), round(float(np.percentile(us, 99)), 1)]
    return out


if __name__ == "__main__":
    main()
