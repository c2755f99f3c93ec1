"""Start-up of a drive described by its own EDS/DCF (a joint with a ``drive`` section,
:mod:`drivers.drive_spec`): scaling read from the drive or given, the torque limit, the reactions,
the interpolation period, the PDOs the runtime does not use switched off, the SDO initialisation
list. Called by :func:`drivers.profiles.p402.configure` after the device type and modes were
checked, before any PDO is mapped or any drive enabled.

Anything inconsistent (a rated torque of 0, a scaling that overflows INTEGER16 per mille at the
torque limit) raises :class:`~drivers.errors.DriveConfigError` naming the file, node and object.
"""

from __future__ import annotations

import logging
import math

from drivers.cia402 import od as odx
from drivers.cia402.scaling import INT16_MAX
from drivers.config import DriveBusConfig
from drivers.drive_spec import DriveSpec, spec_scale
from drivers.eds_check import FAULT_REACTION, GEAR_RATIO, INTERPOLATION_PERIOD, WRITABLE, obj_name
from drivers.errors import DriveConfigError, SdoAbortError
from drivers.node import DriveNode
from drivers.sdo import SdoClient

log = logging.getLogger(__name__)

USED_PDO_COMMS = frozenset({odx.RPDO1_COMM, odx.TPDO1_COMM, odx.TPDO2_COMM})


def interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2 (:01 value UNSIGNED8, :02 index INTEGER8): ``value * 10**index`` s, index -3 first
    (some drives take only milliseconds)."""
    for exponent in (-3, -4, -5, -6):
        value = period_s / 10.0**exponent
        if abs(value - round(value)) < 1e-6 and 1 <= round(value) <= 255:
            return round(value), exponent
    raise DriveConfigError(f"period_s {period_s} cannot be written to 0x60C2 (1..255 x 10^-3..-6 s)")


def _ratio(sdo: SdoClient, spec: DriveSpec, node_id: int, index: int) -> float:
    numerator, denominator = sdo.read_int(node_id, index, 1), sdo.read_int(node_id, index, 2)
    if numerator <= 0 or denominator <= 0:
        raise DriveConfigError(
            f"{spec.eds}: node {node_id}: {obj_name(index, 1)}: the drive reports {numerator}/{denominator}"
        )
    return numerator / denominator


def read_scaling(sdo: SdoClient, node: DriveNode, spec: DriveSpec) -> dict[str, float]:
    """The ``"drive"`` entries of the spec, read from the drive; a drive without the object its
    EDS promised is not the drive the config describes: DriveConfigError naming the object."""
    try:
        return _read_scaling(sdo, node, spec)
    except SdoAbortError as exc:
        raise DriveConfigError(
            f"{spec.eds}: node {node.node_id}: {obj_name(exc.index, exc.subindex)}: the drive refuses it "
            f"(SDO abort 0x{exc.code:08X}): not the drive the config describes"
        ) from None


def _read_scaling(sdo: SdoClient, node: DriveNode, spec: DriveSpec) -> dict[str, float]:
    node_id, read = node.node_id, {}
    if spec.rated_torque == "drive":
        rated = sdo.read_int(node_id, odx.RATED_TORQUE)
        if rated <= 0:
            raise DriveConfigError(
                f"{spec.eds}: node {node_id}: {obj_name(odx.RATED_TORQUE)}: the drive reports a rated torque of "
                f"{rated}: commission the motor or give joints.{node.index}.drive.rated_torque"
            )
        read["rated_torque"] = float(rated)
    if spec.encoder_increments == "drive":
        read["encoder_increments"] = _ratio(sdo, spec, node_id, odx.ENCODER_RESOLUTION)
    if spec.gear_ratio == "drive":
        read["gear_ratio"] = _ratio(sdo, spec, node_id, GEAR_RATIO)
    return read


def configure_spec(sdo: SdoClient, node: DriveNode, config: DriveBusConfig) -> None:
    """Scaling into ``node``, then the drive's objects (see the module doc)."""
    spec = node.joint.drive
    assert spec is not None  # only called for joints with a drive section
    node_id, joint = node.node_id, node.joint
    scale = spec_scale(spec, read_scaling(sdo, node, spec))
    max_permille = joint.max_torque_nm / abs(scale.nm_per_permille)
    if max_permille > INT16_MAX:
        raise DriveConfigError(
            f"{spec.eds}: node {node_id}: {obj_name(odx.TARGET_TORQUE)}: max_torque_nm {joint.max_torque_nm} is "
            f"{max_permille:.0f} per mille of the drive's rated torque, above the INTEGER16 limit {INT16_MAX}"
        )
    node.permille_per_nm = scale.permille_per_nm
    node.counts_per_rad = scale.counts_per_rad
    node.zero_offset_rad = scale.zero_offset_rad
    sdo.write(node_id, odx.MODES_OF_OPERATION, 0, odx.MODE_CYCLIC_SYNC_TORQUE)
    limit = sdo.variable(node_id, odx.MAX_TORQUE, 0)
    if limit is not None and limit.access_type in WRITABLE:
        sdo.write(node_id, odx.MAX_TORQUE, 0, min(math.floor(max_permille), 0xFFFF))
    quick_stop = spec.reactions.quick_stop if spec.reactions.quick_stop is not None else config.quick_stop_option
    if sdo.variable(node_id, odx.QUICK_STOP_OPTION, 0) is not None:
        sdo.write(node_id, odx.QUICK_STOP_OPTION, 0, quick_stop)
    if spec.reactions.fault is not None:
        sdo.write(node_id, FAULT_REACTION, 0, spec.reactions.fault)
    if spec.interpolation_period and sdo.variable(node_id, INTERPOLATION_PERIOD, 2) is not None:
        value, exponent = interpolation_period(config.period_s)
        sdo.write(node_id, INTERPOLATION_PERIOD, 1, value)
        sdo.write(node_id, INTERPOLATION_PERIOD, 2, exponent)
    disable_unused_pdos(sdo, node)
    for entry in spec.sdo:
        sdo.write(node_id, entry.index, entry.sub_index, entry.value)


def disable_unused_pdos(sdo: SdoClient, node: DriveNode) -> None:
    """Every PDO of the drive's EDS the runtime does not map gets bit 31 (not valid) in its COB-ID:
    a DCF or a previous master may have left RPDO2..n / TPDO3..n running, which would add frames
    to the bus load budget and, for RPDOs, set-points the runtime does not send."""
    node_id = node.node_id
    remote = node.sdo_node
    if remote is None:
        return
    for index in sorted(remote.object_dictionary.indices):
        if not (0x1400 <= index <= 0x15FF or 0x1800 <= index <= 0x19FF) or index in USED_PDO_COMMS:
            continue
        var = sdo.variable(node_id, index, 1)
        if var is None or var.access_type not in WRITABLE:
            continue
        cob_id = sdo.read_int(node_id, index, 1)
        if not cob_id & odx.PDO_COB_ID_INVALID:
            sdo.write(node_id, index, 1, cob_id | odx.PDO_COB_ID_INVALID)
            log.info("drive %d: %s disabled (not used by the runtime)", node_id, obj_name(index, 1))
