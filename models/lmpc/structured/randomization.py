"""Domain randomization of the structured LMPC's training rollouts (issue 24, docs/lmpc.md §12).

The expert (the HMPC) runs its training rollouts in a world drawn around a realism profile: each draw
scales the profile's sensing, actuation and plant errors by seeded factors (the ranges below), so the data
hold the states a real arm visits (errors from friction and payload, noisy and delayed measurements,
non-zero law torques) and the labels are the expert's answers to what the drives report there. The
ranges cover the profile and the issue's encoder-noise target (3e-4 rad, 0.2 rad/s) at their top.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from sim_target.realism import RealismSpec

#: encoder noise per draw: log-uniform between the profile's and this top (the issue's noise target)
ENCODER_NOISE_TOP_RAD = 3.0e-4
#: velocity noise per draw: uniform in [0, this] rad/s (the issue's noise target)
VELOCITY_NOISE_TOP_RAD_S = 0.2
#: measurement delay per draw: the profile's plus 0 or 1 period
EXTRA_DELAY_PERIODS = (0, 1)
#: friction (viscous, Coulomb, Stribeck) and torque ripple: x uniform in this range, per joint
FRICTION_SCALE = (0.5, 1.5)
#: payload: x uniform in this range of the profile's
PAYLOAD_SCALE = (0.0, 2.0)
#: link inertia and mass errors: 1 + uniform(-x, x), per link
INERTIA_ERROR = 0.1


def randomized_realism(base: RealismSpec, seed: int) -> RealismSpec:
    """One seeded draw of the world around ``base`` (module docstring); its noise seed is ``seed`` too."""
    rng = np.random.default_rng(seed)
    n = base.n_joints
    s, a, p = base.sensing, base.actuation, base.plant
    low = np.maximum(s.encoder_noise_rad, 1e-7)
    encoder = np.exp(rng.uniform(np.log(low), np.log(np.maximum(low, ENCODER_NOISE_TOP_RAD))))
    sensing = replace(
        s,
        encoder_noise_rad=encoder,
        velocity_noise_rad_s=s.velocity_noise_rad_s + rng.uniform(0.0, VELOCITY_NOISE_TOP_RAD_S, n),
        delay_periods=s.delay_periods + int(rng.choice(EXTRA_DELAY_PERIODS)),
    )
    actuation = replace(a, torque_ripple_ratio=a.torque_ripple_ratio * rng.uniform(*FRICTION_SCALE, n))
    plant = replace(
        p,
        viscous_friction_nm_s_per_rad=p.viscous_friction_nm_s_per_rad * rng.uniform(*FRICTION_SCALE, n),
        coulomb_friction_nm=p.coulomb_friction_nm * rng.uniform(*FRICTION_SCALE, n),
        stribeck_friction_nm=p.stribeck_friction_nm * rng.uniform(*FRICTION_SCALE, n),
        payload_kg=float(p.payload_kg * rng.uniform(*PAYLOAD_SCALE)),
        mass_scale=np.resize(p.mass_scale, n) * (1.0 + rng.uniform(-INERTIA_ERROR, INERTIA_ERROR, n)),
        inertia_scale=np.resize(p.inertia_scale, n) * (1.0 + rng.uniform(-INERTIA_ERROR, INERTIA_ERROR, n)),
    )
    return replace(base, name=f"{base.name}~{seed}", sensing=sensing, actuation=actuation, plant=plant, seed=seed)
