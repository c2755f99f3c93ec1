"""t_L: per-cycle wall time of LMPC (law + emulator in one onnxruntime call), one arm, Python included.

Runs the shipped bundles' controller (models.lmpc.LMPCController, which is hil_runtime.bundle's
single-row path) in a closed loop on the paper's condition C1 and reports the per-call time, plus
the bare ``PolicyBundle.step`` time, each also as a ratio to onnxruntime's floor for the graph's node
count (a chain of as many Adds as the bundle has compute nodes, timed alternately with the bare step in
the same run: issue 24's t_L target is controller call median <= 2x that floor). Prints JSON.

    python benchmarks/bench_lmpc.py [--cycles 3000] [--bundles models/bundles] [--robot ur5_paper|ur5|panda]
    python benchmarks/bench_lmpc.py --fallbacks      # + trust-region counters on the paper's 5 conditions
    python benchmarks/bench_lmpc.py --session-sweep  # + each graph under onnxruntime's optimization levels
    python benchmarks/bench_lmpc.py --compact        # shipped graph vs today's graph code, interleaved
    python benchmarks/bench_lmpc.py --bundles OLD --against NEW   # two bundle sets' t_L, interleaved
    python benchmarks/bench_lmpc.py --reexport-to DIR # the shipped bundles in today's graph, under DIR
    python benchmarks/bench_lmpc.py --float32        # each shipped graph vs its float32 copy, interleaved

``--compact``: per law, the shipped bundle's emulator (from ``results/lmpc/trained_<law>.pt``, the
weights ``hil pipeline --design structured`` keeps, when present: compact graphs fold the weights
into constants; else rebuilt from the graph's initializers and its manifest, which only pre-compact
bundles allow) exported with the working tree's graph code (models.lmpc.structured) to a temporary file;
node counts, the new graph's outputs on the shipped manifest's probes against the recorded ones
(max relative difference), and the bare single-row run time of both graphs, plus a one-node graph
(onnxruntime's per-run floor), all timed interleaved in one process.

``--float32``: per law, the shipped float64 graph and a float32 copy of it (every constant rounded to
float32, a Cast at the input and at the output so the bundle contract's float64 row stays): the
float32 graph's outputs on the manifest's recorded probes (largest relative and absolute torque
difference, trust outputs that changed) and the bare single-row run time of both, interleaved.

``--fallbacks``: every law's LMPC on the paper's five conditions (5 s, nominal plant, the
experiment's settings); per law and condition the cycles outside the trust box (torque = the
feedback law's) and the cycles with a clamped residual (hil_runtime.bundle documents the rule).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from lmpc_graphs import bound_runner, float32_compare, interleaved_us, make_session, one_node_graph

if TYPE_CHECKING:
    from hil_runtime.bundle import PolicyBundle
    from models.robots import RobotModel


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--cycles", type=int, default=3000)
    parser.add_argument("--bundles", type=Path, default=None)
    parser.add_argument("--robot", default="ur5_paper", help="the robot whose shipped bundles are timed")
    parser.add_argument("--laws", default="pd,pid,adrc,hinf,smc,mrac")
    parser.add_argument(
        "--fallbacks", action="store_true", help="also count trust-region fallbacks on the paper's conditions"
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument(
        "--compact", action="store_true", help="only compare the shipped graphs with today's graph code"
    )
    parser.add_argument(
        "--against",
        type=Path,
        default=None,
        help="only time these bundles against --bundles (controller call and bare step, interleaved in rounds)",
    )
    parser.add_argument("--rounds", type=int, default=6, help="with --against: alternations per law")
    parser.add_argument(
        "--reexport-to",
        type=Path,
        default=None,
        help="only write the shipped structured bundles, re-exported with today's graph code, under this directory",
    )
    parser.add_argument(
        "--float32", action="store_true", help="only compare each shipped graph with a float32 copy of it"
    )
    parser.add_argument(
        "--session-sweep",
        action="store_true",
        help="also time each graph under onnxruntime's optimization levels / execution modes",
    )
    args = parser.parse_args()
    if args.reexport_to is not None:
        for law_name in args.laws.split(","):
            print(json.dumps(reexport_shipped(law_name, args.bundles, args.reexport_to)))
        return
    if args.against is not None or args.compact or args.float32:
        if args.float32:
            result = float32_compare(args.laws.split(","), args.bundles, args.cycles)
        elif args.against is not None:
            result = time_against(args.laws.split(","), args.bundles, args.against, args.cycles, args.rounds)
        else:
            result = compact_compare(args.laws.split(","), args.bundles, args.cycles)
        print(json.dumps(result, indent=2))
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(result, indent=2))
        return

    from hil_runtime.bundle import PolicyBundle
    from models.cli.options import gain_set_for
    from models.default_conditions import default_conditions
    from models.feedback import make_law
    from models.lmpc import make_lmpc_controller
    from models.lmpc.controller import bundle_path
    from models.robots import load_robot
    from models.sim import SimConfig, simulate

    robot = load_robot(args.robot)
    condition = default_conditions(robot)[0]
    sim = SimConfig()
    short = replace(condition, duration_s=args.cycles * sim.period_s)
    out: dict = {
        "what": "t_L per control cycle, one arm, onnxruntime 1 intra-op thread; floor_ratio: t_L median over the "
        "median run of a graph of as many chained Adds as the bundle has compute nodes (the onnxruntime floor for "
        "that node count), timed in the same run",
        "robot": robot.name,
        "cycles": args.cycles,
        "laws": {},
    }
    for law_name in args.laws.split(","):
        law = make_law(law_name, robot, sim.period_s, gain_set_for(robot.name, None))
        bundle = PolicyBundle.load(bundle_path(robot.name, law_name, args.bundles))
        graph = bundle.path / bundle.manifest.graph.file
        with tempfile.TemporaryDirectory() as tmp:
            floor_graph = Path(tmp) / "adds.onnx"
            one_node_graph(floor_graph, width=robot.n_joints, nodes=max(_nodes(graph, compute_only=True), 1))
            floor_run = bound_runner(make_session(str(floor_graph)), robot.n_joints)
            controller = _FloorAfterEachCall(make_lmpc_controller(law, robot, bundle_dir=args.bundles), floor_run)
            simulate(robot, controller, [short], sim)
            bare_us, floor_us = _bare_step_and_floor_us(bundle, robot.n_joints, floor_run, args.cycles)
        closed = np.asarray(controller.cycle_times_s[100:]) * 1e6
        closed_floor = np.asarray(controller.floor_times_s[100:]) * 1e6
        floor_median = float(np.median(floor_us))
        out["laws"][law_name] = {
            "controller_call_us": {
                "median": float(np.median(closed)),
                "p99": float(np.percentile(closed, 99)),
                "max": float(closed.max()),
            },
            "bundle_step_us": {"median": float(np.median(bare_us)), "p99": float(np.percentile(bare_us, 99))},
            # the floor graph run right after each call (closed loop) and after each bare step
            "node_floor_us": {
                "closed_loop_median": float(np.median(closed_floor)),
                "bare_median": floor_median,
                "bare_p99": float(np.percentile(floor_us, 99)),
            },
            "floor_ratio": {
                "controller_call": float(np.median(closed)) / float(np.median(closed_floor)),
                "bundle_step": float(np.median(bare_us)) / floor_median,
            },
            "graph_nodes": _nodes(graph),
            "compute_nodes": _nodes(graph, compute_only=True),
            "design": bundle.manifest.training.get("design", "mlp"),
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


class _FloorAfterEachCall:
    """The experiment's controller, with the node-count floor graph run (and timed) right after each call:
    both see the same closed loop's caches."""

    def __init__(self, inner: Any, floor_run: Callable[[], object]) -> None:
        self.inner, self.floor_run = inner, floor_run
        self.floor_times_s: list[float] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def __call__(self, *args: Any) -> Any:
        import time

        tau = self.inner(*args)
        start = time.perf_counter()
        self.floor_run()
        self.floor_times_s.append(time.perf_counter() - start)
        return tau


