"""``hil bench gnss``: the GNSS receiver on a wire -- what the line carries, what the codecs cost,
how well the bridge time-tags reception.

1. Bytes an epoch and line occupancy per message set, at 1/5/10/20 Hz and 9600/38400/115200
   baud (8N1: 10 bits a byte), from the codecs' own output; where occupancy passes 100 % the
   UART model (``hil.wire.line.Uart``) says how many epochs of 10 s overrun.
2. Encode and decode cost per epoch beside pynmeagps's and pyubx2's own parse of the same bytes
   (a ratio, same run, best of several repeats).
3. Reception time tags: a live ``hil up`` with the receiver on a wire; each fix the bridge
   stamped (``rx_stamp_ns``) against the ideal end of its bytes on the line (its output time plus
   its bytes at the baud rate, from the same emulator node replayed on the virtual clock, which
   is where ``hil sim`` stamps it: an error of 0 by construction there).
"""

from __future__ import annotations

import os
import tempfile
import timeit
from pathlib import Path

import numpy as np
from pynmeagps import NMEAReader
from pyubx2 import UBXReader

from hil.bench import command_line, write_section
from hil.nodes.base import SERIAL_TX
from hil.nodes.gnss_emulator import GnssEmulatorNode, GnssEmulatorOptions
from hil.record.mcapio import read_session
from hil.runtime.argtypes import OneLineParser, duration_s
from hil.runtime.supervisor import Supervisor, UpOptions
from hil.wire import protocol
from hil.wire.base import ReceiverEpoch
from hil.wire.line import LineDecoder, Uart, byte_time_ns

SETS: dict[str, list[tuple[str, tuple[str, ...] | None]]] = {
    "NMEA RMC VTG GGA GSA GST ZDA (default)": [("nmea", None)],
    "NMEA GGA RMC": [("nmea", ("RMC", "GGA"))],
    "UBX NAV-PVT NAV-COV NAV-EOE (default) + TIM-TP": [("ubx", None)],
    "UBX NAV-POSLLH NAV-VELNED + TIM-TP": [("ubx", ("NAV-POSLLH", "NAV-VELNED"))],
    "NMEA default + UBX default": [("nmea", None), ("ubx", None)],
}
RATES_HZ = (1, 5, 10, 20)
BAUDS = (9600, 38400, 115200)
EPOCH = ReceiverEpoch(
    1_448_000_000_000_000_000, 50.4512345, 30.5234567, 412.3, (12.3, -4.5, 0.2), (1.5, 1.5, 3.0),
    (0.1, 0.1, 0.2), 3, 14, 0.7, 1.26, 1.05,
)  # fmt: skip


def epoch_bytes(parts: list[tuple[str, tuple[str, ...] | None]]) -> tuple[bytes, int]:
    """One epoch's bytes for a message set, and the TIM-TP bytes sent once a second (UBX)."""
    data, pps = b"", 0
    for name, msgs in parts:
        p = protocol(name)(msgs)
        data += p.encode_epoch(EPOCH)
        pps += len(p.encode_pps_announcement(EPOCH.gps_time_ns + 1_000_000_000))
    return data, pps


