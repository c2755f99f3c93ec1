"""Typed errors of the drive layer.

Everything a caller may need to tell apart is its own class, carrying the protocol's own code
(EMCY error code, SDO abort code) where there is one. User-facing errors carry an integer
``exit_code`` (see ``hil_runtime/cli.py``): 2 for bad input, 3 for a fault met at run time.

    DriveError
    ├── DriveConfigError (ValueError)       bad config / EDS / bus-load budget      exit 2
    │   └── BusLoadError
    ├── TransportError                       the python-can bus failed               exit 3
    ├── DriveCommandError (ValueError)       bad set-point (NaN, wrong shape)         exit 2
    ├── DriveFaultError(node_id, code)       a drive reported a fault (EMCY/Fault)   exit 3
    ├── DriveStateError                      state machine did not reach the target  exit 3
    ├── FeedbackTimeoutError (TimeoutError)  TPDOs missing past the budget           exit 3
    ├── HeartbeatLostError (TimeoutError)    a drive's heartbeat stopped             exit 3
    └── SdoError                                                                       exit 3
        ├── SdoAbortError(code)              the drive (or we) aborted an SDO transfer
        └── SdoTimeoutError (TimeoutError)   no SDO response
"""

from __future__ import annotations

from drivers.cia402.sdo import abort_code_text


class DriveError(Exception):
    """Base of every error raised by the drive layer.

    ``fault_kind``: the runtime's FAULT reason for it (``hil_runtime.supervisor.FaultKind`` value);
    ``internal`` for errors that are not expected while the drives run.
    """

    exit_code: int = 3
    fault_kind: str = "internal"


class DriveConfigError(DriveError, ValueError):
    """Bad drive-bus configuration, EDS or mapping: one line naming the file and the field."""

    exit_code = 2


class BusLoadError(DriveConfigError):
    """The configured drives, rate and bitrate exceed the bus-load budget."""


class TransportError(DriveError):
    """The CAN transport could not be opened or failed while running."""

    fault_kind = "transport"


class DriveCommandError(DriveError, ValueError):
    """A set-point the driver refuses to put on the bus (NaN, wrong shape)."""

    exit_code = 2
    fault_kind = "command"


class DriveFaultError(DriveError):
    """A drive reported a fault: ``code`` is the CiA 301 EMCY error code (0 if none was received)."""

    fault_kind = "drive_fault"

    def __init__(self, node_id: int, code: int, detail: str = "") -> None:
        self.node_id = node_id
        self.code = code
        text = f"drive {node_id} fault, EMCY code 0x{code:04X}"
        super().__init__(f"{text}: {detail}" if detail else text)


class DriveStateError(DriveError):
    """A drive did not reach the requested CiA 402 or NMT state in time."""

    fault_kind = "drive_state"


class FeedbackTimeoutError(DriveError, TimeoutError):
    """TPDOs of one or more drives were missing for more cycles than allowed."""

    fault_kind = "feedback_timeout"

    def __init__(self, node_ids: tuple[int, ...], missed_cycles: int) -> None:
        self.node_ids = node_ids
        self.missed_cycles = missed_cycles
        super().__init__(
            f"no feedback from drive(s) {', '.join(map(str, node_ids))} for {missed_cycles} consecutive cycle(s)"
        )


class HeartbeatLostError(DriveError, TimeoutError):
    """A drive's heartbeat stopped, or it reported an NMT state it must not be in."""

    fault_kind = "heartbeat_lost"

    def __init__(self, node_id: int, detail: str) -> None:
        self.node_id = node_id
        super().__init__(f"drive {node_id}: {detail}")


class SdoError(DriveError):
    """An SDO transfer failed."""


class SdoAbortError(SdoError):
    """An SDO transfer was aborted; ``code`` is the CiA 301 abort code."""

    def __init__(self, node_id: int, index: int, subindex: int, code: int) -> None:
        self.node_id = node_id
        self.index = index
        self.subindex = subindex
        self.code = code
        super().__init__(
            f"drive {node_id} aborted SDO 0x{index:04X}:{subindex:02X} with 0x{code:08X} ({abort_code_text(code)})"
        )


class SdoTimeoutError(SdoError, TimeoutError):
    """No SDO response within the configured time."""


# The run-time errors of a running bus: :meth:`drivers.joint_bus.JointBusBase.exchange` quick-stops
# the drives before raising any of them, and leaves the bus disabled. The one list of them (the
# runtime maps each to its FAULT by ``fault_kind``). A DriveCommandError is not here: nothing was sent.
FATAL_ERRORS: tuple[type[DriveError], ...] = (
    FeedbackTimeoutError,
    HeartbeatLostError,
    DriveFaultError,
    DriveStateError,
    TransportError,
)
