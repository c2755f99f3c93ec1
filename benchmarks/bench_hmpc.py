"""HMPC benchmarks (JSON on stdout): per-cycle wall time for one arm, batch labeling throughput.

    python benchmarks/bench_hmpc.py                 # all
    python benchmarks/bench_hmpc.py --cycles 2000 --batch-states 4000 --workers 2

Per-cycle time: the HMPC controller (law step + candidates + Gauss-Newton/QP, warm-started) in
closed loop on the simulator, single arm, condition C4 of the paper (starts off the reference,
so the first cycles and the t = 2 s impulse are in the sample when cycles >= 2000). Batch:
states visited by the PD law alone on the five paper conditions (large errors, cold start),
labeled by ``solve_batch`` serially and on a process pool.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace

import numpy as np


def machine() -> dict:
    import scipy

    try:
        import pinocchio

        pin_version = pinocchio.__version__
    except ImportError:  # pragma: no cover
        pin_version = None
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "pinocchio": pin_version,
            "load_average_1min_at_start": os.getloadavg()[0]}  # fmt: skip


def cycle_times(robot_name: str, cycles: int, backend: str) -> dict:
    from models.conditions import Condition, load_conditions
    from models.feedback import make_law
    from models.feedback.pd import PDLaw
    from models.hmpc import make_hmpc_controller
    from models.robots import load_robot
    from models.sim import SimConfig, simulate

    robot = load_robot(robot_name)
    dt = 1e-3
    if robot_name == "ur5_paper":
        law = make_law("pd", robot, dt)
        condition = replace(load_conditions(robot=robot)[3], duration_s=cycles * dt)
        options: dict = {}
    else:  # panda: PD gains for its 7 joints; a sine around its ready pose
        law = PDLaw(robot.n_joints, dt, robot.torque_limit_nm, kp=np.array([600, 600, 600, 600, 250, 150, 50.0]),
                    kd=np.array([50, 50, 50, 20, 20, 20, 10.0]))  # fmt: skip
        ready = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
        condition = Condition(name="panda_sine", amplitude_rad=(0.3,) * 7, frequency_hz=(0.2,) * 7, duration_s=cycles * dt,
                              shape="sine", phase_s=0.0, offset_rad=ready, initial_state="reference",
                              disturbance=None)  # fmt: skip
        # The URDF's asymmetric joint ranges (e.g. joint 4 in [-3.07, -0.07]) do not fit the
        # symmetric |q| <= limit the robot model keeps; bound |q| by the widest range instead.
        options = {"position_limit_rad": (2.9, 1.77, 2.9, 3.08, 2.9, 3.76, 2.9)}
    controller = make_hmpc_controller(law, robot, backend=backend, **options)
    simulate(robot, controller, [condition], SimConfig(dt_s=dt))
    samples = np.asarray(controller.cycle_times_s[10:]) * 1e3
    return {"robot": robot_name, "joints": robot.n_joints, "horizon_steps": controller.config.horizon_steps,
            "backend": backend, "law": law.name, "cycles": int(samples.size),
            "median_ms": float(np.median(samples)), "p99_ms": float(np.percentile(samples, 99)),
            "max_ms": float(samples.max()), "mean_gauss_newton_iterations": float(np.mean(controller.iterations)),
            "fallbacks": dict(controller.fallbacks)}  # fmt: skip


def batch_throughput(states: int, workers: int) -> dict:
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.hmpc import ProcessPoolBatchExecutor, solve_batch
    from models.robots import load_robot
    from models.sim import SimConfig, make_controller, simulate

    robot = load_robot("ur5_paper")
    law = make_law("pd", robot, 1e-3)
    conditions = load_conditions(robot=robot)
    traj = simulate(robot, make_controller("fb", law, robot), conditions, SimConfig())
    rng = np.random.default_rng(0)
    run, step = rng.integers(0, len(conditions), states), rng.integers(0, traj.t_s.size, states)
    refs = [c.reference(traj.t_s) for c in conditions]
    q_d, qd_d, qdd_d = (np.stack([refs[r][i][s] for r, s in zip(run, step, strict=True)]) for i in range(3))
    args = (traj.q[run, step], traj.qd[run, step], q_d, qd_d, qdd_d)
    out: dict = {"states": states, "source": "PD-alone closed-loop states, five paper conditions, cold start"}
    start = time.perf_counter()
    _, status = solve_batch(law, robot, *args)
    out["serial_states_per_s"] = states / (time.perf_counter() - start)
    out["converged_fraction"] = float(np.mean(status == 0))
    with ProcessPoolBatchExecutor(workers) as executor:
        solve_batch(law, robot, *(a[:workers] for a in args), executor=executor, chunk_states=1)  # start workers
        start = time.perf_counter()
        solve_batch(law, robot, *args, executor=executor)
        out[f"pool_{workers}_states_per_s"] = states / (time.perf_counter() - start)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=3000)
    parser.add_argument("--batch-states", type=int, default=4000)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    result = {
        "machine": machine(),
        "cycle": [cycle_times("ur5_paper", args.cycles, "pinocchio"), cycle_times("panda", args.cycles, "pinocchio"),
                  cycle_times("ur5_paper", min(args.cycles, 300), "rne")],
        "batch": batch_throughput(args.batch_states, args.workers),
        "targets": {"median_ms": 1.0, "p99_ms": 2.0, "batch_states_per_s": 2000},
    }  # fmt: skip
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
