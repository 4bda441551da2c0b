"""When a fix read off a serial line arrived: from its epoch's first byte, not the read that
completed it.

A receiver's output latency ends where its epoch's output begins; the line then takes its bytes'
time (the default NMEA set: ~27 ms at 115200 baud). The decoders say where each epoch began on
the line and how many bytes the line carried from there (``DecodedFix.line_bytes``), the bridge
turns that into ``GnssFix.line_ns``, and the time sync measures a receiver timed by arrivals
alone from ``rx_stamp_ns - line_ns``. Before, every such fix was stamped the line's time late.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from hil.bench.capture import restamp_errors
from hil.messages import GnssFix
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nodes.base import LineBurst
from hil.nodes.gnss_bridge import GnssBridgeNode, GnssBridgeOptions
from hil.nodes.gnss_emulator import GnssEmulatorNode, GnssEmulatorOptions
from hil.nodes.timesync import TimeSyncNode
from hil.record.mcapio import read_session
from hil.runners.serial import LineWriter
from hil.runners.sim import SimOptions, run_sim, sim_run_info
from hil.wire import protocol
from hil.wire.base import ReceiverEpoch
from hil.wire.gnss_time import utc_ns_to_gps_ns
from hil.wire.line import LineDecoder, byte_time_ns

_GPS_NS = 1_400_000_000_000_000_000  # on the 10 ms grid NMEA prints


def _epoch(gps_ns: int = _GPS_NS) -> ReceiverEpoch:
    return ReceiverEpoch(gps_ns, 50.1, 30.2, 400.0, (1.0, 2.0, 0.0), (1.5, 1.5, 3.0), (0.1,) * 3, 3, 14, 0.7, 1.3, 1.1)  # fmt: skip


@pytest.mark.parametrize("wire", ["nmea", "ubx"])
def test_a_fix_counts_its_epochs_bytes_from_the_first_to_the_end_of_the_read_that_completed_it(
    wire: str,
) -> None:
    # GIVEN noise on the line, then one epoch in three reads, the last carrying the next epoch's start
    enc = protocol(wire)()
    first, second = enc.encode_epoch(_epoch()), enc.encode_epoch(_epoch(_GPS_NS + 100_000_000))
    noise = b"\x00\xffnoise\r\n"
    dec = LineDecoder((wire,))
    a, b = len(first) // 3, 2 * len(first) // 3
    assert dec.feed(noise + first[:a], 1) == [] and dec.feed(first[a:b], 2) == []
    (fix,) = dec.feed(first[b:] + second[:12], 3)  # closed by its last message, in that read
    # THEN it began after the noise and the line carried it, and 12 bytes more, by that read
    assert fix.rx_ns == 3
    assert fix.first_byte_at == len(noise)
    assert fix.line_bytes == len(first) + 12


def test_on_a_line_with_both_protocols_the_ubx_fix_counts_from_the_epochs_first_nmea_sentence() -> None:
    # GIVEN a u-blox port with NMEA and UBX on: each epoch's sentences, then its frames
    nmea, ubx = protocol("nmea")(), protocol("ubx")()
    dec = LineDecoder(("nmea", "ubx"))
    lead = b""
    for k in range(3):
        e = _epoch(_GPS_NS + k * 100_000_000)
        s, f = nmea.encode_epoch(e), ubx.encode_epoch(e)
        (nmea_fix,) = dec.feed(lead + s, 10 * k + 1)
        (ubx_fix,) = dec.feed(f, 10 * k + 2)
        # THEN the NMEA fix took its sentences' bytes; the UBX fix those and its frames': the
        # epoch's output began with its first sentence, whichever protocol the rig reads
        assert (nmea_fix.protocol, ubx_fix.protocol) == ("nmea", "ubx")
        assert nmea_fix.line_bytes == len(s)
        assert ubx_fix.line_bytes == len(s) + len(f), k
        assert ubx_fix.first_byte_at == nmea_fix.first_byte_at
        lead = b"$GPTXT,01,01,02,idle*" + b"00\r\n" if k == 0 else b""  # a bad line between epochs


def test_the_bridge_publishes_the_line_time_at_its_baud_rate_at_most_one_period() -> None:
    run = sim_run_info(SimOptions(duration_s=5.0))
    period_ns = round(1e9 / load_scenario(run.scenario).gnss.rate_hz)
    data = protocol("nmea")().encode_epoch(_epoch(utc_ns_to_gps_ns(run.start_epoch_ns + 1_000_000_000)))
    for baud, want in ((115200, round(len(data) * byte_time_ns(115200))), (9600, period_ns)):
        node = GnssBridgeNode(run, GnssBridgeOptions(protocol=["nmea"], baud=baud))
        outs = node.on_message("@serial/gnss", data, 2_000_000_000)
        (fix,) = [m for k, m in outs if k == "sensor/gnss"]
        assert isinstance(fix, GnssFix)
        # 9600 baud: 317 B take 330 ms, more than the 100 ms period: a line that paused
        assert (fix.rx_stamp_ns, fix.line_ns) == (2_000_000_000, want), baud
        assert fix.arrival_ns() == 2_000_000_000 - want


def test_the_time_sync_measures_an_arrival_timed_receiver_from_its_first_byte() -> None:
    # GIVEN the same fixes twice: read off a line (line_ns, rx at the last byte) and as if the
    # line took no time (rx at the first byte)
    text = load_scenario("straight_level").source_text + "\n[clock.gnss]\ntimetag = false\n"
    run = sim_run_info(SimOptions(duration_s=30.0))
    run = msgspec.structs.replace(run, scenario_toml=text)
    rng = np.random.default_rng(3)
    on_line, no_line = TimeSyncNode(run), TimeSyncNode(run)
    got_line, got_plain = [], []
    for k in range(1, 60):
        t = k * 100_000_000
        first_byte = t + 100_000_000 + int(rng.exponential(2e6))  # the receiver's 100 ms latency
        line = 27_000_000 + int(rng.integers(0, 300_000))
        fix = GnssFix(seq=k, stamp_ns=first_byte + line, device_stamp_ns=t, rx_stamp_ns=first_byte + line,
                      lat_deg=0.0, lon_deg=0.0, alt_m=0.0, pos_ned_m=[0.0] * 3, vel_ned_mps=[0.0] * 3,
                      pos_sigma_m=[1.0] * 3, vel_sigma_mps=[0.1] * 3, fix_type=3, num_sats=9, hdop=1.0,
                      line_ns=line)  # fmt: skip
        plain = msgspec.structs.replace(fix, line_ns=0, rx_stamp_ns=first_byte, stamp_ns=first_byte)
        got_line += [(m.seq, m.stamp_ns) for _, m in on_line.on_message("sensor/gnss", fix, fix.rx_stamp_ns)]
        got_plain += [(m.seq, m.stamp_ns) for _, m in no_line.on_message("sensor/gnss", plain, first_byte)]
    got_line += [(m.seq, m.stamp_ns) for _, m in on_line.finish(10**10)]
    got_plain += [(m.seq, m.stamp_ns) for _, m in no_line.finish(10**10)]
    # THEN it re-stamps them alike, within the exponential delay's floor of the truth
    assert got_line == got_plain and len(got_line) == 59
    late = [s - q * 100_000_000 for q, s in got_line[20:]]
    assert max(abs(v) for v in late) < 1_000_000, late


@pytest.mark.parametrize("wire", [["nmea"], ["nmea", "ubx"]])
def test_a_sim_receiver_timed_by_arrivals_on_a_line_is_stamped_at_its_time_of_validity(
    wire: list[str], tmp_path: Path
) -> None:
    # GIVEN the rig's default run with its receiver on a 115200-baud line and no PPS used
    scenario = tmp_path / "arrivals.toml"
    base = scenario_overrides(load_scenario("straight_level"), name="gnss_line_arrivals")
    scenario.write_text(base.source_text + "\n[clock.gnss]\ntimetag = false\n")
    rec = tmp_path / "r.mcap"
    run_sim(
        SimOptions(
            scenario=str(scenario), duration_s=12.0, record=rec, estimators=["comp1"], gnss_protocol=wire
        )
    )
    t, err = restamp_errors(read_session(rec), "gnss")
    err = err[t > 4.0]
    # THEN its fixes are re-stamped at their capture (27 ms of NMEA late before, 43 ms with UBX)
    assert len(err) > 70
    assert np.max(np.abs(err)) < 1_000_000, (err.min(), err.max())


def test_the_line_writer_hands_over_no_byte_before_its_last_bit_would_have_arrived(tmp_path: Path) -> None:
    # GIVEN the emulator's line, a pty at 115200 baud, and a reader on its link
    link = tmp_path / "gps"
    writer = LineWriter(115200, [str(link)])
    fd = -1
    try:
        fd = os.open(link, os.O_RDONLY | os.O_NONBLOCK)
        data = bytes(range(256)) * 2
        start = time.time() + 0.05
        writer.write(data, start)
        dt_s = byte_time_ns(115200) * 1e-9
        got = 0
        deadline = time.monotonic() + 30.0
        while got < len(data) and time.monotonic() < deadline:
            with contextlib.suppress(BlockingIOError):
                n = len(os.read(fd, 4096))
                now = time.time()
                got += n
                # THEN by any moment, at most the bytes whose 10 bits had gone by have come
                assert got <= (now - start) / dt_s + 1e-6, (got, (now - start) / dt_s)
                continue
            time.sleep(0.0005)
        assert got == len(data)
    finally:
        if fd >= 0:
            os.close(fd)
        writer.close()


def test_at_another_speed_the_line_keeps_its_baud_rate_in_wall_time() -> None:
    # GIVEN ``hil up --speed 2``: rig time runs twice as fast as the wall clock the line is paced by
    run = msgspec.structs.replace(sim_run_info(SimOptions(duration_s=5.0)), speed=2.0)
    data = protocol("nmea")().encode_epoch(_epoch(utc_ns_to_gps_ns(run.start_epoch_ns + 1_000_000_000)))
    bridge = GnssBridgeNode(run, GnssBridgeOptions(protocol=["nmea"], baud=115200))
    (fix,) = [m for k, m in bridge.on_message("@serial/gnss", data, 2_000_000_000) if k == "sensor/gnss"]
    # THEN the bytes' time on the line, in rig ns, is twice their wall time (27 ms of NMEA: 54)
    assert fix.line_ns == round(len(data) * byte_time_ns(115200) * 2.0)
    emulator = GnssEmulatorNode(run, GnssEmulatorOptions(protocol=["nmea"], baud=115200))
    bursts = []
    while (t := emulator.next_tick_ns()) is not None and t < 2_000_000_000:
        bursts += [m for _k, m in emulator.tick(t) if isinstance(m, LineBurst)]
    assert bursts and all(
        b.end_ns - b.start_ns == round(len(b.data) * byte_time_ns(115200) * 2.0) for b in bursts
    )
