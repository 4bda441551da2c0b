"""An IMU timed by arrivals alone on CAN FD: its minimum delay is one frame's wire time.

A sample's arrival is its last frame's; the time sync's minimum delay of the IMU counted four
classic frames (560 µs) whatever the bus, so on CAN FD (one frame a sample, ``--fd``) every
sample was re-stamped 405 µs early. The run says which bus it is (``RunInfo.imu_can_fd``), so the
live service, ``hil sim`` and ``hil rerun --core timesync`` configure the same delay.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.bench.capture import restamp_errors
from hil.messages import RunInfo
from hil.nav.scenario import load_scenario, parse_scenario
from hil.record.mcapio import read_session
from hil.record.rerun_timesync import rerun_timesync_records
from hil.runners.sim import SimOptions, run_sim
from hil.timesync.config import sync_config_for


def test_the_imu_s_minimum_delay_is_its_frames_wire_time() -> None:
    s = load_scenario("straight_level")
    classic, fd = sync_config_for(s, "imu"), sync_config_for(s, "imu", imu_can_fd=True)
    # 20 µs + four classic frames of 135 µs, or one 32-byte CAN FD frame of 104.8 µs
    assert (classic.min_delay_ns, fd.min_delay_ns) == (560_000, 124_800)
    # a delay the scenario states is its own, on any bus
    stated = load_scenario("straight_level").source_text + "\n[clock.imu]\nmin_delay_s = 0.0003\n"
    assert sync_config_for(parse_scenario(stated, "x"), "imu", imu_can_fd=True).min_delay_ns == 300_000


@pytest.mark.parametrize("fd", [False, True])
def test_an_imu_timed_by_arrivals_is_stamped_at_its_capture_on_either_bus(fd: bool, tmp_path: Path) -> None:
    scenario = tmp_path / "imu_arrivals.toml"
    scenario.write_text(load_scenario("straight_level").source_text + "\n[clock.imu]\ntimetag = false\n")
    rec = tmp_path / "r.mcap"
    run_sim(SimOptions(scenario=str(scenario), duration_s=12.0, record=rec, estimators=["comp1"], fd=fd))
    records = tuple(read_session(rec).records)
    run = next(r.decode() for r in records if r.topic.endswith("/run"))
    assert isinstance(run, RunInfo) and run.imu_can_fd is fd
    t, err = restamp_errors(read_session(rec), "imu")
    err = err[t > 6.0]
    # THEN within the CAN model's 10 µs of jitter (FD: 405 µs early before)
    assert len(err) > 2000
    assert np.max(np.abs(err)) < 20_000, (err.min(), err.max())
    res = rerun_timesync_records(records, worker=False)
    assert res.difference is None and res.n_recorded == res.n_recomputed


def test_the_fd_frame_time_is_the_dbc_frame_s_on_the_bus_model() -> None:
    """The sensor table's constant (it imports nothing of ``hil.can``) is what the live sender
    paces the IMU's FD frame by: its DBC length, at the bus model's bit rates."""
    from hil.can.busload import frame_bits
    from hil.can.codec import ImuCanCodec
    from hil.sensor_table import CAN_FRAME_TIME_NS, IMU_FD_FRAME_TIME_NS

    lay = ImuCanCodec.from_dbc(fd=True).fd_layout
    assert lay.is_fd and lay.length == 32
    assert round(frame_bits(lay.length, fd=True, brs=lay.brs).seconds() * 1e9) == IMU_FD_FRAME_TIME_NS
    assert round(frame_bits(8).seconds() * 1e9) == CAN_FRAME_TIME_NS
