"""What the target's server needs from its emulated drives (:class:`sim_target.drives.EmulatedDrives`
implements it; tests stand in for it): the server's one dependency on the drives, apart from it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from sim_target.config import DriveFault, FrameFault
from sim_target.plant_protocol import JointState


class DriveBank(Protocol):
    """What the server needs from the emulated drives (sim_target/drives.py)."""

    def set_sync_handler(self, handler: Callable[[], None]) -> None:
        """Call ``handler`` on every SYNC, after latching the RPDO set-points, before the TPDOs."""

    def serve_until(self, deadline_s: float, return_on_sync: bool = False) -> None:
        """Handle the bus on the calling thread until ``time.monotonic()`` reaches ``deadline_s``
        (or, with ``return_on_sync``, until a SYNC was handled)."""

    def commanded_torque_nm(self) -> np.ndarray:
        """(N,) torque each drive is commanded to deliver now (0 when not Operation Enabled)."""

    def operation_enabled(self) -> np.ndarray:
        """(N,) bool: drive in Operation Enabled (any other joint is braked)."""

    def publish_feedback(self, state: JointState) -> None:
        """Send the TPDOs for ``state`` (the drives apply their own scaling)."""

    def apply_fault(self, fault: FrameFault | DriveFault) -> None: ...

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None:
        """Stop (or resume) one drive's heartbeat producer; its PDOs go on."""

    def safe_stop(self) -> None:
        """Every drive to a safe state (brakes on, torque off)."""

    def close(self) -> None: ...