def _bare_step_and_floor_us(
    bundle: PolicyBundle, n_joints: int, floor_run: Callable[[], object], cycles: int
) -> tuple[np.ndarray, np.ndarray]:
    """``bundle.step`` (the runtime's single-row call) and the floor graph timed alternately, ``cycles`` each
    (the first 100 dropped), in us."""
    import time

    state = bundle.initial_state(np.zeros(n_joints))
    q = np.full(n_joints, 0.1)
    bare, floor = [], []
    for _ in range(cycles):
        start = time.perf_counter()
        bundle.step(q, q, q, q, q, state)
        middle = time.perf_counter()
        floor_run()
        floor.append(time.perf_counter() - middle)
        bare.append(middle - start)
    return np.asarray(bare[100:]) * 1e6, np.asarray(floor[100:]) * 1e6


def _nodes(path: Path, compute_only: bool = False) -> int:
    import onnx

    nodes = onnx.load(str(path)).graph.node
    return sum(1 for n in nodes if not compute_only or n.op_type != "Constant")


def session_sweep(bundle: PolicyBundle, cycles: int) -> dict[str, list[float]]:
    """Bare single-row run time (us, median / p99) of the bundle's graph per onnxruntime session option."""
    import time

    import onnxruntime as ort

    levels = {
        "disable_all": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
        "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
    }
    path = str(bundle.path / bundle.manifest.graph.file)
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


