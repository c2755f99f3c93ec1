"""Graph-level helpers of bench_lmpc.py: onnxruntime sessions, bound single-row runners, interleaved timing,
the one-node floor graph and the float32 copy of a shipped graph (``--float32``).

(imported by bench_lmpc.py as ``import lmpc_graphs``: ``python benchmarks/bench_lmpc.py`` puts this
directory on sys.path)
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import onnxruntime as ort


def make_session(path: str, level_name: str = "all") -> ort.InferenceSession:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads, options.log_severity_level = 1, 1, 3
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = {
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
        "disable_all": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    }[level_name]
    return ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])


def bound_runner(session: ort.InferenceSession, width: int) -> Callable[[], object]:
    """A single-row run with IOBinding (what PolicyBundle.step does, without the Python around it)."""
    import onnxruntime as ort

    x = np.zeros((1, width))
    x[0, : min(width, 30)] = 0.1
    y = np.zeros(
        (1, session.get_outputs()[0].shape[-1] if isinstance(session.get_outputs()[0].shape[-1], int) else width)
    )
    binding = session.io_binding()
    binding.bind_ortvalue_input(session.get_inputs()[0].name, ort.OrtValue.ortvalue_from_numpy(x))
    binding.bind_ortvalue_output(session.get_outputs()[0].name, ort.OrtValue.ortvalue_from_numpy(y))
    return lambda: session.run_with_iobinding(binding)


def one_node_graph(path: Path, width: int = 6, nodes: int = 1) -> None:
    """y = x + x (``nodes`` chained Adds) on one (1, width) float64 row: onnxruntime's per-run and per-node
    cost without any work."""
    import onnx
    from onnx import TensorProto, helper

    names = ["x"] + [f"t{i}" for i in range(nodes - 1)] + ["y"]
    chain = [helper.make_node("Add", [names[i], names[i]], [names[i + 1]]) for i in range(nodes)]
    io = [helper.make_tensor_value_info(k, TensorProto.DOUBLE, [1, width]) for k in ("x", "y")]
    graph = helper.make_graph(chain, "adds", io[:1], io[1:])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))


def interleaved_us(runners: dict[str, Callable[[], object]], cycles: int) -> dict[str, list[float]]:
    """Each runner timed once per round, ``cycles`` rounds (the first 100 dropped): [median, p99] in us."""
    import time

    times: dict[str, list[float]] = {k: [] for k in runners}
    for _ in range(cycles):
        for key, run in runners.items():
            start = time.perf_counter()
            run()
            times[key].append(time.perf_counter() - start)
    figures = {}
    for key, values in times.items():
        us = np.asarray(values[100:]) * 1e6
        figures[key] = [round(float(np.median(us)), 1), round(float(np.percentile(us, 99)), 1)]
    return figures


def float32_copy(source: Path, target: Path) -> None:
    """The float64 graph at ``source`` in float32 (constants rounded, Casts to float32 retargeted), with a
    Cast at its input and output so that it still reads and writes the bundle's float64 row."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    model = onnx.load(str(source))
    graph = model.graph

    def single(tensor: onnx.TensorProto) -> onnx.TensorProto:
        return numpy_helper.from_array(numpy_helper.to_array(tensor).astype(np.float32), tensor.name)

    for tensor in graph.initializer:
        if tensor.data_type == TensorProto.DOUBLE:
            tensor.CopyFrom(single(tensor))
    for node in graph.node:
        for attribute in node.attribute:
            if attribute.name == "value" and attribute.t.data_type == TensorProto.DOUBLE:
                attribute.t.CopyFrom(single(attribute.t))
            if node.op_type == "Cast" and attribute.name == "to" and attribute.i == TensorProto.DOUBLE:
                attribute.i = TensorProto.FLOAT
    for info in graph.value_info:
        if info.type.tensor_type.elem_type == TensorProto.DOUBLE:
            info.type.tensor_type.elem_type = TensorProto.FLOAT
    x_name, y_name = graph.input[0].name, graph.output[0].name
    for node in graph.node:
        node.input[:] = [f"{x_name}_f32" if name == x_name else name for name in node.input]
        node.output[:] = [f"{y_name}_f32" if name == y_name else name for name in node.output]
    graph.node.insert(0, helper.make_node("Cast", [x_name], [f"{x_name}_f32"], to=TensorProto.FLOAT))
    graph.node.append(helper.make_node("Cast", [f"{y_name}_f32"], [y_name], to=TensorProto.DOUBLE))
    onnx.save(model, str(target))


def float32_compare(laws: list[str], bundles: Path | None, cycles: int) -> dict:
    """Per law: the float32 copy's probe differences and both graphs' bare run times, interleaved."""
    import tempfile

    from models.lmpc.controller import bundle_path

    out: dict = {
        "what": "shipped float64 graph vs its float32 copy (Cast in/out): bare single-row run, us median / p99",
        "cycles": cycles,
        "laws": {},
    }
    runners: dict[str, Callable[[], object]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for law_name in laws:
            directory = bundle_path("ur5_paper", law_name, bundles)
            manifest = json.loads((directory / "manifest.json").read_text())
            source = directory / manifest["graph"]["file"]
            target = Path(tmp) / f"{law_name}_float32.onnx"
            float32_copy(source, target)
            n = int(manifest["robot"]["n_joints"])
            width = int(sum(part["size"] for part in manifest["graph"]["input"]["layout"]))
            inputs = np.asarray(manifest["probes"]["inputs"], float)
            recorded = np.asarray(manifest["probes"]["outputs"], float)
            got = make_session(str(target)).run(None, {"x": inputs})[0]
            relative = np.abs(got - recorded) / np.maximum(np.abs(recorded), 1.0)
            out["laws"][law_name] = {
                "probes": len(inputs),
                "probe_max_rel_diff": float(relative.max()),
                "probe_tau_max_abs_diff_nm": float(np.abs(got - recorded)[:, :n].max()),
                "probe_trust_changed": int((np.abs(got[:, -2:] - recorded[:, -2:]) > 1e-3).any(axis=1).sum()),
            }
            runners[f"{law_name}:float64"] = bound_runner(make_session(str(source)), width)
            runners[f"{law_name}:float32"] = bound_runner(make_session(str(target)), width)
        figures = interleaved_us(runners, cycles)
    for key, figure in figures.items():
        law_name, label = key.split(":")
        out["laws"][law_name].setdefault("run_us", {})[label] = figure
    for entry in out["laws"].values():
        entry["float32_saves_pct"] = round(100 * (1 - entry["run_us"]["float32"][0] / entry["run_us"]["float64"][0]), 1)
    out["load_average"] = os.getloadavg()
    return out
