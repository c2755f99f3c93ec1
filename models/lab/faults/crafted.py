"""Crafted policy bundles for the fault campaign, built at run time from a shipped bundle.

Never shipped as product: :func:`craft_bundle` copies a bundle into a scratch directory, wraps its
ONNX graph so that its output misbehaves, and rewrites the manifest's sha256 of the graph. The
misbehaviour is confined to a narrow band of the first joint's measured position (``q[0]`` within
``TRIGGER_HALF_WIDTH_RAD`` of a trigger angle chosen away from every recorded probe input), so the
runtime's own loader (sha256, layout, recorded probes, saturation plateau) accepts the bundle as
it would accept a graph that goes wrong only off its training data; the campaign then starts the
arm inside that band.

Kinds (what the graph's output row ``y = [tau, tau_fb, next_state, trust]`` becomes in the band):

- ``nan``:       tau = NaN (the emulator's torque); tau_fb unchanged
- ``inf``:       tau = +inf
- ``nan_both``:  tau and tau_fb = NaN (nothing finite to apply)
- ``saturate``:  tau = +1e6 N·m on every joint (far past every torque limit)
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Literal

import numpy as np

CraftKind = Literal["nan", "inf", "nan_both", "saturate"]
CRAFT_KINDS: tuple[str, ...] = ("nan", "inf", "nan_both", "saturate")
TRIGGER_HALF_WIDTH_RAD = 0.02
SATURATING_TORQUE_NM = 1e6


class CraftError(RuntimeError):
    """The shipped bundle could not be wrapped (one line)."""

    exit_code = 2


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def choose_trigger_rad(manifest: dict, preferred_rad: float = 0.62) -> float:
    """A q[0] angle whose band holds no probe input (and is not 0, where the saturation probes sit)."""
    probes = manifest.get("probes") or {}
    q0 = np.asarray([row[0] for row in probes.get("inputs", [])], float)
    for step in range(200):
        candidate = preferred_rad + 0.013 * step * (1 if step % 2 else -1)
        if abs(candidate) < 4 * TRIGGER_HALF_WIDTH_RAD:
            continue
        if q0.size == 0 or np.min(np.abs(q0 - candidate)) > 3 * TRIGGER_HALF_WIDTH_RAD:
            return round(candidate, 6)
    raise CraftError("no trigger angle clear of the bundle's probe inputs")


def craft_bundle(source: Path, destination: Path, kind: CraftKind) -> float:
    """Write the crafted copy of ``source`` to ``destination``; returns the trigger angle (rad)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    if kind not in CRAFT_KINDS:
        raise CraftError(f"craft: unknown kind '{kind}' (known: {', '.join(CRAFT_KINDS)})")
    if destination.exists():
        shutil.rmtree(destination)
    shutil.copytree(source, destination)
    manifest_path = destination / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    graph_file = destination / manifest["graph"]["file"]
    n = int(manifest["robot"]["n_joints"])
    width_out = sum(int(slot["size"]) for slot in manifest["graph"]["output"]["layout"])
    input_name = manifest["graph"]["input"]["name"]
    output_name = manifest["graph"]["output"]["name"]
    trigger = choose_trigger_rad(manifest)

    model = onnx.load(str(graph_file))
    graph = model.graph
    raw = f"{output_name}__raw"
    for node in graph.node:  # the graph's last producer of y now writes y__raw
        node.output[:] = [raw if name == output_name else name for name in node.output]

    # Only operators the exporter emits (hil_runtime.bundle_security.ALLOWED_OPERATORS: no Where),
    # or the loader would refuse the crafted graph before the runtime ever ran it. in_band is 1.0
    # inside the trigger band, 0.0 outside; z = 1 - in_band, so z / z is NaN (0 / 0) in the band
    # and 1 outside, and 1 / z - 1 is +inf in the band and 0 outside.
    k = 2 * n if kind == "nan_both" else n  # the leading columns made bad (tau, or tau and tau_fb)

    def const(name: str, value: np.ndarray) -> None:
        graph.initializer.append(numpy_helper.from_array(np.asarray(value, np.float64), name))

    def index(name: str, value: int) -> None:
        graph.initializer.append(numpy_helper.from_array(np.array([value], np.int64), name))

    const("craft_one", np.array([1.0]))
    const("craft_saturating", np.array([SATURATING_TORQUE_NM]))
    const("craft_trigger", np.array([trigger]))
    const("craft_width", np.array([TRIGGER_HALF_WIDTH_RAD]))
    for name, value in (("zero", 0), ("one_i", 1), ("k", k), ("width_out", width_out), ("axis", -1)):
        index(f"craft_{name}", value)
    nodes = [
        helper.make_node("Slice", [input_name, "craft_zero", "craft_one_i", "craft_axis"], ["craft_q0"]),
        helper.make_node("Sub", ["craft_q0", "craft_trigger"], ["craft_dq0"]),
        helper.make_node("Abs", ["craft_dq0"], ["craft_abs"]),
        helper.make_node("Greater", ["craft_width", "craft_abs"], ["craft_in_band_bool"]),
        helper.make_node("Cast", ["craft_in_band_bool"], ["craft_in_band"], to=onnx.TensorProto.DOUBLE),
        helper.make_node("Sub", ["craft_one", "craft_in_band"], ["craft_z"]),
        helper.make_node("Slice", [raw, "craft_zero", "craft_k", "craft_axis"], ["craft_head"]),
        helper.make_node("Slice", [raw, "craft_k", "craft_width_out", "craft_axis"], ["craft_tail"]),
    ]
    if kind in ("nan", "nan_both"):
        nodes += [
            helper.make_node("Div", ["craft_z", "craft_z"], ["craft_nan_or_one"]),
            helper.make_node("Mul", ["craft_head", "craft_nan_or_one"], ["craft_bad"]),
        ]
    elif kind == "inf":
        nodes += [
            helper.make_node("Div", ["craft_one", "craft_z"], ["craft_inv"]),
            helper.make_node("Sub", ["craft_inv", "craft_one"], ["craft_inf_or_zero"]),
            helper.make_node("Add", ["craft_head", "craft_inf_or_zero"], ["craft_bad"]),
        ]
    else:  # saturate
        nodes += [
            helper.make_node("Mul", ["craft_head", "craft_z"], ["craft_kept"]),
            helper.make_node("Mul", ["craft_in_band", "craft_saturating"], ["craft_forced"]),
            helper.make_node("Add", ["craft_kept", "craft_forced"], ["craft_bad"]),
        ]
    nodes.append(helper.make_node("Concat", ["craft_bad", "craft_tail"], [output_name], axis=-1))
    graph.node.extend(nodes)
    del TensorProto  # only the helpers are needed; the dtype comes from the arrays
    onnx.checker.check_model(model)
    onnx.save(model, str(graph_file))

    manifest["files"][graph_file.name] = _sha256(graph_file)
    band = f"|q0 - {trigger}| < {TRIGGER_HALF_WIDTH_RAD}"
    manifest["graph"]["fused"] = f"{manifest['graph'].get('fused', '')} [fault campaign: '{kind}' when {band}]"
    from hil_runtime.bundle_security import write_manifest

    write_manifest(manifest_path, manifest)  # resealed: the campaign tests the runtime, not the bundle id
    return trigger


def tamper_bundle(source: Path, destination: Path) -> None:
    """A copy whose graph file has one byte flipped after the manifest was written (sha256 fails)."""
    if destination.exists():
        shutil.rmtree(destination)
    shutil.copytree(source, destination)
    manifest = json.loads((destination / "manifest.json").read_text())
    graph_file = destination / manifest["graph"]["file"]
    data = bytearray(graph_file.read_bytes())
    data[len(data) // 2] ^= 0x01
    graph_file.write_bytes(bytes(data))
