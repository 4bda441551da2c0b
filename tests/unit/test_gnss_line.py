"""The receiver's line in the node model: the UART's pacing and overrun, faults on the bytes,
bad input at the bridge, and times across a GPS week rollover and a day boundary -- through the
same emulator and bridge nodes the live rig runs, on ``hil sim``'s virtual clock."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.faults import LineAction, LineFaults
from hil.nav.scenario import ScenarioEvent, load_scenario
from hil.nodes.gnss_bridge import GnssBridgeNode, GnssBridgeOptions
from hil.record.mcapio import read_session
from hil.runners.sim import SimOptions, run_sim, sim_run_info
from hil.wire import protocol
from hil.wire.base import ReceiverEpoch
from hil.wire.gnss_time import gps_week_tow, utc_ns_to_gps_ns
from hil.wire.line import BAUD_MISMATCH_BYTES, LineDecoder, Uart

_EPOCH = ReceiverEpoch(1_400_000_000_000_000_000, 50.1, 30.2, 400.0, (1.0, 2.0, 0.0), (1.5, 1.5, 3.0), (0.1,) * 3, 3, 14, 0.7, 1.3, 1.1)  # fmt: skip


def test_the_uart_paces_bytes_at_the_baud_rate_and_drops_what_overruns_its_buffer() -> None:
    uart = Uart(9600, tx_buffer_bytes=600)
    assert uart.send(300, 0) == (0, 312_500_000)  # 300 bytes x 10 bits at 9600 baud
    assert uart.send(300, 100_000_000) == (312_500_000, 625_000_000)  # waits for the line
    assert uart.queued_bytes(100_000_000) == 504
    assert uart.send(300, 200_000_000) is None  # 408 queued + 300 > 600: overrun, dropped whole
    assert (uart.overrun_messages, uart.overrun_bytes, uart.sent_bytes) == (1, 300, 600)
    assert uart.send(300, 700_000_000) == (700_000_000, 1_012_500_000)  # the line is free again


def test_a_slow_line_overruns_like_a_real_receiver_counted_and_visible(tmp_path: Path) -> None:
    # GIVEN the default NMEA set (317 B an epoch) at 10 Hz on a 9600-baud line (960 B/s)
    rec = tmp_path / "slow.mcap"
    run_sim(
        SimOptions(duration_s=10.0, record=rec, estimators=["comp1"], gnss_protocol=["nmea"], gnss_baud=9600)
    )
    s = read_session(rec)
    emu = s.by_topic("hil/sim/status/gnss_emulator")[-1].decode().counter_map()
    fixes = s.by_topic("hil/sim/sensor/gnss")
    # THEN about a third of the epochs fit: the rest overrun, counted, and never reach the bridge
    assert emu["line.epochs"] == 99 and emu["line.overrun_epochs"] >= 50, (
        emu
    )  # the 100th is out after the end
    # what the line carried: 960 B/s, plus what still waited in the 4 KiB buffer at the end
    assert 25 <= len(fixes) <= 99 - emu["line.overrun_epochs"]
    assert emu["line.bytes_sent"] <= 960 * 10 + 4096 + 317
    assert "UART overrun" in s.by_topic("hil/sim/status/gnss_emulator")[-1].decode().last_error


def test_line_faults_damage_the_same_epochs_every_run_and_the_bridge_counts_them() -> None:
    ev = load_scenario("straight_level").events
    faults = [ScenarioEvent("gnss_line_checksum", 0.0, 5.0, {"percent": 40.0})]
    a, b = LineFaults(7, [*ev, *faults]), LineFaults(7, [*ev, *faults])
    acts = [a.epoch(k, k * 100_000_000).corrupt for k in range(50)]
    assert acts == [b.epoch(k, k * 100_000_000).corrupt for k in range(50)]
    assert 10 <= acts.count("checksum") <= 30
    nmea = protocol("nmea")()
    node = GnssBridgeNode(sim_run_info(SimOptions(duration_s=5.0)), GnssBridgeOptions(protocol=["nmea"]))
    data = nmea.encode_epoch(_EPOCH)
    damaged = a.damage(data, LineAction(corrupt="checksum"), 1)
    assert damaged != data and len(damaged) == len(data)
    node.on_message("@serial/gnss", damaged, 1)
    assert node.counters()["rejected.line.bad_checksum"] == 1 and "checksum" in node.last_error.lower()


def test_a_line_at_the_wrong_baud_rate_reads_as_garbage_and_says_so() -> None:
    rng = np.random.default_rng(3)
    line = LineDecoder(("nmea", "ubx"))
    noise = bytes(rng.integers(0, 256, 4 * BAUD_MISMATCH_BYTES, dtype=np.uint8).tolist())
    assert line.feed(noise, 0) == []
    assert line.counters["baud_mismatch"] >= 1 and "baud rate" in line.last_problem
    # ... and a valid message afterwards is read again
    fixes = line.feed(protocol("nmea")().encode_epoch(_EPOCH) + protocol("ubx")().encode_epoch(_EPOCH), 1)
    assert {f.protocol for f in fixes} == {"nmea", "ubx"}


@pytest.mark.parametrize("wire", ["nmea", "ubx"])
def test_times_across_the_gps_week_rollover_and_a_day_boundary_stay_continuous(
    wire: str, tmp_path: Path
) -> None:
    # GIVEN a run whose 30 s span GPS week 2047 -> 2048 (2019-04-06T23:59:42Z) and midnight UTC
    text = load_scenario("static").source_text.replace(
        "seed = ", 'start_utc = "2019-04-06T23:59:30Z"\nseed = ', 1
    )
    path = tmp_path / "rollover.toml"
    path.write_text(text)
    rec = tmp_path / "r.mcap"
    run_sim(
        SimOptions(
            scenario=str(path), duration_s=40.0, record=rec, estimators=["comp1"], gnss_protocol=[wire]
        )
    )
    s = read_session(rec)
    fixes = [r.decode() for r in s.by_topic("hil/sim/sensor/gnss")]
    run = s.by_topic("hil/sim/run")[0].decode()
    # THEN every epoch decodes, numbered by its time of validity, device time continuous
    assert [f.seq for f in fixes] == list(range(fixes[0].seq, fixes[0].seq + len(fixes)))
    dev = np.diff([f.device_stamp_ns for f in fixes])
    period = round(1e9 / load_scenario("static").gnss.rate_hz)
    assert np.all(np.abs(dev - period) < 20_000_000), dev  # NMEA: 10 ms time resolution
    start_gps = utc_ns_to_gps_ns(run.start_epoch_ns)
    end_gps = utc_ns_to_gps_ns(run.start_epoch_ns + fixes[-1].device_stamp_ns)
    assert gps_week_tow(start_gps)[0] == 2047 and gps_week_tow(end_gps)[0] == 2048
