"""Adding a wire protocol is a codec and one registry line: a toy protocol registered at run time
goes through the emulator node, the line (alone and beside NMEA), the bridge node and ``hil sim``
with no other change (docs/recipes.md, "Add a wire protocol")."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from hil.record.mcapio import read_session
from hil.runners.sim import SimOptions, run_sim
from hil.wire import PROTOCOLS, protocol
from hil.wire.base import NO_VEC3, DecodedFix, ReceiverEpoch
from hil.wire.line import LineDecoder


class ToyDecoder:
    """``#TOY,gps_ns,lat,lon,alt,fix\\n`` lines; anything else is counted."""

    def __init__(self) -> None:
        self.counters = dict.fromkeys(("bytes", "messages", "fixes", "bad_checksum", "garbage_bytes"), 0)
        self.last_problem = ""
        self._buf = b""

    def feed(self, data: bytes, rx_ns: int) -> list[DecodedFix]:
        self.counters["bytes"] += len(data)
        self._buf += data
        out = []
        while b"\n" in self._buf:
            line, _, self._buf = self._buf.partition(b"\n")
            parts = line.decode(errors="replace").split(",")
            if parts[0] != "#TOY" or len(parts) != 6:
                self.counters["garbage_bytes"] += len(line) + 1
                self.last_problem = f"not a toy line: {line[:20]!r}"
                continue
            self.counters["messages"] += 1
            self.counters["fixes"] += 1
            gps_ns, lat, lon, alt, fix = int(parts[1]), *map(float, parts[2:5]), int(parts[5])
            out.append(
                DecodedFix(
                    protocol="toy", messages=("TOY",), rx_ns=rx_ns, gps_time_ns=gps_ns,
                    utc_time_of_day_ns=None, lat_deg=lat, lon_deg=lon, alt_m=alt,
                    vel_ned_mps=(0.0, 0.0, 0.0), pos_sigma_ned_m=NO_VEC3, vel_sigma_mps=NO_VEC3,
                    fix_type=fix, num_sats=None, hdop=None, pdop=None, vdop=None,
                )
            )  # fmt: skip
        return out

    def flush(self) -> list[DecodedFix]:
        return []


class ToyProtocol:
    name: ClassVar[str] = "toy"
    START: ClassVar[bytes] = b"#"
    SUPPORTED_MESSAGES: ClassVar[tuple[str, ...]] = ("TOY",)
    DEFAULT_MESSAGES: ClassVar[tuple[str, ...]] = ("TOY",)

    def __init__(self, messages: tuple[str, ...] | None = None, talker: str = "GN") -> None:
        self.messages = messages or self.DEFAULT_MESSAGES

    @staticmethod
    def message_length(buf: bytes | bytearray) -> int:
        end = buf.find(b"\n")
        return end + 1 if end >= 0 else 0

    def encode_epoch(self, e: ReceiverEpoch) -> bytes:
        return f"#TOY,{e.gps_time_ns},{e.lat_deg:.9f},{e.lon_deg:.9f},{e.alt_m:.4f},{e.fix_type}\n".encode()

    def encode_pps_announcement(self, next_pps_gps_ns: int, q_err_ps: int = 0) -> bytes:
        return b""

    def decoder(self) -> ToyDecoder:
        return ToyDecoder()


@pytest.fixture
def toy_registered() -> Iterator[None]:
    PROTOCOLS["toy"] = f"{__name__}:ToyProtocol"
    try:
        yield
    finally:
        del PROTOCOLS["toy"]


def test_a_line_carrying_the_toy_protocol_beside_nmea_splits_into_both(toy_registered: None) -> None:
    assert protocol("toy") is ToyProtocol
    e = ReceiverEpoch(1_400_000_000_000_000_000, 50.1, 30.2, 400.0, (1.0, 2.0, 0.0), (1.0,) * 3, (0.1,) * 3, 3, 9, 0.9, 1.6, 1.3)  # fmt: skip
    nmea = protocol("nmea")()
    line = LineDecoder(("toy", "nmea"))
    data = b"junk" + ToyProtocol().encode_epoch(e) + nmea.encode_epoch(e)
    fixes = [f for i in range(len(data)) for f in line.feed(data[i : i + 1], i)]  # a byte at a time
    assert sorted(f.protocol for f in fixes) == ["nmea", "toy"]
    assert line.counters["garbage_bytes"] == 4


def test_hil_sim_runs_the_toy_receiver_through_emulator_line_and_bridge(
    toy_registered: None, tmp_path: Path
) -> None:
    # GIVEN the same scenario with fixes on Zenoh and on the toy wire
    plain, toy = tmp_path / "plain.mcap", tmp_path / "toy.mcap"
    run_sim(SimOptions(scenario="straight_level", duration_s=5.0, record=plain, estimators=["comp1"]))
    run_sim(
        SimOptions(
            scenario="straight_level", duration_s=5.0, record=toy, estimators=["comp1"], gnss_protocol=["toy"]
        )
    )
    # THEN the bridge decodes every epoch from the toy bytes, at the positions the receiver had
    a = {r.decode().seq: r.decode() for r in read_session(plain).by_topic("hil/sim/sensor/gnss")}
    t = read_session(toy)
    b = {r.decode().seq: r.decode() for r in t.by_topic("hil/sim/sensor/gnss")}
    assert len(b) >= 45 and set(b) <= set(a)
    diff = np.array([np.subtract(b[k].pos_ned_m, a[k].pos_ned_m) for k in b])
    assert np.abs(diff).max() < 1e-3  # 9 decimals of a degree, 4 of a metre
    assert len(t.by_topic("hil/sim/serial/gnss")) == len(b)  # the line, recorded byte for byte
