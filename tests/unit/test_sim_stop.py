"""``hil sim`` stopped before its duration (Ctrl-C, SIGTERM, ``SimOptions.stop``) ends the run at
a window boundary as its end would: the file is whole up to there, says where it stopped, and
reruns bit for bit; what came before the stop is what the full run recorded."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.record.mcapio import read_session
from hil.record.rerun import rerun
from hil.runners.sim import SimOptions, run_sim

REPO = Path(__file__).resolve().parents[2]


def _stop_after(windows: int) -> tuple[list[int], object]:
    """A ``stop`` that says yes from its ``windows + 1``-th question on (asked once a window)."""
    asked = [0]

    def stop() -> bool:
        asked[0] += 1
        return asked[0] > windows

    return asked, stop


def _sim(path: Path, duration_s: float, stop: object = None, worker: bool | None = None) -> object:
    opts = SimOptions(scenario="straight_level", duration_s=duration_s, record=path, fusion_worker=worker)
    if stop is not None:
        opts.stop = stop  # type: ignore[assignment]
    return run_sim(opts)


def test_a_stopped_run_is_whole_up_to_the_stop_and_matches_the_full_run_before_it(tmp_path: Path) -> None:
    full, stopped, alone = tmp_path / "full.mcap", tmp_path / "stopped.mcap", tmp_path / "alone.mcap"
    _sim(full, 12.0)
    _, stop = _stop_after(6)
    res = _sim(stopped, 12.0, stop)
    assert res.stopped_at_s == 7.0  # type: ignore[attr-defined]  # asked at 1..7 s, stopped at the 7th
    assert "stopped at 7 s of 12 s of rig time" in res.summary  # type: ignore[attr-defined]
    _, stop_alone = _stop_after(6)
    _sim(alone, 12.0, stop_alone, worker=False)
    assert stopped.read_bytes() == alone.read_bytes()  # with and without the worker: the same file

    s, f = read_session(stopped), read_session(full)
    assert not s.truncated  # closed: summary, index, footer
    assert s.meta("completeness", "stopped_at_s") == 7.0
    assert s.meta("completeness", "replay_ready") is True
    assert f.meta("completeness", "stopped_at_s") is None
    last_ns = max(r.log_time_ns for r in s.records)
    first_ns = min(r.log_time_ns for r in s.records)
    assert 6.5e9 < last_ns - first_ns <= 7.0e9 + 1  # nothing past the stop
    # before the stop (less the fusion's horizon, whose tail the stop flushes): the full run's bytes
    cut = first_ns + 6_000_000_000

    def before(session: object) -> list[tuple[str, bytes]]:
        return [
            (r.topic, r.payload)
            for r in session.records  # type: ignore[attr-defined]
            if r.log_time_ns < cut and not r.topic.endswith("/run")  # the run names its duration
        ]

    mine, theirs = before(s), before(f)
    assert len(mine) > 15_000  # ~3300 a rig second
    assert mine == theirs


def test_a_stopped_run_reruns_bit_for_bit(tmp_path: Path) -> None:
    path = tmp_path / "stopped.mcap"
    _, stop = _stop_after(4)
    _sim(path, 30.0, stop)
    for core in ("fusion", "timesync"):
        code, lines = rerun(str(path), core=core, verify=True)
        assert code == 0, lines
        assert not [line for line in lines if line.startswith("note:")], lines  # nothing lost
        assert any("VERIFY OK" in line for line in lines), lines


def test_a_stop_asked_at_the_first_boundary_leaves_one_second(tmp_path: Path) -> None:
    path = tmp_path / "one.mcap"
    res = _sim(path, 20.0, lambda: True)
    assert res.stopped_at_s == 1.0  # type: ignore[attr-defined]
    s = read_session(path)
    assert not s.truncated and s.meta("completeness", "stopped_at_s") == 1.0


def test_the_second_signal_abandons_the_end_of_the_file() -> None:
    """The first signal asks for the stop at the next boundary; the second does not wait for it."""
    from hil.cli import _StopOnSignal

    stop = _StopOnSignal()
    assert not stop.requested()
    stop._handle(signal.SIGINT, None)
    assert stop.requested() and stop.signum == signal.SIGINT
    with pytest.raises(KeyboardInterrupt):
        stop._handle(signal.SIGINT, None)


@pytest.fixture
def group() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:  # a failed assertion must not leave the sim or its worker running
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(30)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_on_the_command_closes_the_file_where_it_stopped(
    tmp_path: Path, group: list[subprocess.Popen[str]], signum: int
) -> None:
    """The signal goes to the whole process group, as a terminal's Ctrl-C does: the worker
    must not die of it before the sim has taken its last windows."""
    rec = tmp_path / "s.mcap"
    cmd = [sys.executable, "-m", "hil.cli", "sim", "--scenario", "static", "--duration", "12000"]
    cmd += ["--estimators", "ins", "--record", str(rec), "--quiet"]
    p = subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    group.append(p)
    deadline = time.monotonic() + 240
    while (not rec.exists() or rec.stat().st_size < 2_000_000) and p.poll() is None:
        assert time.monotonic() < deadline, "the sim wrote less than 2 MB in 240 s"
        time.sleep(0.2)
    assert p.poll() is None, p.communicate()
    os.killpg(p.pid, signum)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signum, err
    assert "Traceback" not in err
    assert "stopped by signal" in err and "is whole up to there" in err, err
    assert err.count("stopping at the next second") == 1, err  # the worker leaves it to the sim
    assert "hil sim: stopped at" in out
    s = read_session(rec)
    assert not s.truncated
    stopped_at = float(s.meta("completeness", "stopped_at_s"))
    assert 1.0 <= stopped_at < 12000.0
    code, lines = rerun(str(rec), core="fusion", verify=True)
    assert code == 0, lines