def structured_policy_from_bundle(bundle_dir: Path) -> tuple[Any, dict[str, Any]]:
    """The shipped structured bundle's policy module rebuilt from its graph's weights and its manifest
    (for bundles exported before the trained weights were kept: models.lmpc.structured.save_trained)."""
    import onnx
    import torch
    from onnx import numpy_helper

    from models.feedback import make_law
    from models.lmpc.structured import StructuredEmulator, structured_policy_class
    from models.robots import load_robot

    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    training, trust = manifest["training"], manifest["trust_region"]
    config, physics, residual = training["config"], training["summary"]["physics"], training["summary"]["residual"]
    robot = load_robot(config["robot"])
    weights = {t.name: numpy_helper.to_array(t) for t in onnx.load(str(bundle_dir / "policy.onnx")).graph.initializer}
    model = StructuredEmulator(robot, tuple(config["hidden"]), np.asarray(residual["bound_nm"]), config["ff_point"])
    state = model.state_dict()
    for name in state:
        key = f"emulator.{name}"
        if key in weights:
            state[name] = torch.as_tensor(np.array(weights[key], dtype=np.float64))
    model.load_state_dict(state)
    model.frozen = tuple(
        torch.as_tensor(np.asarray(physics[k], dtype=np.float64)) for k in ("c", "g", "kp_1_s2", "kd_1_s")
    )
    model.use_residual = bool(residual["used"])
    law = make_law(manifest["law"]["name"], robot, manifest["period_s"], training["gain_set"])
    trust_spec = {k: trust[k] for k in ("feature_low", "feature_high", "box_margin", "residual_bound_nm")}
    return structured_policy_class()(law, model.double().eval(), True, trust_spec, "eq22+qdd_d").eval(), manifest


