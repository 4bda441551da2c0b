"""How long a frame occupies the bus: bits on the wire, with a worst-case bit-stuffing estimate.

Pure arithmetic (ISO 11898-1 frame formats), used by the CAN node to report bus load and by the
benchmark and docs to size the protocol. Stuffing is estimated at its worst case (one stuff bit
per 4 bits of the dynamically stuffed region after the first), because a bus is budgeted for the
worst case; real traffic stuffs less, so the measured load is an upper bound.

Classic base-format frame, n data bytes (all at the nominal rate)::

    SOF 1 + ID 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8n + CRC 15   (stuffed: 34 + 8n)
    + CRC delimiter 1 + ACK 2 + EOF 7 + intermission 3                 (not stuffed: 13)

CAN FD base-format frame with bit-rate switch::

    nominal rate: SOF 1 + ID 11 + RRS 1 + IDE 1 + FDF 1 + res 1 + BRS 1   (stuffed, 17)
                  + ACK 2 + EOF 7 + intermission 3                        (12)
    data rate:    ESI 1 + DLC 4 + data 8n (stuffed, dynamic)
                  + stuff count 4 + CRC 17 (n <= 16) or 21, with a fixed stuff bit every 4 bits
                  + CRC delimiter 1
"""

from __future__ import annotations

from dataclasses import dataclass

NOMINAL_BITRATE = 1_000_000
FD_DATA_BITRATE = 5_000_000


@dataclass(frozen=True, slots=True)
class FrameBits:
    nominal_bits: int  # bits sent at the arbitration (nominal) rate
    data_bits: int  # bits sent at the data rate (FD with BRS only)

    def seconds(
        self, nominal_bitrate: float = NOMINAL_BITRATE, data_bitrate: float = FD_DATA_BITRATE
    ) -> float:
        return self.nominal_bits / nominal_bitrate + self.data_bits / data_bitrate


def frame_bits(n_data: int, *, fd: bool = False, brs: bool = True, extended: bool = False) -> FrameBits:
    """Bits of one data frame with ``n_data`` bytes, worst-case stuffing included."""
    id_extra = 20 if extended else 0  # SRR + IDE + 18-bit extension (IDE moves, net +20)
    if not fd:
        stuffed = 34 + id_extra + 8 * n_data
        return FrameBits(stuffed + (stuffed - 1) // 4 + 13, 0)
    arb = 17 + id_extra
    data_dyn = 5 + 8 * n_data
    dyn_stuff = (arb + data_dyn - 1) // 4
    crc_len = 17 if n_data <= 16 else 21
    fixed = 4 + crc_len
    fixed_stuff = (fixed + 3) // 4  # one fixed stuff bit before the count and every 4 bits after
    data_phase = data_dyn + fixed + fixed_stuff + 1
    # Attribute the dynamic stuff bits pro rata to the phase they fall in.
    arb_stuff = dyn_stuff * arb // (arb + data_dyn)
    nominal = arb + arb_stuff + 12
    data = data_phase + (dyn_stuff - arb_stuff)
    if not brs:
        return FrameBits(nominal + data, 0)
    return FrameBits(nominal, data)


def sample_load(
    frame_lengths: list[tuple[int, bool]],
    rate_hz: float,
    *,
    nominal_bitrate: float = NOMINAL_BITRATE,
    data_bitrate: float = FD_DATA_BITRATE,
) -> float:
    """Bus load (0..1+) of sending frames of ``(n_data, is_fd)`` once per sample at ``rate_hz``."""
    busy = sum(frame_bits(n, fd=fd).seconds(nominal_bitrate, data_bitrate) for n, fd in frame_lengths)
    return busy * rate_hz
