"""Plant parity vs substeps: max joint error of the pybullet plant against an RK4 reference over
2 s, and the plant's cost per control period. Prints JSON.

    python benchmarks/bench_plant_parity.py [--excursion-rad 0.005 0.01] [--substeps 1 4 16 32 64]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from models.dynamics import make_dynamics
from models.robots import load_robot
from models.sim.plant_parity import (
    DURATION_S,
    FREQUENCY_HZ,
    PERIOD_S,
    Q0_RAD,
    models_trajectory,
    plant_trajectory,
    torque_law,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--excursion-rad", type=float, nargs="+", default=[0.005, 0.01])
    parser.add_argument("--substeps", type=int, nargs="+", default=[1, 4, 8, 16, 32, 64])
    args = parser.parse_args()
    robot = load_robot("ur5_paper")
    dynamics = make_dynamics(robot, backend="pinocchio")
    n_periods = round(DURATION_S / PERIOD_S)
    rows = []
    for excursion in args.excursion_rad:
        amplitude_nm = np.diag(dynamics.mass_matrix(Q0_RAD)) * (2 * np.pi * FREQUENCY_HZ) ** 2 * excursion
        law = torque_law(dynamics, amplitude_nm)
        reference = models_trajectory(robot, "pinocchio", law, n_periods)
        for substeps in args.substeps:
            start = time.perf_counter()
            plant = plant_trajectory(law, n_periods, substeps)
            elapsed_s = time.perf_counter() - start
            rows.append(
                {
                    "excursion_rad": excursion,
                    "joint_range_rad": np.ptp(reference, axis=0).round(3).tolist(),
                    "substeps": substeps,
                    "max_error_rad": float(np.abs(plant - reference).max()),
                    "plant_and_law_us_per_period": round(elapsed_s / n_periods * 1e6, 1),
                }
            )
    print(
        json.dumps(
            {
                "benchmark": "plant_parity",
                "period_s": PERIOD_S,
                "duration_s": DURATION_S,
                "machine": f"{platform.machine()} {platform.processor() or ''} {platform.python_version()}".strip(),
                "results": rows,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
