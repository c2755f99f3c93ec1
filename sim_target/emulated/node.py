"""The emulated drive's record, the bank's configuration and counters, fault injection settings."""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen

from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import State
from sim_target.emulated.profile import DriveProfile


@dataclass(frozen=True)
class FrameFaults:
    """Random faults on the frames a drive sends (probabilities per frame, seeded)."""

    drop_probability: float = 0.0
    delay_s: float = 0.0  # every frame held this long
    corrupt_probability: float = 0.0  # sent one byte short
    seed: int = 0
    # Any fault to apply: read for every drive every SYNC, so a field computed once, not a property.
    active: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        active = self.drop_probability > 0 or self.delay_s > 0 or self.corrupt_probability > 0
        object.__setattr__(self, "active", active)  # frozen: set once, here


@dataclass(frozen=True)
class EmulatedDrivesConfig:
    node_ids: tuple[int, ...]  # one per joint, joint order
    encoder_counts_per_rev: int = 1 << 20  # 0x608F:01 (joint side, 1 revolution)
    heartbeat_producer_ms: int = 0  # 0x1017 until the master writes it
    eds_path: Path | None = None
    frame_faults: FrameFaults = FrameFaults()  # applied to every drive from the start
    profiles: tuple[DriveProfile, ...] | None = None  # one per drive: a vendor's dictionary and motor

    def __post_init__(self) -> None:
        if not self.node_ids or len(set(self.node_ids)) != len(self.node_ids):
            raise ValueError(f"node_ids must be distinct and non-empty, got {self.node_ids}")
        for node_id in self.node_ids:
            fr.check_node_id(node_id)
        if self.encoder_counts_per_rev <= 0:
            raise ValueError("encoder_counts_per_rev must be positive")
        if self.profiles is not None and len(self.profiles) != len(self.node_ids):
            raise ValueError(f"{len(self.profiles)} drive profiles for {len(self.node_ids)} drives")


@dataclass(frozen=True)
class DriveCounters:
    frames_received: int
    frames_sent: int
    malformed: int
    unknown_cob_id: int
    syncs: int
    dropped_injected: int
    delayed_injected: int
    corrupted_injected: int
    master_lost: int = 0  # loss-of-master events that made a drive react (0x6007)


@dataclass
class FaultPolicy:
    """One drive's injected frame faults: random (``faults``) and one-shot (``*_next``)."""

    faults: FrameFaults
    rng: random.Random
    drop_next: int = 0  # one-shot: drop this many TPDO cycles
    corrupt_next: int = 0
    delay_next: int = 0
    delay_next_s: float = 0.0
    silent_heartbeat: bool = False

    @property
    def clean(self) -> bool:
        """No fault to apply to the next TPDOs: the drive may take its fast path."""
        return not (self.faults.active or self.drop_next or self.corrupt_next or self.delay_next)


@dataclass(frozen=True)
class MasterLoss:
    """A drive's reaction to losing its master, for tests and the target's status."""

    node_id: int
    cause: str  # "heartbeat", "rpdo" or "sync"
    silent_s: float  # how long the master had been silent when the drive reacted
    reaction: str  # "quick stop", "fault", "disable voltage" or "none" (0x6007)
    time_s: float  # time.monotonic() of the reaction


@dataclass(eq=False)
class EmulatedDrive:
    """Everything one emulated drive is: identity, NMT and CiA 402 state, cached objects."""

    index: int
    node_id: int
    node: canopen.LocalNode
    counts_per_rad: float
    policy: FaultPolicy
    nmt: fr.NmtState = fr.NmtState.BOOT_UP
    state: State = State.SWITCH_ON_DISABLED
    controlword: int = 0
    previous_controlword: int = 0
    target_permille: int = 0
    applied_permille: int = 0
    limited: bool = False
    # cached from the object dictionary (refreshed on SDO write and on reset)
    rated_torque_mnm: int = 1000  # 0x6076 as the drive holds it (in its own unit with a profile)
    # Joint N·m per (per mille x one unit of 0x6076): 1e-6 for 0x6076 in mN·m, no gear; a profile's own.
    torque_unit_nm: float = 1e-6
    units_per_nm: float = 1e6  # 1 / torque_unit_nm, kept exact for the default drive (bit-identical frames)
    profile: DriveProfile | None = None  # a vendor's dictionary and motor (sim_target/emulated/profile.py)
    max_torque_permille: int = 1000
    quick_stop_option: int = 2
    heartbeat_ms: int = 0
    next_heartbeat_s: float = math.inf
    rpdo_valid: bool = True
    tpdo1_valid: bool = True
    tpdo2_valid: bool = True
    fd_layout: bool = False  # one FD TPDO (12 bytes, or 16 with the SYNC counter echo)
    fd_sync_echo: bool = False  # the FD TPDO maps 0x2100: it echoes the answered SYNC's counter
    tpdo_msgs: dict[int, can.Message] = field(default_factory=dict)  # reused: send() copies
    error_code: int = 0
    error_register: int = 0
    pending_fault: int | None = None
    mappings: dict[int, list[int]] = field(default_factory=dict)
    # Loss of the master (all 0: not watched). Times are time.monotonic() of the last frame seen.
    master_node_id: int = 0  # 0x1016:01 bits 16..22
    master_heartbeat_timeout_ms: int = 0  # 0x1016:01 bits 0..15
    rpdo_timeout_ms: int = 0  # 0x1400:05 event timer
    sync_timeout_ms: int = 0  # 0x2101
    abort_connection_option: int = 1  # 0x6007
    last_master_heartbeat_s: float = 0.0  # 0: none yet (monitoring starts at the first)
    last_rpdo_s: float = 0.0
    last_sync_s: float = 0.0
