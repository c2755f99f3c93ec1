"""SDO client: reading and writing drive objects (start-up and diagnostics, never the cycle).

canopen's SDO client does the protocol (expedited and segmented transfers, abort codes); this
module gives it a network without its own notifier (frames go out through
:class:`~drivers.network.DriveNetwork`, responses are routed back by its receiving thread), the
EDS of each drive for typed values, and the driver's error types::

    sdo = SdoClient(network, nodes, eds_path, timeout_s)
    sdo.write(3, 0x6072, 0, 1000)        # int encoded with the EDS type of 0x6072
    sdo.read_int(3, 0x608F, 1)
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.eds_check import load_dictionary
from drivers.errors import DriveCommandError, SdoAbortError, SdoTimeoutError
from drivers.network import DriveNetwork
from drivers.node import DriveNode

_ABORT_OBJECT_MISSING = 0x06020000


class _CanopenNetwork(canopen.Network):
    """A canopen Network without its own notifier: sends through the DriveNetwork."""

    def __init__(self, network: DriveNetwork) -> None:
        super().__init__(None)
        self._network = network

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._network.send(can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False))


class SdoClient:
    def __init__(
        self, network: DriveNetwork, nodes: Sequence[DriveNode], eds_path: Path | str, timeout_s: float
    ) -> None:
        self.network = network
        self._canopen = _CanopenNetwork(network)
        self._by_id: dict[int, DriveNode] = {}
        for node in nodes:
            spec = node.joint.drive
            if spec is None:
                od = odx.load_object_dictionary(node.node_id, eds_path)
            else:  # a vendor's EDS/DCF: checked against the runtime's needs by drivers.eds_check
                od = load_dictionary(spec.eds, node.node_id)
            remote = canopen.RemoteNode(node.node_id, od)
            remote.sdo.RESPONSE_TIMEOUT = timeout_s
            self._canopen.add_node(remote)
            node.sdo_node = remote
            self._by_id[node.node_id] = node
            network.subscribe(fr.SDO_TX_BASE + node.node_id, self.on_response, node)

    def on_response(self, node: DriveNode, msg: can.Message, now: float) -> None:
        if len(msg.data) != 8:
            raise fr.MalformedFrameError("SDO length")
        assert node.sdo_node is not None
        node.sdo_node.sdo.on_response(fr.SDO_TX_BASE + node.node_id, bytes(msg.data), now)

    def _remote(self, node_id: int) -> canopen.RemoteNode:
        node = self._by_id.get(node_id)
        if node is None or node.sdo_node is None:
            raise DriveCommandError(f"node {node_id} is not on this drive bus (nodes {tuple(self._by_id)})")
        return node.sdo_node

    def variable(self, node_id: int, index: int, subindex: int) -> ODVariable | None:
        """The EDS entry of an object, or None when the drive's EDS lacks it."""
        return odx.lookup_variable(self._remote(node_id).object_dictionary, index, subindex)

    def read(self, node_id: int, index: int, subindex: int = 0) -> bytes:
        remote = self._remote(node_id)
        try:
            with self.network.background_receive():
                return bytes(remote.sdo.upload(index, subindex))
        except SdoAbortedError as exc:
            raise SdoAbortError(node_id, index, subindex, exc.code) from None
        except SdoCommunicationError as exc:
            raise SdoTimeoutError(f"drive {node_id} SDO 0x{index:04X}:{subindex:02X}: {exc}") from None

    def write(self, node_id: int, index: int, subindex: int, value: int | bytes) -> None:
        remote = self._remote(node_id)
        if isinstance(value, int):
            var = self.variable(node_id, index, subindex)
            if var is None:
                raise SdoAbortError(node_id, index, subindex, _ABORT_OBJECT_MISSING)
            value = var.encode_raw(value)
        try:
            with self.network.background_receive():
                remote.sdo.download(index, subindex, value)
        except SdoAbortedError as exc:
            raise SdoAbortError(node_id, index, subindex, exc.code) from None
        except SdoCommunicationError as exc:
            raise SdoTimeoutError(f"drive {node_id} SDO 0x{index:04X}:{subindex:02X}: {exc}") from None

    def read_int(self, node_id: int, index: int, subindex: int = 0) -> int:
        data = self.read(node_id, index, subindex)
        var = self.variable(node_id, index, subindex)
        if var is None:
            return int.from_bytes(data, "little")
        return int(var.decode_raw(data))