def line_table() -> str:
    rows = ["| message set | B/epoch | " + " | ".join(f"{r} Hz" for r in RATES_HZ) + " |"]
    rows.append("| --- | ---: |" + " ---: |" * len(RATES_HZ))
    for label, parts in SETS.items():
        data, pps = epoch_bytes(parts)
        cells = []
        for rate in RATES_HZ:
            bps = len(data) * rate + pps
            occ = [bps * 10 / baud for baud in BAUDS]
            over = [_overruns(len(data), pps, rate, baud) for baud in BAUDS]
            cells.append(
                f"{bps:,} B/s: "
                + ", ".join(
                    f"{o:.0%}" + (f" ({n} lost)" if n else "") for o, n in zip(occ, over, strict=True)
                )
            )
        rows.append(f"| {label} | {len(data)} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def _overruns(n_bytes: int, pps: int, rate: int, baud: int, seconds: int = 10) -> int:
    """Epochs of ``seconds`` the UART drops (4 KiB transmit buffer)."""
    uart, lost = Uart(baud), 0
    for k in range(seconds * rate):
        t = round(k * 1e9 / rate)
        extra = pps if k % rate == 0 else 0
        lost += uart.send(n_bytes + extra, t) is None
    return lost


def codec_table(repeat: int = 7, number: int = 300) -> str:
    rows = ["| protocol | bytes | encode µs | decode µs | field parser µs | decode / field parser |"]
    rows.append("| --- | ---: | ---: | ---: | ---: | ---: |")
    for name, parser in (("nmea", _pynmeagps_parse), ("ubx", _pyubx2_parse)):
        p = protocol(name)()
        data = p.encode_epoch(EPOCH)
        enc = min(timeit.repeat(lambda p=p: p.encode_epoch(EPOCH), number=number, repeat=repeat)) / number
        dec = (
            min(timeit.repeat(lambda p=p, d=data: p.decoder().feed(d, 0), number=number, repeat=repeat))
            / number
        )
        ref = min(timeit.repeat(lambda d=data, f=parser: f(d), number=number, repeat=repeat)) / number
        us = (enc * 1e6, dec * 1e6, ref * 1e6)
        rows.append(f"| {name} | {len(data)} | {us[0]:.1f} | {us[1]:.1f} | {us[2]:.1f} | {dec / ref:.2f} |")
    return "\n".join(rows)


def _pynmeagps_parse(data: bytes) -> int:
    return sum(1 for line in data.split(b"\r\n") if line and NMEAReader.parse(line + b"\r\n", validate=1))


def _pyubx2_parse(data: bytes) -> int:
    n, i = 0, 0
    while i < len(data):
        size = 8 + int.from_bytes(data[i + 4 : i + 6], "little")
        UBXReader.parse(data[i : i + size], validate=1)
        n, i = n + 1, i + size
    return n


def ideal_ends_ns(run: object, opts: GnssEmulatorOptions) -> dict[int, int]:
    """Epoch index -> when its last byte is on the line, ideally: the emulator node on the
    virtual clock (ticked exactly when it asks)."""
    node = GnssEmulatorNode(run, opts)
    out: dict[int, int] = {}
    t = node.next_tick_ns()
    period = node.core.period_ns
    while t is not None:
        for key, burst in node.tick(t):
            if key == SERIAL_TX:
                k = _epoch_of(burst.data, protocol(opts.protocol[0]), run, period)
                if k is not None:
                    out[k] = burst.end_ns
        t = node.next_tick_ns()
    return out


def _epoch_of(data: bytes, proto: object, run: object, period_ns: int) -> int | None:
    from hil.wire.gnss_time import gps_ns_to_utc_ns

    fixes = LineDecoder((proto.name,)).feed(data, 0) + LineDecoder((proto.name,)).flush()  # type: ignore[attr-defined]
    for f in fixes:
        if f.gps_time_ns is not None:
            return round((gps_ns_to_utc_ns(f.gps_time_ns) - run.start_epoch_ns) / period_ns)  # type: ignore[attr-defined]
    return None


def live_tag_errors(protocol_name: str, baud: int, duration_s: float) -> np.ndarray:
    """Bridge receive stamp minus the ideal end of the epoch's bytes (µs), from a live run."""
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "gnss.mcap"
        sup = Supervisor(
            UpOptions(
                duration_s=duration_s, record=rec, rig="benchgnss", live=False, log_dir=Path(d) / "logs",
                gnss_protocol=[protocol_name], gnss_baud=baud, estimators=["comp1"],
            )
        )  # fmt: skip
        if sup.run() != 0:
            raise RuntimeError("\n".join(sup.failures))
        s = read_session(rec)
        run = s.by_topic("hil/benchgnss/run")[0].decode()
        fixes = [r.decode() for r in s.by_topic("hil/benchgnss/sensor/gnss")]
    ends = ideal_ends_ns(run, GnssEmulatorOptions(protocol=[protocol_name], baud=baud))
    return np.array([(f.rx_stamp_ns - ends[f.seq]) / 1e3 for f in fixes if f.seq in ends])


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench gnss")
    ap.add_argument("--duration", type=duration_s, default=30.0, help="seconds of each live run")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    lines = [
        "Line occupancy per message set: bytes a second at each rate, then the share of a 9600, "
        "38400 and 115200 baud line they take (8N1: 10 bits a byte); past 100 % the UART's 4 KiB "
        "transmit buffer fills and whole epochs are dropped (lost of 10 s, `hil.wire.line.Uart`):",
        "",
        line_table(),
        "",
        "Codec cost per epoch (best of 7 x 300), beside the field's own parser of the same bytes "
        "(pynmeagps `NMEAReader.parse` per sentence, pyubx2 `UBXReader.parse` per frame, both "
        "validating checksums), same run:",
        "",
        codec_table(),
        "",
        f"Reception time tags, live (`hil up` {a.duration:g} s, straight_level, 10 Hz): the bridge's "
        "receive stamp of each fix minus the ideal time its last byte is on the line (output time + "
        "bytes at the baud rate). In `hil sim` it is 0 by construction (the runner delivers the "
        "line's bytes at that instant).",
        "",
        "| line | fixes | median µs | p99 µs | max µs |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    load = os.getloadavg()[0]
    for name, baud in (("nmea", 115200), ("ubx", 115200), ("nmea", 38400)):
        err = live_tag_errors(name, baud, a.duration)
        lines.append(
            f"| {name} at {baud} baud | {len(err)} | {np.median(err):.0f} | {np.percentile(err, 99):.0f} | "
            f"{err.max():.0f} |"
        )
        print(lines[-1], flush=True)
    lines += [
        "",
        f"One byte takes {byte_time_ns(115200) / 1e3:.1f} µs at 115200 baud. The live figure holds the "
        "emulator's wake-up lateness, the writer's 1 ms chunks, the pseudo-terminal and the bridge's read: "
        "what a device reading the same line would also see. Load average (1 min) before the live runs: "
        f"{load:.2f} on {os.cpu_count()} cores (the tail grows with other work on the machine).",
    ]
    md = "\n".join(lines)
    print(md)
    if not a.no_write:
        write_section("gnss", md, command_line())
    return 0