def time_against(laws: list[str], base: Path | None, other: Path, cycles: int, rounds: int) -> dict:
    """t_L of two bundle sets, interleaved: per law, ``rounds`` alternations of a closed loop on C1
    (``cycles`` controller calls each, the first 100 dropped) and of bare ``PolicyBundle.step`` calls."""
    import time

    from hil_runtime.bundle import PolicyBundle
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.lmpc import make_lmpc_controller
    from models.lmpc.controller import bundle_path
    from models.robots import load_robot
    from models.sim import SimConfig, simulate

    robot = load_robot("ur5_paper")
    sim = SimConfig()
    short = replace(load_conditions()[0], duration_s=cycles * sim.period_s)
    sets = {"base": base, "other": other}
    out: dict = {
        "what": "t_L per control cycle (us, median / p99), one arm; base = --bundles, other = --against",
        "bundles": {k: str(v) if v is not None else "shipped" for k, v in sets.items()},
        "cycles": cycles,
        "rounds": rounds,
        "laws": {},
    }
    for law_name in laws:
        calls: dict[str, list[float]] = {k: [] for k in sets}
        bare: dict[str, list[float]] = {k: [] for k in sets}
        nodes = {}
        for _ in range(rounds):
            for key, directory in sets.items():
                controller = make_lmpc_controller(make_law(law_name, robot, sim.period_s), robot, bundle_dir=directory)
                simulate(robot, controller, [short], sim)
                calls[key].extend(controller.cycle_times_s[100:])
                bundle = PolicyBundle.load(bundle_path(robot.name, law_name, directory))
                nodes[key] = _nodes(bundle.path / bundle.manifest.graph.file, compute_only=True)
                state, q = bundle.initial_state(np.zeros(6)), np.full(6, 0.1)
                for i in range(cycles):
                    start = time.perf_counter()
                    bundle.step(q, q, q, q, q, state)
                    if i >= 100:
                        bare[key].append(time.perf_counter() - start)

        def figure(values: list[float]) -> list[float]:
            us = np.asarray(values) * 1e6
            return [round(float(np.median(us)), 1), round(float(np.percentile(us, 99)), 1)]

        out["laws"][law_name] = {
            "compute_nodes": nodes,
            "controller_call_us": {k: figure(v) for k, v in calls.items()},
            "bundle_step_us": {k: figure(v) for k, v in bare.items()},
        }
    out["load_average"] = os.getloadavg()
    return out


TRAINED_DIR = Path("results/lmpc")  # hil pipeline --design structured's default --work (trained_<law>.pt)


def reexport_shipped(law_name: str, bundles: Path | None, out_root: Path) -> dict:
    """A shipped structured bundle re-exported with today's graph code (models.lmpc.structured.export_trained:
    the same emulator, law, trust box and residual bound; fresh probes) to <out_root>/<robot>/<law>; returns
    the largest difference of the new graph from the shipped manifest's recorded probe outputs."""
    from hil_runtime.bundle import PolicyBundle
    from models.lmpc.controller import bundle_path
    from models.lmpc.structured import config_from_json, export_trained, reexport

    source = bundle_path("ur5_paper", law_name, bundles)
    manifest = json.loads((source / "manifest.json").read_text())
    robot_name = manifest["robot"]["name"]
    out = out_root / robot_name / law_name
    trained = TRAINED_DIR / f"trained_{law_name}.pt"
    if trained.is_file():  # the weights hil pipeline kept: the only source for compact-graph bundles
        reexport(TRAINED_DIR, out_root, (law_name,), log=lambda _: None)
    else:  # pre-compact bundles kept the emulator's weights as graph initializers
        policy, manifest = structured_policy_from_bundle(source)
        training, trust = manifest["training"], manifest["trust_region"]
        config = config_from_json(training["config"])
        # bound = scale * label_max + 1e-3 (export_trained): the label maxima back from the recorded bound
        label_max = (np.asarray(trust["residual_bound_nm"], float) - 1e-3) / config.bound_scale
        box = (np.asarray(trust["feature_low"], float), np.asarray(trust["feature_high"], float))
        export_trained(
            out,
            law_name,
            policy.law.robot if hasattr(policy.law, "robot") else _robot(robot_name),
            policy.emulator,
            box,
            label_max,
            config,
            training["summary"],
        )
    bundle = PolicyBundle.load(out)
    probes = manifest["probes"]
    inputs, recorded = np.asarray(probes["inputs"], float), np.asarray(probes["outputs"], float)
    n = bundle.n_joints
    q, qd, q_d, qd_d, qdd_d = (inputs[:, i * n : (i + 1) * n] for i in range(5))
    state_end = 5 * n + bundle.state_size  # a graph reading tau_prev has it after the law's state
    previous = inputs[:, state_end:] if bundle.takes_previous_torque else None
    tau, tau_fb, state = bundle.step_batch(q, qd, q_d, qd_d, qdd_d, inputs[:, 5 * n : state_end], previous)
    got = np.concatenate([tau, tau_fb, state, bundle.last_trust_batch], 1)
    return {
        "law": law_name,
        "bundle": str(out),
        "shipped_probe_max_rel_diff": float((np.abs(got - recorded) / np.maximum(np.abs(recorded), 1.0)).max()),
        "compute_nodes": _nodes(out / bundle.manifest.graph.file, compute_only=True),
        "rebuilt_from": str(trained) if trained.is_file() else "the shipped graph's initializers",
    }


