"""PDOs: their mapping at start-up (by SDO) and the cyclic exchange (RPDOs + SYNC out, TPDOs in).

Mapping follows the CiA 301 order for each PDO (invalidate, clear the count, write the entries,
set the count, transmission type, validate) with one of the fixed layouts of
:mod:`drivers.cia402.od`: classical (RPDO1; TPDO1 + TPDO2) or CAN FD (RPDO1; one tagged TPDO1
echoing the SYNC counter). The RPDO's event timer (0x1400:05) is the drive's RPDO timeout: a
drive whose RPDOs stop for that long quick-stops (0x6007).

:class:`CyclicExchange` is one control cycle, on the caller's thread, holding the network's
receive lock: drain what is already queued (a TPDO among it answers an older SYNC: late, never
used), pack every RPDO in place, send them and the SYNC as one batch, then block in ``recv``
until every TPDO of this cycle is in or ``feedback_timeout_s`` has passed since the SYNC. With
CAN FD a TPDO echoing an older SYNC counter is late whenever it arrives; with classical CAN (no
room for the echo in 8 bytes) only the drain applies. Frames are encoded and decoded with the
codec of :mod:`drivers.cia402.frames`.

On a bus with the raw path (:attr:`drivers.network.DriveNetwork.raw`, the ipc bus) the RPDOs and
the SYNC are one :class:`~drivers.ipc.frame.FrameBatch` built at the first cycle: each cycle packs
the controlwords, torques and the SYNC counter into its payloads (one encode per frame, nothing
allocated) and sends it as it is; the TPDOs come back as undecoded datagrams and their handlers
read the bytes (no ``can.Message`` per frame). Other buses send the reused messages.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.state_machine import State, decode_statusword_fast
from drivers.feedback import DriveFeedback
from drivers.ipc.frame import MAX_BATCH_FRAMES, FrameBatch
from drivers.network import DriveNetwork
from drivers.node import DriveNode
from drivers.sdo import SdoClient
from drivers.sync import SyncProducer

_EVENT_TIMER_SUBINDEX = 5  # RPDO communication parameter: event timer = RPDO timeout (ms)


def map_pdo(sdo: SdoClient, node_id: int, comm: int, mapping: int, cob_id: int, entries: tuple[int, ...]) -> None:
    # CiA 301 order: invalidate the PDO, clear the count, write entries, set the count, validate.
    sdo.write(node_id, comm, 1, cob_id | odx.PDO_COB_ID_INVALID)
    if not entries:
        return  # stays disabled (TPDO2 with CAN FD)
    sdo.write(node_id, mapping, 0, 0)
    for k, entry in enumerate(entries, start=1):
        sdo.write(node_id, mapping, k, entry)
    sdo.write(node_id, mapping, 0, len(entries))
    sdo.write(node_id, comm, 2, odx.TRANSMISSION_SYNC_EVERY)
    sdo.write(node_id, comm, 1, cob_id)


def map_layout(sdo: SdoClient, node: DriveNode, layout: odx.PdoLayout) -> None:
    node_id = node.node_id
    map_pdo(sdo, node_id, odx.RPDO1_COMM, odx.RPDO1_MAP, fr.RPDO1_BASE + node_id, layout.rpdo1)
    map_pdo(sdo, node_id, odx.TPDO1_COMM, odx.TPDO1_MAP, fr.TPDO1_BASE + node_id, layout.tpdo1)
    map_pdo(sdo, node_id, odx.TPDO2_COMM, odx.TPDO2_MAP, fr.TPDO2_BASE + node_id, layout.tpdo2)


def set_rpdo_timeout(sdo: SdoClient, node_id: int, timeout_ms: int) -> bool:
    """The RPDO1 event timer (deadline monitoring, CiA 301 7.5.2.35); False when the drive's
    EDS has no such entry (the drive then relies on its heartbeat consumer alone)."""
    if sdo.variable(node_id, odx.RPDO1_COMM, _EVENT_TIMER_SUBINDEX) is None:
        return False
    sdo.write(node_id, odx.RPDO1_COMM, _EVENT_TIMER_SUBINDEX, timeout_ms)
    return True


class CyclicExchange:
    """The control cycle. Not thread-safe: the caller's thread only."""

    def __init__(
        self, network: DriveNetwork, nodes: Sequence[DriveNode], sync: SyncProducer, feedback_timeout_s: float, fd: bool
    ) -> None:
        self.network = network
        self.nodes = tuple(nodes)
        self.sync = sync
        self.feedback_timeout_s = feedback_timeout_s
        self.fd = fd
        self.layout = odx.FD_SYNC_LAYOUT if fd else odx.CLASSICAL_LAYOUT  # the emulated drive's
        self.tpdos_per_drive = 1 if fd else 2
        self.cycle = 0
        self.late = 0  # TPDOs after their deadline, of an older SYNC, or twice in one cycle
        self.dropped = 0  # TPDOs expected and not in by the deadline
        self._open = False
        self._pending = 0
        self.sync_time_s = 0.0  # the open (or last) cycle's SYNC, time.monotonic()
        self._commanded_nm = np.zeros(len(nodes))
        self._frames = [*(node.rpdo for node in self.nodes), sync.msg]
        self._batch: FrameBatch | None = None  # the raw path's cycle datagram, built at the first cycle
        self._batch_dlc = -1  # the SYNC length it was built with (carry_counter may change it)
        self._rpdo_payloads: tuple[memoryview, ...] = ()  # the batch's RPDO payloads, in node order
        self._counts_per_rad = np.ones(len(self.nodes))
        self._permille_per_nm = np.array([node.permille_per_nm for node in self.nodes])
        self._zero_offset_rad: np.ndarray | None = None
        for node in self.nodes:
            if fd and not node.fd_sync_echo:
                network.subscribe_data(fr.TPDO1_BASE + node.node_id, self.on_tpdo_fd_plain, node)
            elif fd:
                network.subscribe_data(fr.TPDO1_BASE + node.node_id, self.on_tpdo_fd, node)
            else:
                network.subscribe_data(fr.TPDO1_BASE + node.node_id, self.on_tpdo1, node)
                network.subscribe_data(fr.TPDO2_BASE + node.node_id, self.on_tpdo2, node)

    def layout_for(self, node: DriveNode) -> odx.PdoLayout:
        """The emulated drive's layout, or with CAN FD the untagged one for a vendor's drive."""
        return self.layout if not self.fd or node.fd_sync_echo else odx.FD_LAYOUT

    def refresh_scaling(self) -> None:
        """After start-up: each drive's scaling as read from it (encoder, rated torque, offset)."""
        self._counts_per_rad = np.array([node.counts_per_rad for node in self.nodes])
        self._permille_per_nm = np.array([node.permille_per_nm for node in self.nodes])
        offsets = np.array([node.zero_offset_rad for node in self.nodes])
        self._zero_offset_rad = offsets if offsets.any() else None

    # --- one cycle -------------------------------------------------------------------------------

    def run(self, controlwords: Sequence[int], permille: Sequence[int], commanded_nm: np.ndarray) -> DriveFeedback:
        """One blocking cycle: the set-points and the SYNC out, then this SYNC's TPDOs (until every
        one is in or ``feedback_timeout_s`` has passed since the SYNC)."""
        self.begin(controlwords, permille, commanded_nm)
        return self.finish(self.sync_time_s + self.feedback_timeout_s)

    def begin(self, controlwords: Sequence[int], permille: Sequence[int], commanded_nm: np.ndarray) -> None:
        """The first half of a cycle: drain what is queued (late), pack and send the RPDOs and the
        SYNC; the cycle stays open for this SYNC's TPDOs until :meth:`finish` (the overlapped
        cycle: the caller computes meanwhile, docs/runtime.md)."""
        network = self.network
        nodes = self.nodes
        with network.rx_lock:
            network.drain()  # queued before this SYNC: an older cycle's TPDOs are late, not fresh
            raw = network.raw
            encode = fr.encode_rpdo_into
            if raw:
                batch = self._cycle_batch()
                for payload, controlword, torque in zip(self._rpdo_payloads, controlwords, permille, strict=True):
                    encode(payload, controlword, torque)
            else:
                for node, controlword, torque in zip(nodes, controlwords, permille, strict=True):
                    encode(node.rpdo.data, controlword, torque)
            self.cycle += 1
            counter = self.sync.advance()
            if raw and self._batch_dlc:
                batch.payloads[-1][0] = counter  # the SYNC's counter byte, in place
            self._pending = len(nodes) * self.tpdos_per_drive
            self._open = True
            self._commanded_nm = commanded_nm
            self.sync_time_s = time.monotonic()
            try:
                if raw:
                    network.send_frames(batch)
                else:
                    network.send_batch(self._frames)
            except BaseException:
                self._open = False
                raise
            network.last_cycle_end_s = self.sync_time_s  # the background thread stays out meanwhile

    def finish(self, deadline: float) -> DriveFeedback:
        """The second half: this SYNC's TPDOs until every one is in or ``deadline`` (monotonic)
        passes; the cycle closes, a TPDO after it is late. The cycle's feedback."""
        network = self.network
        nodes = self.nodes
        cycle = self.cycle
        sync_time = self.sync_time_s
        commanded_nm = self._commanded_nm
        monotonic = time.monotonic
        with network.rx_lock:
            try:
                self._receive(deadline)
            finally:
                self._open = False
            now = monotonic()
            # Freshness and miss counts; the values are read from the records below.
            fd = self.fd
            if fd:
                fresh = [node.tpdo1_cycle == cycle for node in nodes]
                missing = fresh.count(False)
            else:
                fresh = [node.tpdo1_cycle == cycle and node.tpdo2_cycle == cycle for node in nodes]
                missing = sum((node.tpdo1_cycle != cycle) + (node.tpdo2_cycle != cycle) for node in nodes)
            for node, is_fresh in zip(nodes, fresh, strict=True):
                if is_fresh:
                    node.state = decode_statusword_fast(node.statusword)
            position = [node.position_counts for node in nodes]
            velocity = [node.velocity_counts_s for node in nodes]
            torque_pm = [node.torque_permille for node in nodes]
            rx_time = [node.rx_time_s for node in nodes]
            states = [node.state for node in nodes]
            self.dropped += missing
            supervise = network.supervise
            if supervise is not None:
                supervise(now)
        counts_per_rad = self._counts_per_rad
        position_rad = np.array(position, dtype=np.float64) / counts_per_rad
        if self._zero_offset_rad is not None:
            position_rad -= self._zero_offset_rad
        feedback = DriveFeedback(
            cycle=cycle,
            sync_time_s=sync_time,
            position_rad=position_rad,
            velocity_rad_s=np.array(velocity, dtype=np.float64) / counts_per_rad,
            torque_nm=np.array(torque_pm, dtype=np.float64) / self._permille_per_nm,
            commanded_torque_nm=np.array(commanded_nm, dtype=np.float64),
            fresh=np.array(fresh, dtype=bool),
            rx_time_s=np.array(rx_time, dtype=np.float64),
            states=tuple(states),
        )
        produce = network.produce
        if produce is not None:
            produce(now)  # the master's heartbeat, when due, right after the cycle
        network.last_cycle_end_s = now
        return feedback

    def _cycle_batch(self) -> FrameBatch:
        """The RPDOs and the SYNC as one preallocated datagram (the raw path), built once."""
        dlc = self.sync.msg.dlc
        if self._batch is None or dlc != self._batch_dlc:
            if len(self.nodes) + 1 > MAX_BATCH_FRAMES:
                raise ValueError(f"{len(self.nodes)} drives: more RPDOs than one datagram holds")
            self._batch = FrameBatch(self._frames)
            self._batch_dlc = dlc
            self._rpdo_payloads = tuple(self._batch.payloads[: len(self.nodes)])
        return self._batch

    def _receive(self, deadline: float) -> None:
        """Every TPDO of the open cycle, or until ``deadline`` (monotonic)."""
        receive_one = self.network.receive_one
        monotonic = time.monotonic
        while self._pending > 0:
            remaining = deadline - monotonic()
            if remaining <= 0 or not receive_one(remaining):
                break

    # --- TPDO handlers (under the receive lock) --------------------------------------------------

    def _accept_tpdo1(self, node: DriveNode) -> bool:
        """May this TPDO count for the open cycle?"""
        if not self._open or node.tpdo1_cycle == self.cycle:
            self.late += 1
            return False
        node.tpdo1_cycle = self.cycle
        self._pending -= 1
        return True

    def _store_tpdo1(
        self, node: DriveNode, statusword: int, torque: int, position: int, velocity: int | None, now: float
    ) -> None:
        """A TPDO1's values into the drive's record, when it counts for the open cycle. ``velocity``:
        the CAN FD layouts carry it (0 when a layout leaves it out); None on classical CAN (TPDO2's)."""
        if decode_statusword_fast(statusword) is State.UNKNOWN:
            raise fr.MalformedFrameError("statusword")
        if self._accept_tpdo1(node):
            node.statusword = statusword
            node.torque_permille = torque
            node.position_counts = position
            if velocity is not None:
                node.velocity_counts_s = velocity
            node.rx_time_s = now

    def on_tpdo1(self, node: DriveNode, data: bytes, now: float) -> None:
        statusword, torque, position, _ = fr.decode_tpdo1(data)
        self._store_tpdo1(node, statusword, torque, position, None, now)

    def on_tpdo2(self, node: DriveNode, data: bytes, now: float) -> None:
        velocity = fr.decode_tpdo2(data)
        if not self._open or node.tpdo2_cycle == self.cycle:
            self.late += 1
            return
        node.tpdo2_cycle = self.cycle
        self._pending -= 1
        node.velocity_counts_s = velocity
        node.rx_time_s = now

    def on_tpdo_fd_plain(self, node: DriveNode, data: bytes, now: float) -> None:
        """A vendor's drive on CAN FD: the 12-byte TPDO without the SYNC counter echo (stale
        feedback is recognised by the drain only, as with classical CAN)."""
        statusword, torque, position, velocity = fr.decode_tpdo_fd(data)
        self._store_tpdo1(node, statusword, torque, position, velocity if velocity is not None else 0, now)

    def on_tpdo_fd(self, node: DriveNode, data: bytes, now: float) -> None:
        statusword, torque, position, velocity, counter = fr.unpack_tpdo_fd_sync(data)
        if counter != self.sync.counter:  # answers an older SYNC: stale whenever it arrives
            if decode_statusword_fast(statusword) is State.UNKNOWN:
                raise fr.MalformedFrameError("statusword")
            self.late += 1
            return
        self._store_tpdo1(node, statusword, torque, position, velocity, now)
