"""Bus-load budget: how much of the bus one control cycle of N drives takes.

Per cycle the master sends one SYNC and one RPDO per drive, and every drive answers with its
TPDO(s): classical CAN needs two TPDOs (8 + 4 bytes), CAN FD carries all 12 bytes and the SYNC
counter echo in one 16-byte frame. Heartbeats add N one-byte frames per heartbeat period (and the
master's own, one frame per its period). Frame lengths are worst case: every stuffable bit
sequence stuffed (one stuff bit per four bits), 11-bit identifiers, 3-bit
interframe space.

Classical base frame with n data bytes (Davis et al., 2007):
    47 + 8n + floor((34 + 8n - 1) / 4) bits.
CAN FD base frame (ISO 11898-1:2015) with bit-rate switch: the arbitration phase and the frame
end (SOF..BRS, CRC delimiter, ACK, EOF, IFS) run at the nominal rate, the data phase (ESI, DLC,
data, stuff count, CRC with its fixed stuff bits) at the data rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from drivers.errors import BusLoadError

DEFAULT_LIMIT: Final = 0.85
FD_LENGTHS: Final = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
STANDARD_FD_DATA_BITRATES: Final = (2_000_000, 4_000_000, 5_000_000, 8_000_000)

RPDO_BYTES: Final = 4
TPDO1_BYTES: Final = 8
TPDO2_BYTES: Final = 4
TPDO_FD_BYTES: Final = 12
TPDO_FD_SYNC_BYTES: Final = 13  # + the SYNC counter echo (the driver's FD layout): a 16-byte FD frame
HEARTBEAT_BYTES: Final = 1


def classical_frame_bits(n_bytes: int) -> int:
    """Worst-case bits of a classical base frame including the 3-bit interframe space."""
    if not 0 <= n_bytes <= 8:
        raise ValueError(f"classical CAN carries 0..8 bytes, not {n_bytes}")
    stuffable = 34 + 8 * n_bytes
    return stuffable + 13 + (stuffable - 1) // 4


def fd_padded_length(n_bytes: int) -> int:
    for length in FD_LENGTHS:
        if length >= n_bytes:
            return length
    raise ValueError(f"CAN FD carries at most 64 bytes, not {n_bytes}")


def fd_frame_bits(n_bytes: int) -> tuple[int, int]:
    """Worst-case (nominal-rate bits, data-rate bits) of a CAN FD base frame with BRS."""
    n = fd_padded_length(n_bytes)
    arbitration = 17  # SOF, 11-bit ID, RRS, IDE, FDF, res, BRS
    data_dynamic = 5 + 8 * n  # ESI, DLC, data
    stuff_total = (arbitration + data_dynamic - 1) // 4
    stuff_nominal = (arbitration - 1) // 4  # the most that can fall in the arbitration phase
    crc = 17 if n <= 16 else 21
    crc_field = 4 + crc  # stuff count (gray code + parity) + CRC
    fixed_stuff = 1 + crc_field // 4
    nominal = arbitration + stuff_nominal + 13  # + CRC delimiter, ACK slot+delim, EOF, IFS
    data = data_dynamic + (stuff_total - stuff_nominal) + crc_field + fixed_stuff
    return nominal, data


@dataclass(frozen=True)
class BusLoad:
    n_drives: int
    rate_hz: float
    bitrate: int
    data_bitrate: int | None  # None: classical CAN
    frames_per_cycle: int
    nominal_bits_per_cycle: int  # classical: all bits; FD: bits at the nominal rate
    data_bits_per_cycle: int  # FD: bits at the data rate; classical: 0
    cycle_time_s: float  # bus time one cycle occupies
    heartbeat_load: float  # fraction of the bus taken by heartbeats
    load: float  # fraction of the bus at rate_hz, heartbeats included
    fd_tpdo_bytes: int = TPDO_FD_BYTES  # CAN FD TPDO data bytes (13 with the SYNC counter echo)
    heartbeat_period_s: float | None = None  # the drives' heartbeat period (None: not counted)
    master_heartbeat_period_s: float | None = None  # the master's own heartbeat (None: not counted)

    @property
    def max_rate_hz(self) -> float:
        """Highest cycle rate under the default 85 % limit."""
        return max_rate_hz(self, DEFAULT_LIMIT)

    def describe(self) -> str:
        kind = (
            f"classical CAN at {_mbit(self.bitrate)}"
            if self.data_bitrate is None
            else f"CAN FD at {_mbit(self.bitrate)} nominal, {_mbit(self.data_bitrate)} data"
        )
        bits = (
            f"{self.nominal_bits_per_cycle} bits"
            if self.data_bitrate is None
            else f"{self.nominal_bits_per_cycle}+{self.data_bits_per_cycle} bits"
        )
        return (
            f"{self.n_drives} drives on {kind}: {bits} "
            f"({self.cycle_time_s * 1e6:.0f} µs) per cycle, {self.load:.1%} load at "
            f"{self.rate_hz:g} Hz"
        )


def _mbit(bitrate: int) -> str:
    return f"{bitrate / 1e6:g} Mbit/s"


def max_rate_hz(load: BusLoad, limit: float = DEFAULT_LIMIT) -> float:
    return max(0.0, (limit - load.heartbeat_load) / load.cycle_time_s)


def compute_bus_load(
    n_drives: int,
    rate_hz: float,
    bitrate: int,
    data_bitrate: int | None = None,
    heartbeat_period_s: float | None = None,
    fd_tpdo_bytes: int = TPDO_FD_BYTES,
    master_heartbeat_period_s: float | None = None,
) -> BusLoad:
    """Bus load of one SYNC + N RPDOs + N drives' TPDOs per cycle (+ heartbeats: the drives'
    every ``heartbeat_period_s``, the master's every ``master_heartbeat_period_s``).

    ``fd_tpdo_bytes``: data bytes of the CAN FD TPDO (12, or 13 with the SYNC counter echo the
    driver maps: padded to a 16-byte frame).

    ``data_bitrate`` None means classical CAN; with a value, frames are CAN FD with bit-rate
    switch (a data bitrate equal to the nominal one is CAN FD without switching).
    """
    if n_drives < 1 or rate_hz <= 0 or bitrate <= 0:
        raise ValueError("need at least one drive, a positive rate and a positive bitrate")
    if data_bitrate is None:
        bits = classical_frame_bits(0) + n_drives * (
            classical_frame_bits(RPDO_BYTES) + classical_frame_bits(TPDO1_BYTES) + classical_frame_bits(TPDO2_BYTES)
        )
        nominal_bits, data_bits, frames = bits, 0, 1 + 3 * n_drives
        cycle_time_s = bits / bitrate
        heartbeat_time_s = n_drives * classical_frame_bits(HEARTBEAT_BYTES) / bitrate
    else:
        if data_bitrate < bitrate:
            raise ValueError("the CAN FD data bitrate cannot be below the nominal bitrate")
        sync_bits = classical_frame_bits(0)  # SYNC stays a classical frame
        rpdo_nominal, rpdo_data = fd_frame_bits(RPDO_BYTES)
        tpdo_nominal, tpdo_data = fd_frame_bits(fd_tpdo_bytes)
        nominal_bits = sync_bits + n_drives * (rpdo_nominal + tpdo_nominal)
        data_bits = n_drives * (rpdo_data + tpdo_data)
        frames = 1 + 2 * n_drives
        cycle_time_s = nominal_bits / bitrate + data_bits / data_bitrate
        heartbeat_time_s = n_drives * classical_frame_bits(HEARTBEAT_BYTES) / bitrate
    heartbeat_load = heartbeat_time_s / heartbeat_period_s if heartbeat_period_s else 0.0
    if master_heartbeat_period_s:
        heartbeat_load += classical_frame_bits(HEARTBEAT_BYTES) / bitrate / master_heartbeat_period_s
    return BusLoad(
        n_drives=n_drives,
        rate_hz=rate_hz,
        bitrate=bitrate,
        data_bitrate=data_bitrate,
        frames_per_cycle=frames,
        nominal_bits_per_cycle=nominal_bits,
        data_bits_per_cycle=data_bits,
        cycle_time_s=cycle_time_s,
        heartbeat_load=heartbeat_load,
        load=cycle_time_s * rate_hz + heartbeat_load,
        fd_tpdo_bytes=fd_tpdo_bytes,
        heartbeat_period_s=heartbeat_period_s,
        master_heartbeat_period_s=master_heartbeat_period_s,
    )


def what_would_fit(load: BusLoad, limit: float = DEFAULT_LIMIT) -> str:
    """One sentence on what does fit: this bus's max rate, an FD data rate, or more buses."""
    parts = [f"this bus fits about {math.floor(max_rate_hz(load, limit))} Hz"]
    hb_period, master_hb_period = load.heartbeat_period_s, load.master_heartbeat_period_s
    for data_bitrate in STANDARD_FD_DATA_BITRATES:
        if load.data_bitrate is not None and data_bitrate <= load.data_bitrate:
            continue
        fd = compute_bus_load(
            load.n_drives, load.rate_hz, load.bitrate, data_bitrate, hb_period, load.fd_tpdo_bytes, master_hb_period
        )
        if fd.load <= limit:
            parts.append(f"{load.rate_hz:g} Hz needs CAN FD with a {_mbit(data_bitrate)} data phase ({fd.load:.0%})")
            break
    per_bus = 0
    for n in range(load.n_drives, 0, -1):
        if (
            compute_bus_load(
                n, load.rate_hz, load.bitrate, load.data_bitrate, hb_period, load.fd_tpdo_bytes, master_hb_period
            ).load
            <= limit
        ):
            per_bus = n
            break
    if per_bus:
        buses = math.ceil(load.n_drives / per_bus)
        parts.append(f"or {buses} buses of at most {per_bus} drives")
    return "; ".join(parts)


def check_bus_load(
    n_drives: int,
    rate_hz: float,
    bitrate: int,
    data_bitrate: int | None = None,
    heartbeat_period_s: float | None = None,
    limit: float = DEFAULT_LIMIT,
    source: str = "config",
    fd_tpdo_bytes: int = TPDO_FD_BYTES,
    master_heartbeat_period_s: float | None = None,
) -> BusLoad:
    """The bus load, or :class:`BusLoadError` saying what would fit when above ``limit``."""
    load = compute_bus_load(
        n_drives, rate_hz, bitrate, data_bitrate, heartbeat_period_s, fd_tpdo_bytes, master_heartbeat_period_s
    )
    if load.load > limit:
        raise BusLoadError(f"{source}: {load.describe()}, above the {limit:.0%} limit; {what_would_fit(load, limit)}")
    return load
