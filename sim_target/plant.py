"""The HIL plant: a fixed-base pybullet arm stepped one control period at a time.

The emulated drives (``sim_target/drives.py``) call :meth:`PybulletPlant.step` once per SYNC with the
motor torques they were commanded and which joints are braked (drive not in Operation Enabled).

pybullet defaults that would make this arm differ from the project's own dynamics, all undone here
(see :func:`load_arm`):

- every joint starts with a velocity motor (a hidden brake): disabled with force 0;
- links get linear/angular damping 0.04: zeroed, and joint damping zeroed;
- inertia is recomputed from collision shapes unless ``URDF_USE_INERTIA_FROM_FILE`` is given;
- a link with no ``<inertial>`` element (e.g. ``ur5_paper``'s ``flange``) gets mass 1 kg and inertia
  diag(1, 1, 1): reset to zero, else the arm carries a phantom kilogram at its flange.

Integration is pybullet's semi-implicit Euler. Each control period is ``substeps`` internal steps of
``period_s / substeps`` with the torque held (zero-order hold); pybullet keeps applied torques over
its internal substeps. Its global error is first order in the step, so parity with an RK4 reference
to 1e-3 rad needs substeps: the error is about h × (velocity change), 1.3e-2 rad with one 1 ms
step against 4e-4 with 32 on tests/integration/test_plant_parity.py's trajectory.

Faults that belong to the plant: encoder noise (seeded), a payload on the flange, an external joint
torque impulse (the paper's disturbance).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pybullet

from sim_target.arm_loading import MOVABLE_JOINT_TYPES, PlantError, default_urdf_path, load_arm
from sim_target.impulse import PAPER_DISTURBANCE, TorqueImpulse, external_profile_nm
from sim_target.plant_inputs import bool_flags, finite_floats
from sim_target.plant_protocol import JointState
from sim_target.realism import RealismModel, RealismSpec

__all__ = [
    "PAPER_DISTURBANCE",
    "JointState",
    "PlantError",
    "PybulletPlant",
    "TorqueImpulse",
    "default_urdf_path",
    "load_arm",
]

GRAVITY_M_S2 = 9.81
# 32 steps of 31 µs per 1 ms period: semi-implicit Euler's first-order error then stays under
# 1e-3 rad over 2 s for joint moves of a few tenths of a radian (benchmarks/bench_plant_parity.py).
DEFAULT_SUBSTEPS = 32
_BRAKE_POSITION_GAIN = 0.5  # fraction of the position error the brake motor removes per substep
# Every joint braked and not one moved by more than this over a period: the brakes hold the arm
# (at 8+ substeps at a fixed point of pybullet's solver, to the last bit; at 4, in a 6e-9 rad limit
# cycle; its reported velocity there is a ~1e-5 rad/s artefact), and the periods after it are not
# integrated until something changes (a drive enabled, a payload, an impulse, a reset): a held arm
# cost pybullet 2-3 times a free period (its position motors), most of an idle target's CPU. A
# brake that slips (load over its holding torque) accelerates far past this and is integrated.
_HELD_MOTION_RAD = 1e-8


class PybulletPlant:
    """A fixed-base pybullet arm under joint torque control, one control period per :meth:`step`.

    Args:
        urdf: the arm's URDF.
        period_s: control period (the zero-order-hold interval).
        substeps: pybullet steps per period (the physics step is ``period_s / substeps``).
        joint_names: the controlled joints in drive order; default every revolute joint. Other
            movable joints (e.g. a gripper's fingers) are held at their initial position.
        brake_holding_torque_nm: brake capacity per joint; default twice the URDF effort limit.
        encoder_noise_rad, velocity_noise_rad_s: standard deviations of measurement noise.
        seed: seeds the measurement noise, so a noisy run is reproducible.
        realism: the sensing/actuation/plant profile shared with the models simulator
            (``sim_target/realism.py``, docs/realism.md); None: today's ideal world.
    """

    def __init__(
        self,
        urdf: Path | str | None = None,
        *,
        period_s: float = 1e-3,
        substeps: int = DEFAULT_SUBSTEPS,
        joint_names: Sequence[str] | None = None,
        initial_position_rad: np.ndarray | Sequence[float] | None = None,
        brake_holding_torque_nm: Sequence[float] | None = None,
        encoder_noise_rad: float = 0.0,
        velocity_noise_rad_s: float = 0.0,
        seed: int = 0,
        realism: RealismSpec | None = None,
    ) -> None:
        if not period_s > 0.0:
            raise PlantError(f"period_s must be positive, got {period_s}")
        if substeps < 1:
            raise PlantError(f"substeps must be at least 1, got {substeps}")
        self.urdf = Path(urdf) if urdf is not None else default_urdf_path()
        self.period_s = float(period_s)
        self.substeps = int(substeps)
        self._client = pybullet.connect(pybullet.DIRECT)
        try:
            self._body = load_arm(self._client, self.urdf)
            self._init_joints(joint_names)
        except Exception:
            pybullet.disconnect(self._client)
            raise
        pybullet.setGravity(0.0, 0.0, -GRAVITY_M_S2, physicsClientId=self._client)
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=self.period_s, numSubSteps=self.substeps, physicsClientId=self._client
        )
        if brake_holding_torque_nm is None:
            self.brake_holding_torque_nm = 2.0 * self.torque_limit_nm
        else:
            self.brake_holding_torque_nm = self._vector(brake_holding_torque_nm, "brake_holding_torque_nm")
        self._initial_position_rad = (
            np.zeros(self.n_joints)
            if initial_position_rad is None
            else self._vector(initial_position_rad, "initial_position_rad")
        )
        self._encoder_noise_rad = float(encoder_noise_rad)
        self._velocity_noise_rad_s = float(velocity_noise_rad_s)
        self._seed = int(seed)
        self._impulses: list[TorqueImpulse] = []
        self._payload_kg = 0.0
        self._world: RealismModel | None = None
        self._measured: JointState | None = None  # the last measurement, made on demand (state)
        self._floats: tuple[list[float], list[float], list[float]] = ([], [], [])  # its values
        self.reset()
        if realism is not None:
            self.use_realism(realism)

    # --- set-up -------------------------------------------------------------------------------

    def _init_joints(self, joint_names: Sequence[str] | None) -> None:
        movable: dict[str, int] = {}
        revolute: list[str] = []
        lower, upper, effort = {}, {}, {}
        for index in range(pybullet.getNumJoints(self._body, physicsClientId=self._client)):
            info = pybullet.getJointInfo(self._body, index, physicsClientId=self._client)
            if info[2] not in MOVABLE_JOINT_TYPES:
                continue
            name = info[1].decode()
            movable[name] = index
            lower[name], upper[name], effort[name] = info[8], info[9], info[10]
            if info[2] == pybullet.JOINT_REVOLUTE:
                revolute.append(name)
        names = list(joint_names) if joint_names is not None else revolute
        unknown = [name for name in names if name not in movable]
        if unknown:
            raise PlantError(f"{self.urdf}: joint(s) {unknown} not movable joints of this URDF")
        self.joint_names: tuple[str, ...] = tuple(names)
        self.n_joints = len(names)
        self._joint_indices = [movable[name] for name in names]
        self._held_indices = [index for name, index in movable.items() if name not in names]
        self.position_limit_rad = np.array([[lower[n], upper[n]] for n in names])
        self.torque_limit_nm = np.array([effort[n] for n in names], dtype=float)
        self._torque_limit: list[float] = self.torque_limit_nm.tolist()  # the hot path's copy
        # pybullet's mass matrix is over every movable joint, in index order
        self._movable_indices = sorted(movable.values())
        self._mass_matrix_index = [self._movable_indices.index(movable[name]) for name in names]
        # The payload rides on the last link of the chain (the massless flange for ur5_paper).
        self._payload_link = pybullet.getNumJoints(self._body, physicsClientId=self._client) - 1
        dyn = pybullet.getDynamicsInfo(self._body, self._payload_link, physicsClientId=self._client)
        self._payload_link_mass_kg = float(dyn[0])
        self._payload_link_inertia = np.array(dyn[2], dtype=float)

    def _vector(self, values: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
        array = np.asarray(values, dtype=float)
        if array.shape != (self.n_joints,):
            raise PlantError(f"{name}: expected {self.n_joints} values, got shape {array.shape}")
        if not np.all(np.isfinite(array)):
            raise PlantError(f"{name}: non-finite value in {array.tolist()}")
        return array

    # --- the TargetPlant protocol ---------------------------------------------------------------

    def reset(
        self,
        position_rad: np.ndarray | Sequence[float] | None = None,
        velocity_rad_s: np.ndarray | Sequence[float] | None = None,
    ) -> JointState:
        """Put the arm at ``position_rad`` (default: the initial position) moving at
        ``velocity_rad_s`` (default: at rest), time 0."""
        q0 = self._initial_position_rad if position_rad is None else self._vector(position_rad, "position_rad")
        v0 = np.zeros(self.n_joints) if velocity_rad_s is None else self._vector(velocity_rad_s, "velocity_rad_s")
        for index, q, v in zip(self._joint_indices, q0, v0, strict=True):
            pybullet.resetJointState(self._body, index, float(q), float(v), physicsClientId=self._client)
        for index in self._held_indices:
            pybullet.resetJointState(self._body, index, 0.0, 0.0, physicsClientId=self._client)
        self._time_s = 0.0
        self._steps = 0
        self._applied: list[float] = [0.0] * self.n_joints  # the motor torque over the last period
        self._braked = [False] * self.n_joints
        self._brake_position_rad = np.array(q0, dtype=float)
        self._rng = np.random.default_rng(self._seed)
        self._held: JointState | None = None  # the true state while every brake holds a still arm
        self._motor_mask: list[bool] | None = None  # the brakes pybullet's motors were last set to
        if self._world is not None:
            self._world.reset(np.asarray(q0, dtype=float), v0)
        self._measure()
        return self.state()

    def state(self) -> JointState:
        """The last measurement (the same noise sample until the next step)."""
        if self._measured is None:  # made on demand: the target's cycle reads measured_floats
            q, qd, torque = self._floats
            self._measured = JointState(np.array(q), np.array(qd), np.array(torque), self._time_s)
        return self._measured

    def measured_floats(self) -> tuple[list[float], list[float], list[float]]:
        """:meth:`state`'s position, velocity and torque as plain floats (the same values), without
        a JointState or an array: what the emulated drives pack every period. Not to be modified."""
        return self._floats

    def step(self, torque_nm: np.ndarray | Sequence[float], brake_engaged: np.ndarray | Sequence[bool]) -> JointState:
        """:meth:`advance`, then the new :meth:`state`."""
        self.advance(torque_nm, brake_engaged)
        return self.state()

    def advance(self, torque_nm: np.ndarray | Sequence[float], brake_engaged: np.ndarray | Sequence[bool]) -> None:
        """Advance one control period with ``torque_nm`` held; braked joints are held still.

        The motor torque is clipped to the URDF effort limit and is zero on a braked joint (its
        drive is not enabled). External impulses are added on top; the brake resists them up to
        its holding torque. (Six joints in plain floats: numpy's per-call overhead on 6-element
        arrays cost more than pybullet's step itself at a few substeps.)
        """
        command = finite_floats(torque_nm, self.n_joints, self._vector, "torque_nm")
        braked = bool_flags(brake_engaged, self.n_joints)
        motor = [
            0.0 if held else (limit if c > limit else (-limit if c < -limit else c))
            for c, held, limit in zip(command, braked, self._torque_limit, strict=True)
        ]
        all_braked = all(braked)
        external_nm = self._external_profile_nm()
        if self._held is not None and external_nm is None and all_braked:
            self._advance_held()
            return
        self._held = None
        before = self._last_q
        # A brake locks the joint where it engaged, up to its holding torque. A stiff position
        # motor rather than a velocity lock: the latter creeps by ~1e-4 rad/s under gravity.
        if self._world is not None:  # the drive's torque loop, then friction (docs/realism.md)
            applied = self._realism_torque(np.array(motor), np.array(before))
            motor = np.where(braked, 0.0, applied).tolist()
        if braked != self._braked:
            for i, (now_held, was_held) in enumerate(zip(braked, self._braked, strict=True)):
                if now_held and not was_held:
                    self._brake_position_rad[i] = before[i]
            self._braked = braked
        if braked != self._motor_mask:
            # pybullet keeps motor settings between steps: sent again only when a brake changes
            self._set_brake_motors(braked)
        if external_nm is None:  # the common case: one call, pybullet runs the substeps
            pybullet.setJointMotorControlArray(
                self._body, self._joint_indices, pybullet.TORQUE_CONTROL, forces=motor, physicsClientId=self._client
            )
            pybullet.stepSimulation(physicsClientId=self._client)
        else:  # an impulse touches this period: substep by substep, each with its share of it
            self._step_substeps(np.array(motor), external_nm)
        self._steps += 1
        # Counted in periods so long runs do not accumulate floating-point drift.
        self._time_s = self._steps * self.period_s
        self._applied = motor
        self._measure()
        if all_braked and external_nm is None:
            after = self._last_q
            if all(abs(a - b) < _HELD_MOTION_RAD for a, b in zip(after, before, strict=True)):  # NaN: not held
                self._held = JointState(np.array(after), np.zeros(self.n_joints), np.array(motor), 0.0)

    def _set_brake_motors(self, braked: list[bool]) -> None:
        held = self._held_indices
        pybullet.setJointMotorControlArray(
            self._body,
            self._joint_indices + held,
            pybullet.POSITION_CONTROL,
            targetPositions=self._brake_position_rad.tolist() + [0.0] * len(held),
            targetVelocities=[0.0] * (self.n_joints + len(held)),
            forces=np.where(braked, self.brake_holding_torque_nm, 0.0).tolist() + [1e3] * len(held),
            positionGains=[_BRAKE_POSITION_GAIN] * (self.n_joints + len(held)),
            velocityGains=[1.0] * (self.n_joints + len(held)),
            physicsClientId=self._client,
        )
        self._motor_mask = braked

    def _realism_torque(self, motor_nm: np.ndarray, true_q: np.ndarray) -> np.ndarray:
        """What the drive applies for ``motor_nm`` minus the profile's friction, held over the period
        (the same calls, in the same order, as ``models.sim.closed_loop``)."""
        world = self._world
        assert world is not None  # only called with a realism profile
        applied = world.actuate(motor_nm, true_q)
        if world.spec.plant.has_friction:
            qd = self.true_state().velocity_rad_s
            mass = pybullet.calculateMassMatrix(self._body, self._all_movable_positions(), physicsClientId=self._client)
            index = self._mass_matrix_index
            inertia = np.array([mass[i][i] for i in index], dtype=float)
            applied = applied - world.friction_nm(qd, inertia)
        return applied

    def _all_movable_positions(self) -> list[float]:
        states = pybullet.getJointStates(self._body, self._movable_indices, physicsClientId=self._client)
        return [float(s[0]) for s in states]

    def use_realism(self, realism: RealismSpec) -> None:
        """Apply a realism profile (once, before the first run; the arm is reset)."""
        if self._world is not None:
            raise PlantError("realism: a profile is already applied to this plant")
        if not realism.is_ideal:
            self._apply_plant_errors(realism)
            self._world = RealismModel(realism)
        self.reset()

    @property
    def realism(self) -> RealismSpec | None:
        return None if self._world is None else self._world.spec

    def _apply_plant_errors(self, realism: RealismSpec) -> None:
        """The profile's inertial errors: link masses and inertias scaled, the payload on the flange."""
        plant = realism.plant
        if any(plant.payload_com_m):
            raise PlantError(
                "realism: plant.payload_com_m: the pybullet target cannot move a link's centre of mass at run time"
            )
        if realism.n_joints != self.n_joints:
            raise PlantError(f"realism: profile bound to {realism.n_joints} joints, the arm has {self.n_joints}")
        for link, mass_scale, inertia_scale in zip(
            self._joint_indices, plant.mass_scale, plant.inertia_scale, strict=True
        ):
            if mass_scale == 1.0 and inertia_scale == 1.0:
                continue
            dyn = pybullet.getDynamicsInfo(self._body, link, physicsClientId=self._client)
            pybullet.changeDynamics(
                self._body,
                link,
                mass=float(dyn[0]) * float(mass_scale),
                localInertiaDiagonal=(np.asarray(dyn[2], dtype=float) * float(inertia_scale)).tolist(),
                physicsClientId=self._client,
            )
        if plant.payload_kg:
            self.set_payload(plant.payload_kg, plant.payload_inertia_kg_m2)

    def _advance_held(self) -> None:
        """A period of a held arm: time goes on, the joints stay where the brakes hold them."""
        assert self._held is not None
        self._steps += 1
        self._time_s = self._steps * self.period_s
        self._applied = self._held.torque_nm.tolist()
        self._set_measured(self._noisy(self._held.position_rad, self._held.velocity_rad_s))

    def probe_step_cost_s(self, steps: int = 200) -> float:
        """Median wall time of one free period (no brake, zero torque): what keeping real time
        costs. The plant is reset afterwards (initial position, time 0)."""
        free = np.zeros(self.n_joints, dtype=bool)
        zero_nm = np.zeros(self.n_joints)
        times_s = []
        for _ in range(max(1, steps)):
            started_s = time.perf_counter()
            self.step(zero_nm, free)
            times_s.append(time.perf_counter() - started_s)
        self.reset()
        return float(np.median(times_s))

    def _external_profile_nm(self) -> np.ndarray | None:
        """(substeps, N) external torque per physics substep of this period; None when no impulse
        touches it (sim_target/impulse.py)."""
        if not self._impulses:
            return None
        return external_profile_nm(self._impulses, self._time_s, self.period_s, self.substeps, self.n_joints)

    def _step_substeps(self, motor_nm: np.ndarray, external_nm: np.ndarray) -> None:
        """One period as ``substeps`` single pybullet steps (the same step size as one call with
        numSubSteps), the external torque changing between them."""
        client = self._client
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=self.period_s / self.substeps, numSubSteps=1, physicsClientId=client
        )
        try:
            for k in range(self.substeps):
                pybullet.setJointMotorControlArray(
                    self._body,
                    self._joint_indices,
                    pybullet.TORQUE_CONTROL,
                    forces=(motor_nm + external_nm[k]).tolist(),
                    physicsClientId=client,
                )
                pybullet.stepSimulation(physicsClientId=client)
        finally:
            pybullet.setPhysicsEngineParameter(
                fixedTimeStep=self.period_s, numSubSteps=self.substeps, physicsClientId=client
            )

    # --- plant faults -------------------------------------------------------------------------

    def set_encoder_noise(self, position_rad: float, velocity_rad_s: float = 0.0) -> None:
        """Gaussian measurement noise, standard deviations; 0 turns it off."""
        if position_rad < 0.0 or velocity_rad_s < 0.0:
            raise PlantError("encoder noise standard deviations must be non-negative")
        self._encoder_noise_rad = float(position_rad)
        self._velocity_noise_rad_s = float(velocity_rad_s)

    def set_payload(self, mass_kg: float, inertia_kg_m2: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        """Put a payload of ``mass_kg`` (diagonal inertia about its centre) on the flange.

        Its centre of mass is the last link's inertial origin (the flange frame for ur5_paper):
        pybullet cannot move a link's centre of mass at run time. 0 removes the payload.
        """
        inertia = np.asarray(inertia_kg_m2, dtype=float)
        if mass_kg < 0.0 or inertia.shape != (3,) or np.any(inertia < 0.0):
            raise PlantError(f"payload: need mass_kg >= 0 and 3 non-negative inertias, got {mass_kg}, {inertia}")
        self._held = None  # a new load may be more than the brakes hold
        pybullet.changeDynamics(
            self._body,
            self._payload_link,
            mass=self._payload_link_mass_kg + float(mass_kg),
            localInertiaDiagonal=(self._payload_link_inertia + inertia).tolist(),
            physicsClientId=self._client,
        )
        self._payload_kg = float(mass_kg)

    @property
    def payload_kg(self) -> float:
        return self._payload_kg

    def add_impulse(self, impulse: TorqueImpulse) -> None:
        """Schedule an external joint torque (in simulated time)."""
        self._vector(impulse.torque_nm, "impulse.torque_nm")
        if impulse.duration_s <= 0.0:
            raise PlantError(f"impulse.duration_s must be positive, got {impulse.duration_s}")
        self._impulses.append(impulse)

    def clear_impulses(self) -> None:
        self._impulses.clear()

    # --- read-outs ----------------------------------------------------------------------------

    @property
    def time_s(self) -> float:
        return self._time_s

    def true_state(self) -> JointState:
        """The noiseless state (for tests and logging; the drives report :meth:`state`)."""
        states = pybullet.getJointStates(self._body, self._joint_indices, physicsClientId=self._client)
        q = np.array([s[0] for s in states], dtype=float)
        qd = np.array([s[1] for s in states], dtype=float)
        return JointState(q, qd, np.array(self._applied), self._time_s)

    def _measure(self) -> None:
        """The state the drives report; the true positions kept (``_last_q``) for the next step.
        Without realism or noise it is the true state, kept in plain floats (JointState on demand)."""
        states = pybullet.getJointStates(self._body, self._joint_indices, physicsClientId=self._client)
        q = [s[0] for s in states]
        qd = [s[1] for s in states]
        self._last_q = q
        if self._world is None and not self._encoder_noise_rad > 0.0 and not self._velocity_noise_rad_s > 0.0:
            self._floats = (q, qd, self._applied)
            self._measured = None
            return
        self._set_measured(self._noisy(np.array(q, dtype=float), np.array(qd, dtype=float)))

    def _set_measured(self, state: JointState) -> None:
        self._measured = state
        self._floats = (state.position_rad.tolist(), state.velocity_rad_s.tolist(), state.torque_nm.tolist())

    def _noisy(self, q: np.ndarray, qd: np.ndarray) -> JointState:
        if self._world is not None:  # what the drives report (docs/realism.md)
            q, qd = self._world.sense(q, qd)
        if self._encoder_noise_rad > 0.0:
            q = q + self._rng.normal(0.0, self._encoder_noise_rad, self.n_joints)
        if self._velocity_noise_rad_s > 0.0:
            qd = qd + self._rng.normal(0.0, self._velocity_noise_rad_s, self.n_joints)
        return JointState(q, qd, np.array(self._applied), self._time_s)

    def close(self) -> None:
        if self._client is not None and pybullet.isConnected(physicsClientId=self._client):
            pybullet.disconnect(self._client)
        self._client = None

    def __enter__(self) -> PybulletPlant:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
