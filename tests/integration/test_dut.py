"""The reference device under test (examples/dut/navbox.py) sees the rig only through its wires.

Quick tests: the unit imports nothing from ``hil``; the IMU frames the rig sends decode in the unit
to the same increments, the unit's own frames decode in the rig (``hil.can.dut``, with
examples/dut/navbox.toml) and in cantools to the values it sent; the receiver's bytes the rig
writes (NMEA, UBX) decode in the unit, and garbled bytes are counted, never turned into a fix.
Slow test: ``hil up --dut examples/dut/navbox.toml --dut-emulator`` runs the unit as its own
process on the run's CAN bus and its own GNSS line, and the rig scores the solution it decoded.
"""

from __future__ import annotations

import ast
import importlib.util
import math
import os
import random
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import cantools
import numpy as np
import pytest

from hil.can.codec import ImuCanCodec
from hil.can.dut import DutNavDecoder
from hil.can.dut_emulator import load_dut
from hil.messages import ServiceStatus, decode
from hil.record.info import estimator_errors
from hil.record.mcapio import read_session
from hil.wire.base import ReceiverEpoch
from hil.wire.gnss_time import utc_ns_to_gps_ns
from hil.wire.nmea import NmeaProtocol
from hil.wire.ubx import UbxProtocol
from tests.conftest import REPO, hil_cmd

UNIT = REPO / "examples/dut/navbox.py"
MAPPING = REPO / "examples/dut/navbox.toml"
# what a unit may use: the standard library and these (docs/dut.md)
ALLOWED = {"numpy", "can", "cantools", "serial", "pynmeagps", "pyubx2"}