def _robot(name: str) -> RobotModel:
    from models.robots import load_robot

    return load_robot(name)


def compact_compare(laws: list[str], bundles: Path | None, cycles: int) -> dict:
    """Shipped graph vs today's graph code per law: nodes, probe equality, interleaved run times."""
    import tempfile

    import onnxruntime

    from models.lmpc.controller import bundle_path

    out: dict = {
        "what": "bare single-row graph run (IOBinding, 1 thread), us median / p99",
        "cycles": cycles,
        "laws": {},
    }
    runners: dict[str, Callable[[], object]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for count in (1, 60):
            floor = Path(tmp) / f"adds_{count}.onnx"
            one_node_graph(floor, nodes=count)
            runners[f"chained_adds_{count}/all"] = bound_runner(make_session(str(floor)), 6)
        for law_name in laws:
            directory = bundle_path("ur5_paper", law_name, bundles)
            manifest = json.loads((directory / "manifest.json").read_text())
            width = int(sum(part["size"] for part in manifest["graph"]["input"]["layout"]))
            rebuilt = reexport_shipped(law_name, bundles, Path(tmp))
            path = Path(tmp) / manifest["robot"]["name"] / law_name / manifest["graph"]["file"]
            old_path = str(directory / manifest["graph"]["file"])
            probes = manifest["probes"]
            inputs, recorded = np.asarray(probes["inputs"], float), np.asarray(probes["outputs"], float)
            got = make_session(str(path)).run(None, {"x": inputs})[0]
            scale = np.maximum(np.abs(recorded), 1.0)
            written = json.loads((path.parent / "manifest.json").read_text())
            out["laws"][law_name] = {
                "compute_nodes": {"shipped": _nodes(Path(old_path), True), "new": _nodes(path, True)},
                "probe_max_abs_diff": float(np.abs(got - recorded).max()),
                "probe_max_rel_diff": float((np.abs(got - recorded) / scale).max()),
                # the export's own check: the new graph vs the graph code's torch forward
                "new_onnx_vs_torch_max_abs": written["validation"]["onnx_vs_torch_max_abs_nm"],
                "rebuilt_from": rebuilt["rebuilt_from"],
            }
            for label, p, level in (
                ("shipped/all", old_path, "all"),
                ("new/all", str(path), "all"),
                ("new/basic", str(path), "basic"),
            ):
                runners[f"{law_name}:{label}"] = bound_runner(make_session(p, level), width)
        figures = interleaved_us(runners, cycles)
    for key, figure in figures.items():
        if ":" in key:
            law_name, label = key.split(":")
            out["laws"][law_name].setdefault("run_us", {})[label] = figure
        else:
            out[key + "_us"] = figure
    out["load_average"] = os.getloadavg()
    out["machine"] = {
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "onnxruntime": onnxruntime.__version__,
    }
    return out


if __name__ == "__main__":
    main()
