"""The target's pybullet plant from its config (``hil target serve``; sim_target/server.py)."""

from __future__ import annotations

from sim_target.config import TargetConfig, TargetConfigError
from sim_target.plant import PybulletPlant, default_urdf_path


def make_plant(config: TargetConfig) -> PybulletPlant:
    urdf = config.urdf if config.urdf is not None else default_urdf_path(config.robot or "ur5_paper")
    plant_cfg = config.plant
    try:
        plant = PybulletPlant(
            urdf,
            period_s=config.period_s,
            substeps=config.substeps,
            joint_names=plant_cfg.joint_names,
            initial_position_rad=plant_cfg.initial_position_rad,
            brake_holding_torque_nm=plant_cfg.brake_holding_torque_nm,
            encoder_noise_rad=plant_cfg.encoder_noise_rad,
            velocity_noise_rad_s=plant_cfg.velocity_noise_rad_s,
            seed=plant_cfg.seed,
        )
    except ValueError as exc:  # PlantError and the robot loader's ModelInputError
        raise TargetConfigError(f"plant: {exc}") from None
    if config.realism != "ideal":
        from sim_target.realism_profiles import load_realism

        try:  # RealismError names the profile file and field; the plant's own refusals say "realism:"
            plant.use_realism(
                load_realism(
                    config.realism,
                    plant.n_joints,
                    config.period_s,
                    config.period_s / plant.substeps,
                    plant.torque_limit_nm,
                )
            )
        except ValueError as exc:
            plant.close()
            raise TargetConfigError(str(exc)) from None
    return plant
