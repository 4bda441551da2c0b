"""A receiver on a line tells one clock: its PPS tag states the pulse as the line states the
fixes' times, its capture truth carries the epoch index its bytes state, and its "no fix" epochs
of an outage leave at their own times.

NMEA prints times to 10 ms. The emulated receiver's clock is 1.5 ms off its epochs' grid by
default, so each NMEA fix said a time 1.5 ms early while the pulse was stamped to the ns: every
fix was re-stamped 1.5 ms early (sim and ``hil up --gnss-serial``). A clock half a period or more
off the grid (a step, an offset) made the bridge's seq one more than the capture truth's, so
every fix was scored against the next epoch's truth (-96 ms after a +50 ms step).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.bench.capture import restamp_errors
from hil.nav.scenario import load_scenario
from hil.nodes.base import LineBurst
from hil.nodes.gnss_emulator import GnssEmulatorNode, GnssEmulatorOptions
from hil.record.mcapio import read_session
from hil.runners.sim import SimOptions, run_sim, sim_run_info
from hil.wire import protocol
from hil.wire.gnss_time import gps_ns_to_utc_ns
from hil.wire.line import LineDecoder


def test_each_protocol_states_a_time_of_validity_at_its_fields_resolution() -> None:
    t = 1_400_000_000_001_500_000  # 1.5 ms past a 10 ms grid line
    assert protocol("nmea").printed_time_ns(t) == 1_400_000_000_000_000_000  # hhmmss.ss
    assert protocol("nmea").printed_time_ns(t + 4_000_000) == 1_400_000_000_010_000_000
    assert protocol("ubx")().printed_time_ns(t) == t  # NAV-PVT: UTC fields + nano
    assert protocol("ubx")(("NAV-POSLLH", "NAV-VELNED")).printed_time_ns(t) == 1_400_000_000_002_000_000


def _errors(rec: Path) -> tuple[np.ndarray, np.ndarray]:
    t, e = restamp_errors(read_session(rec), "gnss")
    return t, e


@pytest.mark.parametrize("wire", [["nmea"], ["ubx"], ["nmea", "ubx"]])
def test_a_pps_timed_receiver_on_a_line_is_stamped_at_its_time_of_validity(
    wire: list[str], tmp_path: Path
) -> None:
    rec = tmp_path / "r.mcap"
    run_sim(SimOptions(duration_s=8.0, record=rec, estimators=["comp1"], gnss_protocol=wire))
    t, err = _errors(rec)
    err = err[t > 4.0]
    # THEN within the receiver's 20 ns stamp noise and its 1 ns quantum (NMEA: 1.5 ms early before)
    assert len(err) > 35
    assert np.max(np.abs(err)) < 10_000, (err.min(), err.max())


def test_a_receiver_clock_stepped_half_a_period_is_scored_against_the_epoch_it_states(tmp_path: Path) -> None:
    # GIVEN a 10 Hz NMEA receiver whose clock is 6 ms off and steps +50 ms at 10 s
    text = load_scenario("straight_level").source_text
    scenario = tmp_path / "stepped.toml"
    scenario.write_text(text + "\n[clock.gnss]\noffset_s = 0.006\nsteps = [{t_s = 10.0, step_s = 0.05}]\n")
    rec = tmp_path / "r.mcap"
    run_sim(
        SimOptions(
            scenario=str(scenario), duration_s=16.0, record=rec, estimators=["comp1"], gnss_protocol=["nmea"]
        )
    )
    s = read_session(rec)
    fixes = {r.decode().seq for r in s.by_topic("hil/sim/sensor/gnss")}
    truths = {r.decode().seq for r in s.by_topic("hil/sim/capture/gnss")}
    # THEN every fix the bridge read pairs with its epoch's capture truth by seq
    assert fixes <= truths and len(fixes) > 150
    t, err = _errors(rec)
    # before the step: at the truth (+4 ms before: 6 ms printed as 10); after the time sync has
    # declared the step and re-locked: at the truth again (-96 ms before: the next epoch's truth)
    before, after = err[(t > 4.0) & (t < 9.9)], err[t > 13.0]
    assert len(before) > 50 and len(after) > 25
    assert np.max(np.abs(before)) < 10_000, (before.min(), before.max())
    assert np.max(np.abs(after)) < 10_000, (after.min(), after.max())


def _line_epochs(tmp_path: Path, resume_at_ns: int | None = None) -> list[tuple[int, int]]:
    """(first byte out, time of validity on the rig's device timeline) of every epoch the
    receiver puts on an NMEA line in 5 s of ``straight_level`` with an outage 2-3 s."""
    text = load_scenario("straight_level").source_text
    path = tmp_path / "outage.toml"
    path.write_text(text + '\n[[event]]\nkind = "gnss_outage"\nt_start_s = 2.0\nt_end_s = 3.0\n')
    run = sim_run_info(SimOptions(scenario=str(path), duration_s=5.0))
    node = GnssEmulatorNode(run, GnssEmulatorOptions(protocol=["nmea"], resume=resume_at_ns is not None))
    start = resume_at_ns or 0
    node.start(start)
    bursts: list[LineBurst] = []
    while (t := node.next_tick_ns()) is not None:
        bursts += [m for _k, m in node.tick(max(t, start)) if isinstance(m, LineBurst)]
    out = []
    for b in bursts:
        dec = LineDecoder(("nmea",))
        (fix,) = dec.feed(b.data, b.end_ns)
        assert fix.gps_time_ns is not None
        out.append((b.start_ns, gps_ns_to_utc_ns(fix.gps_time_ns) - run.start_epoch_ns))
    return out


def test_an_outage_goes_out_as_no_fix_epochs_each_at_its_own_time(tmp_path: Path) -> None:
    epochs = _line_epochs(tmp_path)
    # THEN every epoch of the run, once, in order, each leaving its latency (0.1 s + < 2 ms of
    # jitter) after its validity -- the outage's ones too; before, those left together at its end
    # (1 s late at most) and delayed the first fix after it by their bytes (~0.3 s)
    assert [round(v / 1e8) for _s, v in epochs] == list(range(49))
    late = [s - v for s, v in epochs]
    assert all(99_000_000 <= d <= 103_000_000 for d in late), late


def test_a_restarted_receiver_sends_no_no_fix_epochs_for_the_time_it_was_dead(tmp_path: Path) -> None:
    epochs = _line_epochs(tmp_path, resume_at_ns=3_450_000_000)
    # THEN its first epoch is the first valid after the restart, on time (before: all 35 epochs
    # it was dead for, at once)
    assert [round(v / 1e8) for _s, v in epochs] == list(range(35, 49))
    assert all(99_000_000 <= s - v <= 103_000_000 for s, v in epochs)
