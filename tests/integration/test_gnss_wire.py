"""The GNSS receiver on a real wire, judged by readers nobody here wrote: gpsd reads the
pseudo-terminal of a live ``hil up`` and reports 3-D fixes at the configured rate near truth;
pyubx2 and pynmeagps read the same line over TCP with valid checksums; the rig's own bridge
decodes it; a recorded line played back onto a pty decodes to the recorded fixes."""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from pyubx2 import NMEA_PROTOCOL, UBX_PROTOCOL, UBXReader

from hil.nav.earth import lla_to_ned
from hil.record.mcapio import read_session
from tests.conftest import REPO, free_port, hil_cmd, run_hil

pytestmark = pytest.mark.slow

RIG = "gwire"
DURATION_S = 14.0


def _require(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        if os.environ.get("HIL_REQUIRE_DOCKER") or os.environ.get("HIL_REQUIRE_GPSD"):
            pytest.fail(f"{tool} is not installed (.ci/run installs gpsd and gpsd-clients)")
        pytest.skip(f"{tool} is not installed (apt-get install gpsd gpsd-clients)")
    return path


def _terminate(proc: subprocess.Popen[bytes] | subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class LiveWire:
    """``hil up`` with the receiver on a pty (for gpsd) and on TCP (for pyubx2), NMEA and UBX."""

    def __init__(self, tmp: Path) -> None:
        self.tty = tmp / "gnss0"
        self.tcp_port = free_port()
        self.record = tmp / "wire.mcap"
        self.up = subprocess.Popen(
            hil_cmd(
                "up", "--rig", RIG, "--duration", str(DURATION_S), "--quiet", "--record", str(self.record),
                "--gnss-protocol", "nmea,ubx", "--gnss-serial", str(self.tty),
                "--gnss-tcp", f"127.0.0.1:{self.tcp_port}",
            ),
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip

    def wait_for_line(self, timeout_s: float = 90.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not self.tty.exists():
            assert self.up.poll() is None, self.up.communicate()[0][-3000:]
            assert time.monotonic() < deadline, "hil up never made the receiver's line"
            time.sleep(0.1)

    def finish(self) -> str:
        try:
            out, _ = self.up.communicate(timeout=120)
        finally:
            _terminate(self.up)
        assert self.up.returncode == 0, out[-3000:]
        return out


@pytest.fixture
def live_wire(tmp_path: Path) -> Iterator[LiveWire]:
    rig = LiveWire(tmp_path)
    try:
        yield rig
    finally:
        _terminate(rig.up)


def test_gpsd_and_pyubx2_read_the_live_receiver_and_the_rig_decodes_it(
    live_wire: LiveWire, tmp_path: Path
) -> None:
    gpsd, gpspipe = _require("gpsd"), _require("gpspipe")
    live_wire.wait_for_line()
    port = free_port()
    # gpsd as a user would run it: foreground, no wait for clients, read-only (-b: no
    # reconfiguring the "receiver"), its own port and control socket
    gps = subprocess.Popen(
        [gpsd, "-N", "-n", "-b", "-S", str(port), "-F", str(tmp_path / "gpsd.sock"), str(live_wire.tty)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        # pyubx2 on the TCP copy of the same line: every frame and sentence, checksums validated
        frames = _read_tcp(live_wire.tcp_port, seconds=4.0)
        tpv = _gpspipe_tpv(gpspipe, port, count=30)
    finally:
        _terminate(gps)
    out = live_wire.finish()
    # THEN pyubx2/pynmeagps parsed everything with valid checksums: NAV-PVT at 10 Hz, all six NMEA
    pvt = [m for m in frames if m.identity == "NAV-PVT"]
    assert 30 <= len(pvt) <= 45, len(pvt)  # 4 s at 10 Hz
    assert {"GNRMC", "GNVTG", "GNGGA", "GNGSA", "GNGST", "GNZDA"} <= {m.identity for m in frames}
    assert all(m.fixType == 3 and m.gnssFixOk == 1 for m in pvt)
    # gpsd reported 3-D fixes at the receiver's rate, near the scenario's truth
    s = read_session(live_wire.record)
    truth = [r.decode() for r in s.by_topic(f"hil/{RIG}/truth")]
    run = s.by_topic(f"hil/{RIG}/run")[0].decode()
    fixes3d = [t for t in tpv if t.get("mode") == 3]
    assert len(fixes3d) >= 25, tpv[:3]
    # the rate by the receiver's own time stamps (gpsd reports an epoch once per protocol on the
    # line, so count distinct epochs): no wall-clock figure that a loaded machine could upset
    times = sorted(float(t["_time_s"]) for t in fixes3d)
    epochs = [t for i, t in enumerate(times) if i == 0 or t - times[i - 1] > 0.03]
    rate = (len(epochs) - 1) / (epochs[-1] - epochs[0])
    assert 9.5 < rate < 10.5, epochs
    # ... at the positions the rig's own bridge decoded from the same bytes (the quantised fixes a
    # device sees), which are the truth plus the emulated receiver noise
    origin = np.radians([run.origin_lat_deg, run.origin_lon_deg])
    bridged = {f.device_stamp_ns: f for f in (r.decode() for r in s.by_topic(f"hil/{RIG}/sensor/gnss"))}
    stamps = np.array(sorted(bridged))
    tt = np.array([t.stamp_ns for t in truth]) * 1e-9
    tp = np.array([t.pos_ned_m for t in truth])
    same, noise = [], []
    for f in fixes3d:
        t_dev_ns = round(f["_time_s"] * 1e9) - run.start_epoch_ns
        nearest = int(stamps[np.argmin(np.abs(stamps - t_dev_ns))])
        assert abs(nearest - t_dev_ns) < 10_000_000, (nearest, t_dev_ns)
        ned = np.asarray(lla_to_ned(np.radians(f["lat"]), np.radians(f["lon"]), 0.0, *origin, 0.0)).reshape(3)
        same.append(np.hypot(*(ned[:2] - np.asarray(bridged[nearest].pos_ned_m[:2]))))
        ref = [np.interp(t_dev_ns * 1e-9, tt, tp[:, i]) for i in range(2)]
        noise.append(np.hypot(*(ned[:2] - ref)))
    sigma = bridged[nearest].pos_sigma_m[0]
    assert max(same) < 0.05, same  # gpsd and the rig read the same numbers off the line
    assert np.median(noise) < 2.5 * sigma and max(noise) < 6 * sigma, (sigma, noise)  # truth + noise
    # the rig's own bridge decoded the same line: every epoch, nothing rejected
    counts = s.by_topic(f"hil/{RIG}/status/gnss_bridge")[-1].decode().counter_map()
    assert counts.get("line.ubx.fixes", 0) >= 100 and counts.get("line.nmea.fixes", 0) >= 100, counts
    assert not any(k.startswith("rejected") and v for k, v in counts.items()), counts
    assert "FAILED" not in out


def _read_tcp(port: int, seconds: float) -> list[object]:
    """What a TCP client of the line got in ``seconds``, whole epochs only (it joins mid-stream),
    parsed by pyubx2 with checksums validated: a bad one raises and fails the test."""
    deadline = time.monotonic() + 30.0
    while True:
        try:
            sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
            break
        except OSError:
            assert time.monotonic() < deadline, "the receiver's TCP line never accepted"
            time.sleep(0.2)
    sock.settimeout(60.0)  # the run starts once every service is up
    with sock:
        data = sock.recv(65536)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            data += sock.recv(65536)
    first, last = data.find(b"$GNRMC"), data.rfind(b"$GNRMC")  # an epoch starts with RMC
    assert 0 <= first < last, data[:200]
    reader = UBXReader(
        io.BytesIO(data[first:last]), protfilter=NMEA_PROTOCOL | UBX_PROTOCOL, validate=1, quitonerror=2
    )
    out = []
    for _raw, msg in reader:
        out.append(msg)
    return out


def _gpspipe_tpv(gpspipe: str, port: int, count: int) -> list[dict[str, object]]:
    proc = subprocess.Popen(
        [gpspipe, "-w", f"localhost:{port}"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    tpv: list[dict[str, object]] = []
    try:
        deadline = time.monotonic() + 30.0
        assert proc.stdout is not None
        while len(tpv) < count and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            report = json.loads(line)
            if report.get("class") == "TPV" and "time" in report:
                report["_time_s"] = np.datetime64(report["time"].rstrip("Z"), "ns").astype(np.int64) * 1e-9
                tpv.append(report)
    finally:
        _terminate(proc)
    return tpv


def test_replay_puts_the_recorded_line_back_on_a_pty_and_it_decodes_to_the_recorded_fixes(
    tmp_path: Path,
) -> None:
    from hil.runners.sim import SimOptions, run_sim
    from hil.wire.line import LineDecoder

    # GIVEN a session whose receiver was on an NMEA+UBX line (hil sim: the same nodes)
    rec = tmp_path / "line.mcap"
    run_sim(SimOptions(duration_s=6.0, record=rec, estimators=["comp1"], gnss_protocol=["nmea", "ubx"]))
    recorded = [r.decode() for r in read_session(rec).by_topic("hil/sim/sensor/gnss")]
    # WHEN hil replay plays the recorded bytes onto a pty (5x faster than recorded)
    tty = tmp_path / "replay0"
    proc = subprocess.Popen(
        hil_cmd("replay", str(rec), "--gnss-serial", str(tty), "--topics", "serial/", "--rate", "5", "--no-progress"),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    line = LineDecoder(("nmea", "ubx"))
    fixes = []
    try:
        deadline = time.monotonic() + 60.0
        while not tty.exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0]
            time.sleep(0.05)
        fd = os.open(tty, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            while proc.poll() is None and time.monotonic() < deadline:
                try:
                    fixes += line.feed(os.read(fd, 65536), 0)
                except BlockingIOError:
                    time.sleep(0.01)
                except OSError as err:  # EIO: the replay has closed its end, after we read it all
                    if err.errno != errno.EIO:
                        raise
                    break
            with contextlib.suppress(OSError):
                fixes += line.feed(os.read(fd, 65536), 0)
        finally:
            os.close(fd)
        out, _ = proc.communicate(timeout=30)
    finally:
        _terminate(proc)
    # THEN a device reading that pty gets every recorded epoch, to the recorded numbers
    assert proc.returncode == 0 and "bytes onto the receiver's line" in out, out
    ubx = [f for f in fixes if f.protocol == "ubx"]
    assert len(ubx) >= len(recorded) - 1, (len(ubx), len(recorded))  # the pty may open a moment late
    by_time = {f.gps_time_ns: f for f in ubx}
    run = read_session(rec).by_topic("hil/sim/run")[0].decode()
    from hil.wire.gnss_time import utc_ns_to_gps_ns

    matched = [
        (by_time[g], m)
        for m in recorded
        if (g := utc_ns_to_gps_ns(run.start_epoch_ns + m.device_stamp_ns)) in by_time
    ]
    assert len(matched) >= len(recorded) - 1
    assert all(abs(f.lat_deg - m.lat_deg) < 1e-7 and abs(f.lon_deg - m.lon_deg) < 1e-7 for f, m in matched)
    assert line.counters["garbage_bytes"] == 0


@pytest.mark.parametrize(
    ("path", "why"),
    [
        ("{tmp}/no/such/dir/gnss0", "No such file or directory"),
        ("/sys/gnss0", "cannot make a link in /sys"),  # root passes os.access here; the link fails
        ("{tmp}/taken", "exists and is not a link"),
    ],
)
def test_a_gnss_line_path_that_cannot_be_made_is_one_line_at_start(
    tmp_path: Path, path: str, why: str
) -> None:
    (tmp_path / "taken").write_text("")
    proc = run_hil("up", "--gnss-serial", path.format(tmp=tmp_path), "--duration", "2", timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and why in lines[0] and "--gnss-serial" in lines[0], proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert "hil up: rig" not in proc.stdout, "refused before any process started"
