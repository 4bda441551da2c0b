"""AUTOSAR E2E profile 1 (CRC-8 SAE-J1850 + 4-bit rolling counter), table-driven.

cantools ships profiles 2 and 5 only, so profile 1 lives here. The profile-1 chain calls the
AUTOSAR CRC library as ``Crc_CalculateCRC8(id_lo, 1, 0xFF, FALSE)`` -> ``(id_hi, ..., FALSE)`` ->
``(data, ..., FALSE)`` and XORs the result with 0xFF. Because the library un-XORs the start value
and XORs its output with 0xFF, the net algorithm is: polynomial 0x1D, register start 0x00, no
final XOR, over ``[DataID low byte, DataID high byte, data bytes except the CRC byte]``
(mode ``E2E_P01_DATAID_BOTH``, CRC in byte 0, counter in bits 8..11). The counter runs 0..14;
15 is invalid on the wire.
"""

from __future__ import annotations

import functools
import struct
from typing import Any

POLY = 0x1D
COUNTER_MODULO = 15  # profile 1: counter 0..14, 15 never sent


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _make_table()
# Two bytes per step, indexed by the pair as a little-endian 16-bit value v = b0 | b1 << 8 (b0
# first on the wire): for register r, T[T[r ^ b0] ^ b1] = T16[r ^ v], because r has 8 bits and
# so only meets b0. Little-endian, so the codec reads the pairs straight off the frame as an int
# (``(word >> 8 * i) & 0xFFFF``) with no byte swap. 64 Ki entries, ~15 ms once at import.
_TABLE16 = tuple(_TABLE[_TABLE[x & 0xFF] ^ (x >> 8)] for x in range(1 << 16))


def crc8_j1850_raw(data: bytes | bytearray | memoryview, start: int = 0x00) -> int:
    """CRC-8 with polynomial 0x1D, MSB first, given register start, no final XOR."""
    crc = start
    table = _TABLE
    for b in data:
        crc = table[crc ^ b]
    return crc


_WORDS: dict[int, struct.Struct] = {}


def p01_crc(
    data_id: int, payload: bytes | bytearray | memoryview, data_length: int, crc_byte: int = 0
) -> int:
    """Profile-1 CRC of ``payload[:data_length]`` (the CRC byte itself excluded)."""
    table16 = _TABLE16
    crc = table16[data_id & 0xFFFF]  # id low byte, then high byte: one little-endian pair
    if crc_byte == 0:
        body = payload[1:data_length]
    else:
        body = bytes(payload[:crc_byte]) + bytes(payload[crc_byte + 1 : data_length])
    n = len(body) >> 1
    unpack = _WORDS.get(n)
    if unpack is None:
        unpack = _WORDS[n] = struct.Struct(f"<{n}H")
    for pair in unpack.unpack_from(body):
        crc = table16[crc ^ pair]
    if len(body) & 1:
        crc = _TABLE[crc ^ body[-1]]
    return crc


# Names the expressions of p01_crc_expr use; a generated function's globals must hold them.
CRC_SCOPE = {"_CRC_T8": _TABLE, "_CRC_T16": _TABLE16}


def p01_crc_expr(data_id: int, data_length: int, frame_length: int, word: str) -> str:
    """The profile-1 CRC (CRC byte 0) as one Python expression over ``word``, the frame's
    ``frame_length`` bytes as a little-endian int (< 2**(8 * frame_length)), for code generated
    per frame layout.

    Byte 0 of ``word`` is ignored, so the same expression computes the CRC to send (byte 0 zero)
    and checks a received frame. Unrolled over the constant length: a pair per table look-up,
    no slicing, no bytes objects. Globals needed: :data:`CRC_SCOPE`.
    """
    if not 2 <= data_length <= frame_length:
        raise ValueError(f"E2E data length {data_length} outside 2..{frame_length}")
    expr = f"{_TABLE16[data_id & 0xFFFF]}"  # the register after the Data ID, a constant
    i = 1
    while i < data_length:
        size = 2 if data_length - i >= 2 else 1
        chunk = f"({word} >> {8 * i})"
        if i + size < frame_length:  # bytes above the chunk: mask them off
            chunk = f"({chunk} & {0xFFFF if size == 2 else 0xFF:#x})"
        expr = f"{'_CRC_T16' if size == 2 else '_CRC_T8'}[{expr} ^ {chunk}]"
        i += size
    return expr


def p01_crc_array(data_id: int, data_length: int, frame_length: int, words: Any) -> Any:
    """:func:`p01_crc_expr`'s CRC of each of ``words`` (a uint64 numpy array of frames of at most
    8 bytes, little-endian, byte 0 ignored): the same table look-ups, one numpy pass each, for a
    block of frames computed ahead (``hil.can.codec.ImuCanCodec.prepare_block``)."""
    import numpy as np

    if not 2 <= data_length <= frame_length <= 8:
        raise ValueError(f"E2E data length {data_length} outside 2..{frame_length}, or a frame over 8 bytes")
    t8, t16 = _tables_np()
    reg = np.full(len(words), _TABLE16[data_id & 0xFFFF], dtype=np.int64)
    i = 1
    while i < data_length:
        size = 2 if data_length - i >= 2 else 1
        chunk = ((words >> np.uint64(8 * i)) & np.uint64(0xFFFF if size == 2 else 0xFF)).astype(np.int64)
        reg = (t16 if size == 2 else t8)[reg ^ chunk]
        i += size
    return reg


@functools.cache
def _tables_np() -> tuple[Any, Any]:
    """The look-up tables as numpy arrays, made on first use (numpy only where blocks are)."""
    import numpy as np

    return np.array(_TABLE, dtype=np.int64), np.array(_TABLE16, dtype=np.int64)


def next_counter(counter: int) -> int:
    """The profile-1 successor of ``counter`` (14 wraps to 0)."""
    return (counter + 1) % COUNTER_MODULO


def counter_delta(received: int, last: int) -> int:
    """How far ``received`` is ahead of ``last`` modulo 15 (0 = repeated, 1 = in order)."""
    return (received - last) % COUNTER_MODULO
