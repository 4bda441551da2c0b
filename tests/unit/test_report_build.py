"""hil report: metrics from a synthetic session with known errors, and graceful degradation.

GIVEN small sessions written with the real ``SessionWriter`` (truth, two estimators with known
offsets, GNSS, synced stamps with a known error, CAN frames, a scenario with a fault)
WHEN ``build_report`` runs
THEN the numbers in the report are the ones put in, and missing parts become notes.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest

from hil.can.busload import frame_bits
from hil.cli import main
from hil.messages import (
    CanFrame,
    CaptureTruth,
    Event,
    GnssFix,
    ImuSample,
    Message,
    NavSolution,
    RunInfo,
    ServiceStatus,
    Truth,
    counts,
    encode,
)
from hil.progress import Progress
from hil.record.mcapio import RecordingError, SessionWriter
from hil.report.build import build_report
from hil.report.data import load
from hil.report.metrics import quat_mul

SCENARIO = """
name = "synthetic"
seed = 1
duration_s = 20
[origin]
lat_deg = 45.0
lon_deg = 7.0
alt_m = 100.0
[initial]
speed_mps = 10.0
[[segment]]
kind = "hold"
duration_s = 20
[[event]]
kind = "gnss_outage"
t_start_s = 5.0
t_end_s = 8.0
"""
SYNC_ERR_NS = 2_000  # synced stamp - true capture, every IMU sample
OFFSET_M = (3.0, 4.0, 0.0)  # "good" estimator's constant position error: 5 m horizontal


def _quat_z(angle_rad: float) -> list[float]:
    return [math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2)]


def write_session(
    path: Path,
    *,
    truth: bool = True,
    gnss: bool = True,
    can: bool = True,
    drop_nav_seq: int | None = None,
    duration_s: float = 20.0,
) -> Path:
    w = SessionWriter(path, chunk_size=64 * 1024)
    seqs: dict[str, int] = {}

    def put(key: str, msg: Message) -> None:
        w.write(
            key, type(msg), encode(msg), log_time_ns=msg.stamp_ns, publish_time_ns=msg.stamp_ns, seq=msg.seq
        )

    def nxt(key: str) -> int:
        seqs[key] = seqs.get(key, -1) + 1
        return seqs[key]

    k = "hil/t"
    put(
        f"{k}/run",
        RunInfo(
            seq=0,
            stamp_ns=0,
            rig="t",
            start_epoch_ns=0,
            speed=1.0,
            scenario="synthetic",
            scenario_sha256="x",
            seed=1,
            duration_s=duration_s,
            origin_lat_deg=45.0,
            origin_lon_deg=7.0,
            origin_alt_m=100.0,
            scenario_toml=SCENARIO,
        ),
    )
    q_truth = _quat_z(0.3)
    q_bad = quat_mul(np.array([_quat_z(math.radians(2.0))]), np.array([q_truth]))[0].tolist()
    for i in range(int(duration_s * 100) + 1):  # truth 100 Hz, moving north at 10 m/s
        t = i * 10_000_000
        if truth:
            put(
                f"{k}/truth",
                Truth(
                    seq=nxt("truth"),
                    stamp_ns=t,
                    lat_deg=45.0,
                    lon_deg=7.0,
                    alt_m=100.0,
                    pos_ned_m=[10.0 * t * 1e-9, 0.0, 0.0],
                    vel_ned_mps=[10.0, 0.0, 0.0],
                    q_nb=q_truth,
                    f_b_mps2=[0.0, 0.0, -9.8],
                    w_ib_b_radps=[0.0, 0.0, 0.0],
                ),
            )
        if i % 2 == 1:  # nav at 50 Hz, between truth samples
            tn = t + 5_000_000
            north = 10.0 * tn * 1e-9
            for est, off, q, dv in (("good", OFFSET_M, q_truth, 0.0), ("bad", (0.0, 0.0, 0.0), q_bad, 1.0)):
                s = nxt(est)
                if est == "good" and drop_nav_seq is not None and s == drop_nav_seq:
                    continue
                put(
                    f"{k}/nav/{est}",
                    NavSolution(
                        seq=s,
                        stamp_ns=tn,
                        estimator=est,
                        pos_ned_m=[north + off[0], off[1], off[2]],
                        vel_ned_mps=[10.0 + dv, 0.0, 0.0],
                        q_nb=q,
                        lat_deg=45.0,
                        lon_deg=7.0,
                        alt_m=100.0,
                    ),
                )
        if i % 100 == 0 and gnss and not 5.0 <= t * 1e-9 < 8.0:
            fix = GnssFix(
                seq=nxt("gnss"),
                stamp_ns=t + 1000,
                device_stamp_ns=t,
                rx_stamp_ns=t + 1000,
                lat_deg=45.0,
                lon_deg=7.0,
                alt_m=100.0,
                pos_ned_m=[10.0 * t * 1e-9, 0.0, 0.0],
                vel_ned_mps=[10.0, 0.0, 0.0],
                pos_sigma_m=[1.0, 1.0, 1.0],
                vel_sigma_mps=[0.1, 0.1, 0.1],
                fix_type=3,
                num_sats=10,
                hdop=0.9,
            )
            put(f"{k}/sensor/gnss", fix)
        if i % 4 == 0:  # an "IMU" at 25 Hz with known sync error, 3 classic 8-byte frames each
            s = nxt("imu")
            put(f"{k}/capture/imu", CaptureTruth(seq=s, stamp_ns=t, sensor="imu", true_stamp_ns=t))
            put(
                f"{k}/synced/imu",
                ImuSample(
                    seq=s,
                    stamp_ns=t + SYNC_ERR_NS,
                    device_stamp_ns=t,
                    rx_stamp_ns=t,
                    dt_ns=40_000_000,
                    dtheta_b_rad=[0.0, 0.0, 0.0],
                    dvel_b_mps=[0.0, 0.0, -0.4],
                ),
            )
            if can:
                for j in range(3):
                    put(
                        f"{k}/can/vcan0",
                        CanFrame(
                            seq=nxt("can"),
                            stamp_ns=t + j * 150_000,
                            channel="vcan0",
                            arbitration_id=0x100 + j,
                            data_hex="00" * 8,
                        ),
                    )
        if i % 100 == 50:
            put(
                f"{k}/status/imu_emulator",
                ServiceStatus(
                    seq=nxt("st"),
                    stamp_ns=t,
                    service="imu_emulator",
                    state="running",
                    pid=1,
                    uptime_s=t * 1e-9,
                    counters=counts({"bus_load_permille": 7}),
                ),
            )
    put(f"{k}/event/fusion", Event(seq=0, stamp_ns=12_000_000_000, kind="service_restart", source="fusion"))
    w.close()
    return path


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_session(tmp_path_factory.mktemp("rep") / "s.mcap", drop_nav_seq=100)


def test_report_numbers_match_what_was_put_in(session: Path, tmp_path: Path) -> None:
    res = build_report(session, tmp_path / "out")
    stats = {s.name: s for s in res.stats}
    assert stats["good"].horiz.rms == pytest.approx(5.0, abs=1e-6)
    assert stats["good"].horiz.max == pytest.approx(5.0, abs=1e-6)
    assert stats["good"].vel.rms == pytest.approx(0.0, abs=1e-9)
    assert stats["good"].att.max == pytest.approx(0.0, abs=1e-4)
    assert stats["bad"].horiz.rms == pytest.approx(0.0, abs=1e-6)
    assert stats["bad"].vel.rms == pytest.approx(1.0, abs=1e-9)
    assert stats["bad"].att.rms == pytest.approx(2.0, abs=1e-6)  # a 2° yaw offset
    assert stats["good"].convergence_s is not None and stats["good"].convergence_s < 0.1
    page = res.html_path.read_text()
    assert "gnss_outage 5–8 s" in page
    assert "service_restart" in page
    assert {p.name for p in res.pngs} == {
        "trajectory.png",
        "errors.png",
        "errors_ned.png",
        "timesync.png",
        "can_load.png",
    }
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in res.pngs)
    # self-contained: images inline, nothing fetched
    assert page.count("data:image/png;base64,") == 5
    assert "http://" not in page and "https://" not in page and "<script" not in page


def test_report_timesync_loss_and_can_load(session: Path) -> None:
    d = load(session)
    assert set(d.sync_err_ns) == {"imu"}
    assert np.all(d.sync_err_ns["imu"] == SYNC_ERR_NS)
    topics = {t.topic: t for t in d.topics}
    assert topics["hil/t/nav/good"].missing == 1  # the dropped seq
    assert topics["hil/t/nav/bad"].missing == 0
    assert topics["hil/t/nav/good"].loss_pct == pytest.approx(100 / 1000, rel=1e-6)  # 1 of 1000 solutions
    # 25 samples/s x 3 classic 8-byte frames, worst-case stuffing, at 1 Mbit/s
    _t, load_ = d.can_load["vcan0"]
    expect = 75 * frame_bits(8).seconds()
    assert np.allclose(load_, expect)
    assert d.status_load["imu_emulator"][1][0] == pytest.approx(0.007)


def test_report_degrades_to_notes(tmp_path: Path) -> None:
    p = write_session(tmp_path / "bare.mcap", truth=False, gnss=False, can=False, duration_s=4.0)
    res = build_report(p, tmp_path / "out")
    text = " ".join(res.notes)
    assert "no truth" in text
    assert res.stats == []
    page = res.html_path.read_text()
    assert "no GNSS fixes" in page
    # no frames, but the emulator's own bus-load counter is still reported
    assert "imu_emulator (status)" in page and "(from frames)" not in page


def test_report_on_truncated_file(session: Path, tmp_path: Path) -> None:
    data = session.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    res = build_report(cut, tmp_path / "out")
    assert any("truncated" in n for n in res.notes)
    assert res.stats and res.html_path.is_file()
    full = load(session)
    part = load(cut)
    assert 0 < part.messages < full.messages


def test_report_cli_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    assert main(["report", str(junk), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not an MCAP file" in err[0]
    assert main(["report", str(tmp_path / "missing.mcap")]) == 2


def test_report_on_golden_sim_recording(tmp_path: Path) -> None:
    golden = Path(__file__).resolve().parents[1] / "replay" / "golden" / "straight_level_4s.mcap"
    if not golden.is_file():
        pytest.skip(f"no golden recording at {golden}")
    res = build_report(golden, tmp_path / "g")
    names = {s.name for s in res.stats}
    assert {"ekf15", "ins"} <= names
    ekf = next(s for s in res.stats if s.name == "ekf15")
    assert 0 < ekf.horiz.rms < 50
    d = load(golden)
    assert set(d.sync_err_ns) == {"imu", "gnss"}
    assert d.can_load and 0 < float(np.mean(d.can_load["vcan0"][1])) < 1


def test_progress_silent_off_tty_and_draws_on_tty() -> None:
    quiet = io.StringIO()
    with Progress("x", total=10, stream=quiet) as bar:  # StringIO is not a TTY
        bar.update(5)
    assert quiet.getvalue() == ""
    loud = io.StringIO()
    with Progress("sim", total=10, unit="s", stream=loud, enabled=True, min_interval_s=0) as bar:
        bar.update(5)
        bar.update(10)
    out = loud.getvalue()
    assert out.startswith("\rsim [") and "50.0%" in out and "100.0%" in out and out.endswith("\n")


def test_an_unwritable_report_directory_is_one_line_before_any_reading(tmp_path: Path) -> None:
    in_the_way = tmp_path / "a_file"
    in_the_way.write_text("x")
    with pytest.raises(RecordingError, match=r"cannot write the report under .*a_file/rep: Not a directory"):
        build_report(tmp_path / "no_such_recording.mcap", in_the_way / "rep")


def test_a_run_shorter_than_its_scenario_shows_no_fault_it_never_reached(tmp_path: Path) -> None:
    """A 20 s car_drive: its scenario's faults at 150-480 s were listed and drawn as if they had
    happened. They are left out, with a note saying how many and from when."""
    from hil.report.metrics import fault_windows
    from tests.conftest import run_hil

    rec = tmp_path / "car.mcap"
    proc = run_hil("sim", "--scenario", "car_drive", "--duration", "20", "--record", str(rec), "--quiet")
    assert proc.returncode == 0, proc.stderr
    windows, notes = fault_windows(load(rec))
    assert all(w.t0_s < 20.0 for w in windows), windows
    assert any("start after the run's 20 s (from 150 s): not in this run" in n for n in notes), notes
