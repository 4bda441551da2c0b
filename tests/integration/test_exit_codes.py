"""Exit codes tell the truth (issue 18.5), as a user meets them on a real rig.

- A recorder that cannot write (a disk that fills up mid-run: a real 1 MB tmpfs, which holds the
  service logs too) makes ``hil up`` exit non-zero, and the reason is on its console -- at once
  and in the summary -- not only in logs on the full disk.
- A recording directory that cannot be written at all is refused up front: exit 2, one line.
- A restarted service that never becomes ready (SIGSTOPped right after its restart) is a failure
  once ``--restart-deadline`` has passed; the CPU table shows no negative figure after restarts
  and has the supervisor's own row.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO, hil_cmd, run_hil

pytestmark = pytest.mark.slow


def _mount_tmpfs(where: Path, *options: str) -> None:
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", ",".join(options), "tmpfs", str(where)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    if r.returncode != 0:
        pytest.skip(
            f"cannot mount a tmpfs here ({r.stderr.strip() or 'not root'}): a real small disk is needed"
        )


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    where = tmp_path / "small"
    _mount_tmpfs(where, "size=512k")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=30)


@pytest.fixture
def read_only_dir(tmp_path: Path) -> Iterator[Path]:
    where = tmp_path / "ro"
    if os.getuid() != 0:  # an ordinary user cannot write into a 0500 directory
        where.mkdir(mode=0o500)
        yield where
        where.chmod(0o700)
        return
    _mount_tmpfs(where, "ro", "size=1m")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=30)


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:  # a failed assertion must not leave a rig running
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(30)


def test_a_disk_that_fills_up_fails_the_run_with_the_reason_on_the_console(
    small_disk: Path, spawn: list[subprocess.Popen[str]]
) -> None:
    rec = small_disk / "run.mcap"  # its logs go beside it: <stem>.logs on the same full disk
    p = subprocess.Popen(
        hil_cmd("up", "--duration", "10", "--record", str(rec), "--quiet", "--rig", f"full{os.getpid()}"),
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    spawn.append(p)
    out, err = p.communicate(timeout=240)
    assert p.returncode not in (0, None), out[-2000:] + err[-2000:]
    # the reason, at once (as it happened) and in the summary; from the recorder's own status
    assert re.search(r"recorder is DEGRADED: writing .*run\.mcap failed: No space left on device", err), err
    assert re.search(r"FAILED: recorder degraded: .*No space left on device", err), err
    assert "Traceback" not in out + err
    assert os.statvfs(small_disk).f_bavail == 0  # the disk really was full


def test_an_unwritable_recording_directory_is_refused_before_anything_starts(read_only_dir: Path) -> None:
    rec = read_only_dir / "sub" / "run.mcap"
    proc = run_hil("up", "--duration", "5", "--record", str(rec), "--quiet", timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "cannot write in" in lines[0] and str(rec.parent) in lines[0], proc.stderr
    assert "hil up: rig" not in proc.stdout


def _child_pid(parent: int, service: str, not_pid: int = -1) -> int | None:
    try:
        kids = Path(f"/proc/{parent}/task/{parent}/children").read_text().split()
    except OSError:
        return None
    for k in kids:
        try:
            cmd = Path(f"/proc/{k}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"service" in cmd and service.encode() in cmd and int(k) != not_pid:
            return int(k)
    return None


def _wait_pid(parent: int, service: str, not_pid: int = -1, timeout: float = 120) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pid = _child_pid(parent, service, not_pid)
        if pid is not None:
            return pid
        time.sleep(0.02)
    raise AssertionError(f"no {service} process under {parent}")


def test_a_restart_that_never_becomes_ready_fails_the_run(
    tmp_path: Path, spawn: list[subprocess.Popen[str]]
) -> None:
    # GIVEN a run that allows one restart per service, with a 6 s readiness deadline, in which
    # the fusion is killed by the scenario at rig time 4 s
    scen = tmp_path / "kill.toml"
    scen.write_text(
        'duration_s = 60.0\n[[event]]\nkind = "kill_service"\nt_start_s = 4.0\nservice = "fusion"\n'
    )
    p = subprocess.Popen(
        hil_cmd("up", "--scenario", str(scen), "--duration", "16", "--restart", "1", "--restart-deadline", "6",
                "--record", str(tmp_path / "r.mcap"), "--quiet", "--rig", f"stuck{os.getpid()}"),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    spawn.append(p)
    first = _wait_pid(p.pid, "fusion")
    # WHEN its replacement is stopped as soon as it exists (it never gets to "running")
    second = _wait_pid(p.pid, "fusion", not_pid=first)
    os.kill(second, signal.SIGSTOP)
    out, err = p.communicate(timeout=240)
    # THEN the run fails, saying which service was down and why
    assert p.returncode == 1, out[-2000:] + err[-2000:]
    assert f"fusion was restarted (pid {second}) but is not ready after 6 s" in err, err[-3000:]
    assert f"fusion died (killed by signal 9); restarted (1/1) as pid {second}" in out
    # and the CPU table has no negative figure, fusion's two lives and the supervisor included
    rows = dict(re.findall(r"^  (\w+)\s+(-?[\d.]+) s\s+-?[\d.]+ %\s+\d+ wake-ups/s$", out, flags=re.M))
    assert {"fusion", "supervisor", "recorder"} <= set(rows), out
    assert all(float(v) >= 0 for v in rows.values()), rows
    assert float(rows["fusion"]) > 0 and float(rows["supervisor"]) > 0, rows


def test_a_run_whose_imu_never_reaches_the_bridge_fails_with_the_reason(tmp_path: Path) -> None:
    """Every service stays up, yet the CAN bridge decodes not one IMU sample (the bus is off for
    the whole run): no navigation came out, so ``hil up`` must not exit 0 (it once did, when a
    Zenoh link between the emulator and the bridge never formed)."""
    scenario = tmp_path / "silent_imu.toml"
    text = (REPO / "hil/scenarios/straight_level.toml").read_text()
    scenario.write_text(
        text.replace('name = "straight_level"', 'name = "silent_imu"')
        + '\n[[event]]\nkind = "can_bus_off"\nt_start_s = 0.0\nt_end_s = 3600.0\n'
    )
    out = tmp_path / "silent.mcap"
    r = run_hil(
        "up", "--scenario", str(scenario), "--duration", "5", "--record", str(out), "--quiet",
        "--rig", f"silent{os.getpid()}", timeout=240,
    )  # fmt: skip
    assert r.returncode != 0, r.stdout[-3000:]
    said = r.stdout + r.stderr
    assert "can_bridge decoded no IMU sample" in said, said[-3000:]
    assert "Traceback" not in said
    assert out.exists()  # what was recorded is kept


def test_hil_sim_on_a_disk_that_fills_up_says_which_file_in_one_line(
    small_disk: Path, tmp_path: Path
) -> None:
    """`hil sim` that runs out of room (a real 512 KiB tmpfs; /dev/full at once) said
    "hil: OSError: [Errno 28] No space left on device", naming no file; a --record under a
    regular file said "File exists". Each is one line naming the path, exit 2, and what was
    flushed before the disk filled reads."""
    rec = small_disk / "sim.mcap"
    proc = run_hil("sim", "--duration", "20", "--record", str(rec), "--quiet", timeout=300)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert (
        lines[-1]
        == f"hil: writing {rec} failed: No space left on device; what was flushed before stays readable"
    )
    assert run_hil("info", str(rec), "--no-accuracy", timeout=120).returncode == 0
    proc = run_hil("sim", "--duration", "1", "--record", "/dev/full", "--quiet", timeout=120)
    assert proc.returncode == 2 and proc.stderr.strip().startswith(
        "hil: writing /dev/full failed: No space"
    ), proc.stderr
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    proc = run_hil("sim", "--duration", "1", "--record", str(blocker / "y.mcap"), "--quiet", timeout=120)
    assert proc.returncode == 2 and f"{blocker} is a file, not a directory" in proc.stderr, proc.stderr