@pytest.fixture(scope="module")
def navbox() -> ModuleType:
    """The unit's source as a module (it is a script, not part of any package)."""
    spec = importlib.util.spec_from_file_location("navbox_unit", UNIT)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["navbox_unit"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_the_unit_imports_nothing_from_hil() -> None:
    # every import in the source, at any depth, is the standard library or an allowed package
    tree = ast.parse(UNIT.read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "a relative import"
            roots.add(str(node.module).split(".")[0])
    assert roots, "no import found: the check looked at nothing"
    assert not {r for r in roots if r not in sys.stdlib_module_names and r not in ALLOWED}, roots
    assert "hil" not in roots
    # ... and it runs with hil made unimportable
    code = (
        "import runpy, sys; sys.modules['hil'] = None; sys.argv = [sys.argv[1], '--help']; "
        "runpy.run_path(sys.argv[0], run_name='__main__')"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(UNIT)], capture_output=True, text=True, timeout=120, cwd=REPO
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "--gnss" in proc.stdout and "--can-interface" in proc.stdout


@pytest.mark.parametrize("fd", [False, True])
def test_imu_frames_from_the_rig_decode_in_the_unit(navbox: ModuleType, fd: bool) -> None:
    """The rig's encoder (hil.can.codec) in, the unit's decoder (cantools + its own E2E check) out."""
    codec = ImuCanCodec.from_dbc(fd=fd)
    unit = navbox.ImuDecoder(navbox.DEFAULT_IMU_DBC)
    rng = np.random.default_rng(7)
    sent, got = [], []
    for k in range(60):
        dth, dv = rng.normal(0, 1e-3, 3), rng.normal(0, 0.02, 3)
        sent.append((k * 2_500_000 + 123, dth, dv))
        for frame in codec.encode_sample(
            device_stamp_ns=k * 2_500_000 + 123, dtheta_b_rad=dth, dvel_b_mps=dv
        ):
            frame.timestamp = 1000.0 + k
            sample = unit.feed(frame)
            if sample is not None:
                got.append(sample)
    assert len(got) == len(sent)
    for (t_ns, dth, dv), s in zip(sent, got, strict=True):
        assert s.device_ns == t_ns
        assert np.allclose(s.dtheta_rad, dth, atol=codec.dtheta_lsb_rad / 2 + 1e-15)
        assert np.allclose(s.dvel_mps, dv, atol=codec.dvel_lsb_mps / 2 + 1e-12)
    assert unit.counts["bad_crc"] == unit.counts["lost_frames"] == unit.counts["incomplete"] == 0
    # a corrupted frame is refused by its CRC
    zero = {"dtheta_b_rad": [0.0, 0.0, 0.0], "dvel_b_mps": [0.0, 0.0, 0.0]}
    bad = codec.encode_sample(device_stamp_ns=10**9, **zero)[-1]
    bad.data = bytearray(bad.data)
    bad.data[3] ^= 0x10
    assert unit.feed(bad) is None and unit.counts["bad_crc"] == 1
    # a lost frame: its sample is dropped (classic: incomplete), the gap counted, the next one whole
    frames = codec.encode_sample(device_stamp_ns=10**9 + 2_500_000, **zero)
    kept = [] if fd else [f for f in frames if f.arbitration_id != 0x102]  # FD: the frame is the sample
    assert all(unit.feed(f) is None for f in kept)
    frames = codec.encode_sample(device_stamp_ns=10**9 + 5_000_000, **zero)
    assert [unit.feed(f) for f in frames][-1] is not None
    assert unit.counts["lost_frames"] >= 1
    assert unit.counts["incomplete"] == (0 if fd else 1)


def _solution(**over: float) -> dict[str, object]:
    sol: dict[str, object] = {
        "lat_deg": 50.4500123,
        "lon_deg": 30.5200456,
        "alt_m": 312.345,
        "vel_ned_mps": (49.87, -1.23, 0.45),
        "sigma_h_m": 2.5,
        "sigma_v_m": 4.25,
        "roll_deg": 1.5,
        "pitch_deg": -2.25,
        "heading_deg": 359.5,
    }
    sol.update(over)
    return sol


def test_the_units_frames_decode_in_cantools_and_in_the_rig(navbox: ModuleType) -> None:
    """The unit's encoder round trip: cantools with navbox.dbc, and the rig's decoder with the
    mapping (Up -> Down sign, the solution closed by NAV_Attitude), within one LSB."""
    frames = navbox.NavEncoder(navbox.DEFAULT_NAV_DBC).frames(_solution())
    db = cantools.database.load_file(str(navbox.DEFAULT_NAV_DBC))
    assert [db.get_message_by_frame_id(f.arbitration_id).name for f in frames][-1] == "NAV_Attitude"
    values = {k: v for f in frames for k, v in db.decode_message(f.arbitration_id, bytes(f.data)).items()}
    assert values["Latitude"] == pytest.approx(50.4500123, abs=1e-7)
    assert values["Longitude"] == pytest.approx(30.5200456, abs=1e-7)
    assert values["Altitude"] == pytest.approx(312.345, abs=1e-3)
    assert values["VelUp"] == pytest.approx(-0.45, abs=0.01)
    assert values["Heading"] == pytest.approx(359.5, abs=0.01)
    assert values["PosSigmaH"] == pytest.approx(2.5, abs=0.01)
    dbc, mapping = load_dut(MAPPING)
    rig = DutNavDecoder(dbc, mapping, 50.45, 30.52, 300.0)
    sols = [rig.feed(f, 1_000_000 + i) for i, f in enumerate(frames)]
    assert sols[:-1] == [None] * (len(frames) - 1) and sols[-1] is not None
    sol = sols[-1]
    assert sol.estimator == "dut_navbox" and rig.counters["solutions"] == 1
    assert (sol.lat_deg, sol.lon_deg, sol.alt_m) == pytest.approx((50.4500123, 30.5200456, 312.345), abs=1e-6)
    assert sol.vel_ned_mps == pytest.approx([49.87, -1.23, 0.45], abs=0.01)
    assert sol.pos_sigma_m == pytest.approx([2.5, 2.5, 4.25], abs=0.01)
    # a value beyond the DBC's range goes out at its limit, not as an exception or a wrapped value
    wild = navbox.NavEncoder(navbox.DEFAULT_NAV_DBC).frames(_solution(sigma_h_m=1e6, alt_m=math.nan))
    values = {k: v for f in wild for k, v in db.decode_message(f.arbitration_id, bytes(f.data)).items()}
    assert values["PosSigmaH"] == pytest.approx(655.0) and values["Altitude"] == 0.0


def _epochs(n: int) -> bytes:
    out = b""
    for k in range(n):
        e = ReceiverEpoch(
            gps_time_ns=utc_ns_to_gps_ns(1_767_225_600_000_000_000 + k * 100_000_000),
            lat_deg=50.45, lon_deg=30.52, alt_m=300.0, vel_ned_mps=(50.0, 1.0, -0.5),
            pos_sigma_ned_m=(2.0, 2.0, 3.0), vel_sigma_mps=(0.2, 0.2, 0.2),
            fix_type=3, num_sats=12, hdop=0.8, pdop=1.2, vdop=1.0,
        )  # fmt: skip
        out += NmeaProtocol().encode_epoch(e) + UbxProtocol().encode_epoch(e)
    return out


def test_the_receivers_bytes_decode_in_the_unit_and_garbage_never_becomes_a_fix(navbox: ModuleType) -> None:
    clean = navbox.GnssParser()
    fixes = clean.feed(_epochs(20), 0.0)
    # one fix per epoch from NMEA (RMC + GGA) and one from UBX NAV-PVT, at the epoch's UTC time
    assert sorted({f.source for f in fixes}) == ["nmea", "ubx"] and len(fixes) == 40
    for f in fixes:
        assert (f.lat_deg, f.lon_deg, f.alt_m) == pytest.approx((50.45, 30.52, 300.0), abs=1e-6)
        assert f.vel_ned_mps[:2] == pytest.approx([50.0, 1.0], abs=0.01)
    ubx = [f for f in fixes if f.source == "ubx"]
    assert [round(f.t_valid_s - 1_767_225_600, 3) for f in ubx] == [round(0.1 * k, 3) for k in range(20)]
    assert not clean.counts["bad_messages"] and not clean.counts["garbage_bytes"]
    # flipped bytes and cut-out stretches, fed a few bytes at a time: counted, and every fix that
    # still comes out is a true one (checksums)
    rng = random.Random(3)
    bad = bytearray(_epochs(40))
    for _ in range(80):
        bad[rng.randrange(len(bad))] = rng.randrange(256)
    for _ in range(15):
        i = rng.randrange(len(bad))
        del bad[i : i + rng.randrange(1, 40)]
    parser = navbox.GnssParser()
    fixes = [f for i in range(0, len(bad), 7) for f in parser.feed(bytes(bad[i : i + 7]), 0.0)]
    assert parser.counts["bad_messages"] > 0 and parser.counts["garbage_bytes"] > 0
    assert 0 < len(fixes) < 80
    assert all(abs(f.lat_deg - 50.45) < 1e-6 and abs(f.alt_m - 300.0) < 1e-3 for f in fixes)


# ---------------------------------------------------------------------------------------------
# the unit live, under hil up

RIG = "duttest"
DURATION_S = 20


def _unit_pids(marker: str) -> list[int]:
    """Processes whose command line names ``marker`` (this run's logs directory)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if marker in cmd and "navbox.py" in cmd:
                pids.append(int(d.name))
    return pids


@pytest.mark.slow
def test_hil_up_runs_the_unit_on_the_wires_and_scores_it(tmp_path: Path) -> None:
    record = tmp_path / "dut.mcap"
    logs = record.with_suffix(".logs")
    up = subprocess.Popen(
        hil_cmd(
            "up", "--dut", str(MAPPING), "--dut-emulator", "--duration", str(DURATION_S),
            "--quiet", "--rig", RIG, "--record", str(record),
            "--estimators", "comp1",  # the rig's own estimators are not under test: leave the CPU to the unit
        ),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        out, _ = up.communicate(timeout=300)
    finally:
        if up.poll() is None:
            up.terminate()
            try:
                up.wait(timeout=60)
            except subprocess.TimeoutExpired:
                up.kill()
                up.wait()
        for pid in _unit_pids(str(logs)):  # never leave the unit behind, even on a failure
            os.kill(pid, 9)
    assert up.returncode == 0, out[-4000:]
    assert "FAILED" not in out
    assert not _unit_pids(str(logs)), "the unit outlived hil up"
    # the unit ran as its own process on the wires: its log says which, and what it took in
    log = (logs / "dut.log").read_text()
    assert f"GNSS line {logs / 'dut_gnss.tty'} open" in log, log[-3000:]
    final = dict(kv.split("=") for kv in log.split("stopped: ")[-1].split())
    assert int(final["imu_samples"]) > 0.5 * 400 * DURATION_S, final
    assert int(final["fixes_used"]) > 0.5 * 10 * DURATION_S and int(final["solutions"]) > 0, final
    assert int(final["imu_bad_crc"]) == int(final["imu_lost_frames"]) == 0, final
    s = read_session(record)
    # the rig decoded the unit's frames off the bus (recorded raw) into nav/dut_navbox at ~10 Hz
    raw = [r.decode() for r in s.by_topic(f"hil/{RIG}/can/vcan0")]
    closing = [f for f in raw if f.arbitration_id == 0x503]  # NAV_Attitude closes a solution
    sols = [r.decode() for r in s.by_topic(f"hil/{RIG}/nav/dut_navbox")]
    bridge = [decode(ServiceStatus, r.payload) for r in s.by_topic(f"hil/{RIG}/status/can_bridge")][-1]
    rejected = bridge.counter_map().get("rejected.dut", 0)  # a starved bridge may see a frame go stale
    assert len(sols) + rejected == len(closing) and rejected <= max(3, 0.05 * len(closing)), (
        bridge.counter_map()
    )
    assert len(sols) >= 50
    t = np.array([x.stamp_ns for x in sols]) * 1e-9
    assert 0.08 < float(np.median(np.diff(t))) < 0.12  # the unit's 10 Hz, by the rig's stamps
    assert len(sols) >= 0.6 * 10 * (t[-1] - t[0])  # and it kept it up
    # scored against truth like any estimator: GNSS at 20 m (1 sigma per axis) smoothed by the
    # unit's filter; measured on a loaded 2-core machine: RMS 5-9 m, 95 % 8-20 m (docs/dut.md)
    err = estimator_errors(s)["dut_navbox"]
    assert err["rms_m"] < 15.0 and err["p95_m"] < 30.0, err
