"""Why a law's η is what it is on an arm (docs/any_arm.md, "SMC on the real arms"). Prints JSON.

    # the composite's six terms per mode for one law, from a `hil experiment` results.json
    python benchmarks/any_arm_score_terms.py terms RESULTS.json --law smc
    # dE/dt energy per joint in windows after the disturbance, from its trajectories (FB vs HMPC, LMPC)
    python benchmarks/any_arm_score_terms.py response OUT_DIR --law smc --condition C1
    # the structured LMPC's physics loop, linearized along the robot's default references
    python benchmarks/any_arm_score_terms.py loop --robot panda --law smc

``terms`` renormalizes exactly as models.scoring.composite_scores does (every configuration of the
run, failed runs out of the maximum) and splits each mode's score into its weighted terms.

``loop``: the bundle's emulator is r = c τ_fb + g ID(q, q̇, q̈_d + K_p e + K_d ė) + residual
(models/lmpc/structured); with c = −1 the LMPC's torque is g ID(...) + residual. On the ideal plant
M q̈ + h = that torque, the physics part alone gives the error dynamics ë = −M⁻¹ G M (K_p e + K_d ė)
(+ the (1 − g) share of the feed-forward), whose eigenvalues are reported per pose of the reference:
the fitted (g, K_p, K_d), then with g = 1 and with the gains' diagonals only, to say which one moves
the loop across the imaginary axis.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from models.scoring import METRICS, WEIGHTS


def terms(results: Path, law: str) -> dict[str, Any]:
    data = json.loads(results.read_text())
    runs = data["runs"]
    conditions = sorted({r["condition"] for r in runs})
    largest: dict[str, dict[str, float]] = {}
    for c in conditions:
        ok = [r for r in runs if r["condition"] == c and r["finite"] and r["within_limits"]]
        ok = ok or [r for r in runs if r["condition"] == c]
        largest[c] = {m: max(r["metrics"][m] for r in ok) for m in METRICS}
    out: dict[str, Any] = {"results": str(results), "law": law, "modes": {}}
    for mode in sorted({r["mode"] for r in runs}):
        split = dict.fromkeys(METRICS, 0.0)
        for r in runs:
            if r["law"] == law and r["mode"] == mode:
                for m, w in zip(METRICS, WEIGHTS, strict=True):
                    top = largest[r["condition"]][m]
                    split[m] += w * (r["metrics"][m] / top if top > 0 else 0.0) / len(conditions)
        out["modes"][mode] = {
            "score": round(sum(split.values()), 4),
            "terms": {k: round(v, 4) for k, v in split.items()},
        }
    return out


def response(out_dir: Path, law: str, condition: str, disturbance_s: float) -> dict[str, Any]:
    windows = [(disturbance_s, disturbance_s + 0.02), (disturbance_s + 0.02, disturbance_s + 0.05)]
    windows += [(disturbance_s + 0.05, disturbance_s + 0.2), (disturbance_s + 0.2, np.inf)]
    result: dict[str, Any] = {"dir": str(out_dir), "law": law, "condition": condition, "modes": {}}
    for mode in ("fb", "hmpc", "lmpc"):
        path = out_dir / "trajectories" / f"{law}_{mode}_{condition}.npz"
        if not path.is_file():
            continue
        d = np.load(path)
        t = d["t"]
        e = np.degrees(d["q_ref"] - d["q"])
        dt = float(t[1] - t[0])
        dedt = np.diff(e, axis=0) / dt
        rows = {}
        for a, b in windows:
            w = (t[1:] >= a) & (t[1:] < b)
            rows[f"[{a:g},{b:g})"] = np.round((dedt[w] ** 2).sum(0) * dt, 3).tolist()
        step = np.abs(np.diff(d["tau"], axis=0)).max(0)
        result["modes"][mode] = {
            "dedt_rms_deg_s": round(float(np.sqrt((dedt**2).mean())), 4),
            "dedt_energy_per_joint_deg2_s": rows,
            "max_torque_step_nm": np.round(step, 2).tolist(),
        }
    return result


def loop(robot_name: str, law: str, bundles: Path, stride: int) -> dict[str, Any]:
    from models.conditions import load_conditions
    from models.dynamics import make_dynamics
    from models.robots import load_robot

    robot = load_robot(robot_name)
    n = robot.n_joints
    dyn = make_dynamics(robot, "pinocchio")
    manifest = json.loads((bundles / robot_name / law / "manifest.json").read_text())
    physics = manifest["training"]["summary"]["physics"]
    g, kp, kd = (np.asarray(physics[k], float) for k in ("g", "kp_1_s2", "kd_1_s"))
    variants = {
        "fitted": (g, kp, kd),
        "g=1": (np.ones(n), kp, kd),
        "diagonal gains": (g, np.diag(np.diag(kp)), np.diag(np.diag(kd))),
    }
    out: dict[str, Any] = {
        "robot": robot_name,
        "law": law,
        "c": physics["c"],
        "g": np.round(g, 3).tolist(),
        "kp_diagonal_1_s2": np.round(np.diag(kp), 1).tolist(),
        "kd_diagonal_1_s": np.round(np.diag(kd), 2).tolist(),
        "kp_symmetric_part_min_eig": round(float(np.linalg.eigvalsh((kp + kp.T) / 2).min()), 2),
        "conditions": {},
    }
    for condition in load_conditions(None, robot=robot):
        t = np.arange(0.0, condition.duration_s, 1e-3 * stride)
        q_ref = condition.reference(t)[0]
        mass = np.asarray(dyn.mass_matrix(q_ref))
        row = {}
        for name, (gv, p, d) in variants.items():
            worst = []
            for m in mass:
                b = np.linalg.solve(m, np.diag(gv) @ m)
                a = np.block([[np.zeros((n, n)), np.eye(n)], [-b @ p, -b @ d]])
                ev = np.linalg.eigvals(a)
                i = int(ev.real.argmax())
                worst.append((float(ev[i].real), float(abs(ev[i].imag) / (2 * np.pi))))
            arr = np.asarray(worst)
            k = int(arr[:, 0].argmax())
            row[name] = {
                "unstable_pose_share": round(float(np.mean(arr[:, 0] > 0)), 3),
                "max_real_1_s": round(float(arr[k, 0]), 3),
                "at_hz": round(float(arr[k, 1]), 3),
            }
        out["conditions"][condition.name] = row
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("terms")
    p.add_argument("results", type=Path)
    p.add_argument("--law", default="smc")
    p = sub.add_parser("response")
    p.add_argument("out_dir", type=Path)
    p.add_argument("--law", default="smc")
    p.add_argument("--condition", default="C1")
    p.add_argument("--disturbance-s", type=float, default=2.0)
    p = sub.add_parser("loop")
    p.add_argument("--robot", default="panda")
    p.add_argument("--law", default="smc")
    p.add_argument("--bundles", type=Path, default=Path(__file__).resolve().parents[1] / "models" / "bundles")
    p.add_argument("--stride", type=int, default=100, help="reference poses every STRIDE ms")
    args = parser.parse_args()
    if args.command == "terms":
        result = terms(args.results, args.law)
    elif args.command == "response":
        result = response(args.out_dir, args.law, args.condition, args.disturbance_s)
    else:
        result = loop(args.robot, args.law, args.bundles, args.stride)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
