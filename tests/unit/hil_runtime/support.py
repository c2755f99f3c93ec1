"""Shared by the runtime's unit tests (``from tests.unit.hil_runtime.support import ...``): a runtime
config for the shipped PD bundle, and a stand-in bundle whose outputs a test sets (NaN policy output,
trust fallbacks) without onnxruntime."""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers.testing import FakeJointBus, PlantStep
from hil_runtime.bundle import PolicyBundle
from hil_runtime.bundle_schema import Emulator, Graph, GraphLayout, InitialState, Law, Limits, Manifest, Port, Robot
from hil_runtime.config import RuntimeConfig, parse_runtime_config
from sim_target.testing.ur5 import JOINT_NAMES, MAX_TORQUE_NM, PD_BUNDLE, Q0_RAD, bus_joints

ROOT = Path(__file__).resolve().parents[3]


# Clock-paced tests of other things (stop requests, telemetry, the time base) on the wall clock of a
# shared machine: a stall of a few tens of ms would end them in FAULT overrun_budget (the budget's
# own tests: test_overruns.py), so they set it past any stall.
NO_OVERRUN_BUDGET = {"overrun_budget": 100_000}
INERTIA = (2.0, 2.0, 1.0, 0.2, 0.2, 0.1)  # the fake bus's joint inertias (kg m^2)


def config_dict(**overrides: Any) -> dict[str, Any]:
    """A valid runtime config (virtual transport, the PD bundle, hold); sections merged shallowly."""
    data: dict[str, Any] = {
        "robot": "ur5_paper",
        "bundle": {"path": str(PD_BUNDLE), "mode": "lmpc"},
        "bus": {
            "transport": {"interface": "virtual", "channel": "unit", "fd": True, "data_bitrate": 5_000_000},
            "period_s": 0.001,
            "joints": bus_joints(),
        },
        "reference": {"kind": "hold"},
        "loop": {"pacing": "bus", "warmup_cycles": 5},
    }
    data = copy.deepcopy(data)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return data


class StubBundle(PolicyBundle):
    """A PolicyBundle without a graph or onnxruntime for the loop: tau = ``tau_value`` (or a PD law
    when None). Its own ``__init__`` on purpose (no files to load); ``step`` keeps the base's
    signature, so a change there shows here. ``before_step``, when set, runs first in every step (a
    test makes the policy raise or stall with it)."""

    def __init__(
        self, n: int = 6, period_s: float = 0.001, state_size: int = 0, applied: list[int] | None = None
    ) -> None:
        self.n_joints, self.period_s, self.state_size = n, period_s, state_size
        self.law_name = "stub"
        self.joint_names = JOINT_NAMES[:n]
        self.torque_limit_nm = np.array(MAX_TORQUE_NM[:n])
        # The typed manifest the runtime reads, built without the fields a stub has no use for.
        self.manifest = Manifest.model_construct(
            robot=Robot.model_construct(
                name="ur5_paper", n_joints=n, joint_names=list(self.joint_names), urdf_sha256="0" * 64, urdf_file=""
            ),
            limits=Limits(position_rad=[3.0] * n, velocity_rad_s=[2.5] * n, torque_nm=list(self.torque_limit_nm)),
            law=Law.model_construct(
                name="stub",
                params={},
                state_size=state_size,
                applied_torque_slice=None if applied is None else (applied[0], applied[1]),
                initial_state=InitialState(constant=[0.0] * state_size, position_gain=[[0.0] * n] * state_size),
            ),
            schema_id="hil-policy-bundle/3",
            period_s=period_s,
            graph=Graph(
                file="none",
                opset=17,
                dtype="float64",
                input=Port(name="x", layout=[]),
                output=Port(name="y", layout=[]),
            ),
            emulator=Emulator(feature_set="eq22", residual=True),
            trust_region=None,
            files={},
            training={},
            validation={},
            created="",
        )
        self.layout = GraphLayout(n, state_size)
        self.takes_previous_torque, self.previous_torque_nm = False, None  # the graph reads no tau_prev
        self._out = np.zeros(self.layout.output_width)
        self.tau_value: np.ndarray | None = None
        self.tau_fb_value: np.ndarray | None = None
        self.trust_value = 0.0
        self.next_state_value: float | None = None  # when set, every entry of the law's next state
        self.states_seen: list[np.ndarray] = []
        self.calls = 0
        self.before_step: Callable[[], None] | None = None

    @property
    def last_trust(self) -> np.ndarray:
        return self.layout.split(self._out)[3]

    def initial_state(self, q0: np.ndarray) -> np.ndarray:
        return np.zeros(self.state_size)

    def step(
        self, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray, law_state: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.before_step is not None:
            self.before_step()
        state = law_state
        self.calls += 1
        self.states_seen.append(np.array(state))
        law = 50.0 * (q_d - q) + 5.0 * (qd_d - qd)
        tau, tau_fb, next_state, trust = self.layout.split(self._out)
        tau_fb[:] = law if self.tau_fb_value is None else self.tau_fb_value
        tau[:] = (
            np.clip(tau_fb, -self.torque_limit_nm, self.torque_limit_nm) if self.tau_value is None else self.tau_value
        )
        next_state[:] = state + 1.0 if self.next_state_value is None else self.next_state_value
        trust[0] = self.trust_value
        return tau, tau_fb, next_state

    def describe(self) -> dict[str, Any]:
        return {"law": "stub"}


def model_plant(period_s: float = 0.001) -> PlantStep:
    """ur5_paper's rigid-body dynamics (pinocchio ABA, RK4, two substeps a period, no mismatch): the plant the shipped
    bundles were made for. The fake bus's default double integrator has no gravity and no coupling,
    which a model-based policy (the LMPC's feed-forward) is not meant to survive; the loop's tests
    run the policy on its own model so that a fault there is the loop's, not the plant's."""
    from models.conditions import Mismatch
    from models.robots import load_robot
    from models.sim.closed_loop import ModelPlant, SimConfig

    plant = ModelPlant(load_robot("ur5_paper"), Mismatch(), SimConfig(period_s=period_s, substeps=2))
    return plant.integrate


def c1_on_model(
    torque_rate_limit: str, ramp_s: float, bundle: dict[str, str] | None = None
) -> tuple[RuntimeConfig, FakeJointBus]:
    """A runtime config tracking C1 (a ramp of ``ramp_s``) with ``bundle.torque_rate_limit`` (and the other
    ``bundle`` fields given), and a fake bus on the PD bundle's own model (:func:`model_plant`) that keeps
    no commands."""
    config = parse_runtime_config(
        config_dict(
            bundle={"torque_rate_limit": torque_rate_limit, **(bundle or {})},
            reference={"kind": "condition", "condition": "C1", "ramp_s": ramp_s},
        ),
        "rt.yaml",
    )
    bus = FakeJointBus(
        6,
        period_s=0.001,
        inertia_kgm2=INERTIA,
        max_torque_nm=MAX_TORQUE_NM,
        initial_position_rad=Q0_RAD,
        keep_commands=False,
        plant=model_plant(),
    )
    return config, bus
