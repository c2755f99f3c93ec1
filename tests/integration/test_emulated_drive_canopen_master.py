"""An independent CANopen master (the canopen library's RemoteNode with the EDS) reads and writes
the emulated drives' objects by SDO and drives their NMT state: the drives are real CANopen
nodes, not something only our own driver understands."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import can
import canopen
import pytest

from drivers.cia402.frames import NmtState
from drivers.cia402.od import EDS_PATH
from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
from sim_target.testing.drive_rig import wait_until


@pytest.fixture
def master() -> Iterator[tuple[canopen.Network, EmulatedDrives]]:
    channel = f"co-{uuid.uuid4().hex[:10]}"
    side = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    drives = EmulatedDrives(side, EmulatedDrivesConfig(node_ids=(3, 4), encoder_counts_per_rev=4096))
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05  # the notifier polls this often: a fast teardown
    network.connect(interface="virtual", channel=channel)
    drives.start()
    yield network, drives
    network.disconnect()
    drives.close()
    side.shutdown()


def test_sdo_read_write_through_the_eds(master: tuple[canopen.Network, EmulatedDrives]) -> None:
    network, _ = master
    node = network.add_node(3, str(EDS_PATH))
    assert node.sdo["Device type"].raw == 0x00020192
    assert node.sdo["Manufacturer device name"].raw == "HIL CST drive"
    assert node.sdo[0x608F][1].raw == 4096
    assert node.sdo["Modes of operation display"].raw == 10
    node.sdo["Motor rated torque"].raw = 2500
    assert node.sdo["Motor rated torque"].raw == 2500
    assert node.sdo["Statusword"].raw & 0x4F == 0x40  # switch on disabled
    with pytest.raises(canopen.SdoAbortedError) as info:
        node.sdo["Statusword"].raw = 0
    assert info.value.code == 0x06010002
    with pytest.raises(canopen.SdoAbortedError) as info:
        node.sdo["Modes of operation"].raw = 1
    assert info.value.code == 0x06090030
    node.tpdo.read()  # the mapping objects decode into the EDS's own objects
    assert [var.name for var in node.tpdo[1].map] == ["Statusword", "Torque actual value", "Position actual value"]
    node.rpdo.read()
    assert [var.name for var in node.rpdo[1].map] == ["Controlword", "Target torque"]


def test_nmt_and_heartbeat(master: tuple[canopen.Network, EmulatedDrives]) -> None:
    network, drives = master
    node = network.add_node(4, str(EDS_PATH))
    node.sdo["Producer heartbeat time"].raw = 10
    assert node.nmt.wait_for_heartbeat(timeout=2) == "PRE-OPERATIONAL"
    node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: drives.nmt_states() == (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL))
    assert node.nmt.wait_for_heartbeat(timeout=2) == "OPERATIONAL"
    node.nmt.state = "STOPPED"
    assert node.nmt.wait_for_heartbeat(timeout=2) == "STOPPED"
    node.nmt.state = "RESET COMMUNICATION"
    node.nmt.wait_for_bootup(timeout=2)
    # A communication reset restores 0x1017 from the EDS (0: no heartbeat) but keeps 0x6076.
    assert node.sdo["Producer heartbeat time"].raw == 0
    assert drives.nmt_states()[1] is NmtState.PRE_OPERATIONAL


def test_only_the_shared_pdo_layouts_can_be_mapped(master: tuple[canopen.Network, EmulatedDrives]) -> None:
    network, _ = master
    node = network.add_node(3, str(EDS_PATH))
    with pytest.raises(canopen.SdoAbortedError) as info:
        node.sdo[0x1A00][0].raw = 0  # TPDO1 still valid: its mapping is locked
    assert info.value.code == 0x08000022
    node.sdo[0x1800][1].raw = 0x80000183  # invalidate TPDO1 (CiA 301 order)
    node.sdo[0x1A00][0].raw = 0
    with pytest.raises(canopen.SdoAbortedError) as info:
        node.sdo[0x1A00][1].raw = 0x606C0020  # velocity first: not a layout the driver decodes
    assert info.value.code == 0x06040041
    for sub, entry in enumerate((0x60410010, 0x60770010, 0x60640020, 0x606C0020), start=1):
        node.sdo[0x1A00][sub].raw = entry
    node.sdo[0x1A00][0].raw = 4  # the CAN FD layout: one 12-byte TPDO
    node.sdo[0x1800][1].raw = 0x183
    node.tpdo.read()
    assert node.tpdo[1].length == 96
