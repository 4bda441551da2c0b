"""``hil replay`` as a user runs it: selection, another rig, step, loop, Ctrl-C, and bad files
given to ``hil info/replay/rerun`` (one line, exit 2, no traceback)."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.record.mcapio import read_session
from tests.conftest import REPO, hil_cmd, run_hil
from tests.replay.helpers import GOLDEN, Hub

pytestmark = pytest.mark.slow


@pytest.fixture
def hub() -> Iterator[Hub]:
    h = Hub()
    try:
        yield h
    finally:
        h.close()


def bad_files(tmp: Path) -> dict[str, Path]:
    data = GOLDEN.read_bytes()
    out = {
        "garbage": b"this is not an mcap file\n" * 10,
        "empty": b"",
        "magic_only": data[:8],
        "cut_in_header": data[:40],
    }
    paths = {}
    for name, blob in out.items():
        p = tmp / f"{name}.mcap"
        p.write_bytes(blob)
        paths[name] = p
    paths["missing"] = tmp / "missing.mcap"
    return paths


@pytest.mark.parametrize("cmd", [["info"], ["replay", "--afap"], ["rerun", "--verify"]])
def test_a_bad_file_exits_2_with_one_line(tmp_path: Path, cmd: list[str]) -> None:
    for name, path in bad_files(tmp_path).items():
        proc = run_hil(cmd[0], str(path), *cmd[1:], timeout=60)
        assert proc.returncode == 2, (name, proc.stdout, proc.stderr)
        assert "Traceback" not in proc.stderr, (name, proc.stderr)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and str(path) in lines[0], (name, proc.stderr)


def test_a_truncated_file_replays_up_to_its_last_chunk(tmp_path: Path, hub: Hub) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(GOLDEN.read_bytes()[: GOLDEN.stat().st_size // 2])
    hub.collect("hil/cut/truth")
    proc = hub.run("replay", str(cut), "--afap", "--rig", "cut", "--topics", "/truth$")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "truncated" in proc.stdout
    time.sleep(0.5)
    assert 0 < len(hub.samples) < 401


def test_time_window_topic_filter_and_rig_rekey(hub: Hub) -> None:
    # GIVEN the recorded truth between 1 s and 2 s after the first message
    s = read_session(GOLDEN)
    t0 = s.records[0].log_time_ns
    want = [r.payload for r in s.records if r.topic.endswith("/truth") and 1e9 <= r.log_time_ns - t0 < 2e9]
    hub.collect("hil/**")
    # WHEN it is replayed under rig "other", truth only, 1..2 s
    proc = hub.run(
        "replay", str(GOLDEN), "--afap", "--rig", "other", "--topics", "/truth$", "--start", "1", "--end", "2"
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    time.sleep(0.5)
    # THEN exactly those payloads arrive, byte for byte, on hil/other/truth and nowhere else
    assert {k for k, _ in hub.samples} == {"hil/other/truth"}
    assert [p for _, p in hub.samples] == want and len(want) == 100  # [1 s, 2 s): the end excluded
    # and the summary says what was sent: the window's 0.99 s, not where it ended in the file
    assert "replay: 100 messages" in proc.stdout and "0.99 s of recording" in proc.stdout, proc.stdout


def test_back_to_back_windows_send_each_message_once_as_filter_cuts_them(hub: Hub, tmp_path: Path) -> None:
    # GIVEN the recorded truth from 1 s to 3 s, and a message exactly at 2 s (truth is at 100 Hz)
    s = read_session(GOLDEN)
    t0 = s.records[0].log_time_ns
    truth = [r for r in s.records if r.topic.endswith("/truth")]
    want = [r.payload for r in truth if 1e9 <= r.log_time_ns - t0 < 3e9]
    assert any(r.log_time_ns - t0 == 2e9 for r in truth)
    hub.collect("hil/halves/truth")
    # WHEN it is replayed as [1, 2) then [2, 3)
    for start, end in (("1", "2"), ("2", "3")):
        proc = hub.run(
            "replay",
            str(GOLDEN),
            "--afap",
            "--rig",
            "halves",
            "--topics",
            "/truth$",
            "--start",
            start,
            "--end",
            end,
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
    time.sleep(0.5)
    # THEN every message arrives once (the one at 2 s was sent twice), as hil filter cuts the file
    assert [p for _, p in hub.samples] == want
    cut = tmp_path / "cut.mcap"
    assert run_hil("filter", str(GOLDEN), "-o", str(cut), "--start", "1", "--end", "2").returncode == 0
    filtered = [r.payload for r in read_session(cut).records if r.topic.endswith("/truth")]
    assert filtered == want[: len(filtered)] and len(filtered) == 100


@pytest.mark.parametrize("selection", [["--topics", "nosuch"], ["--start", "100"]])
def test_a_loop_over_a_selection_that_takes_nothing_is_refused_up_front(selection: list[str]) -> None:
    # it reread the file for ever at full CPU, sending nothing (the timeout fails the test then)
    proc = run_hil("replay", str(GOLDEN), "--rig", "qa", "--loop", "--no-progress", *selection, timeout=120)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stdout + proc.stderr
    assert "nothing selected" in lines[0] and str(GOLDEN) in lines[0] and " s from the first" in lines[0]


def test_original_timing_and_rate(hub: Hub) -> None:
    hub.collect("hil/timed/truth")
    t = time.monotonic()
    proc = hub.run(
        "replay", str(GOLDEN), "--rig", "timed", "--topics", "/truth$", "--end", "2", "--rate", "2"
    )
    took = time.monotonic() - t
    assert proc.returncode == 0, proc.stdout + proc.stderr
    stamps = [json.loads(p)["stamp_ns"] for _, p in hub.samples]
    assert len(stamps) == 200  # [0, 2 s): the message at 2 s is the next window's
    assert 1.0 <= took < 1.0 + 3.0  # 2 s of recording at rate 2 (+ start-up)


def test_step_sends_one_message_per_enter(hub: Hub) -> None:
    hub.collect("hil/stepper/**")
    p = subprocess.run(
        hil_cmd("replay", str(GOLDEN), "--rig", "stepper", "--topics", "/truth$", "--step"),
        input="\n\n\nq\n",
        cwd=REPO,
        env=hub.env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    time.sleep(0.5)
    assert [json.loads(b)["seq"] for _, b in hub.samples] == [0, 1, 2]


def test_loop_runs_until_ctrl_c_and_stops_cleanly(hub: Hub) -> None:
    hub.collect("hil/looper/run")
    proc = hub.spawn("replay", str(GOLDEN), "--rig", "looper", "--topics", "/run$", "--afap", "--loop")
    n_run = sum(1 for r in read_session(GOLDEN).records if r.topic.endswith("/run"))
    deadline = time.monotonic() + 60  # a deadline, not a pause: a loaded machine loops slower
    while len(hub.samples) <= 2 * n_run and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 130, out
    assert "Traceback" not in out and "replay:" in out
    assert len(hub.samples) > 2 * n_run  # it went round more than twice


@pytest.mark.parametrize("flag", ["--topics", "--exclude-topics"])
def test_a_bad_topic_pattern_is_one_line_and_exit_2(flag: str) -> None:
    proc = run_hil("replay", str(GOLDEN), "--afap", flag, "[bad", "--no-progress", timeout=60)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr  # it was exit 1, "ValueError: ..."
    assert lines[0].startswith("hil replay: --topics/--exclude-topics: bad pattern '[bad'"), lines


def damaged_files(tmp: Path) -> dict[str, Path]:
    """The golden file (finished) with one bit flipped in a middle chunk's compressed bytes, and
    with a middle chunk's record length garbled: damage, not a cut."""
    from mcap.reader import make_reader

    data = GOLDEN.read_bytes()
    with open(GOLDEN, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    mid = chunks[len(chunks) // 2]
    assert mid.chunk_length > 10_000  # a chunk of messages, not a short one
    out = {}
    for name, at, mask in (
        ("bit", mid.chunk_start_offset + mid.chunk_length // 2, 0x01),
        ("length", mid.chunk_start_offset + 4, 0xFF),
    ):
        blob = bytearray(data)
        blob[at] ^= mask
        out[name] = tmp / f"{name}.mcap"
        out[name].write_bytes(bytes(blob))
    return out


@pytest.mark.parametrize(
    "cmd",
    [["info"], ["replay", "--afap", "--no-progress"], ["rerun", "--verify"], ["report", "--no-progress"]],
)
def test_a_damaged_finished_file_exits_2_naming_it_damaged(tmp_path: Path, cmd: list[str]) -> None:
    """A finished file whose middle chunk fails its CRC or does not parse is corrupt: exit 2 with
    one line naming the file, the byte and the way out -- never "truncated" and exit 0."""
    for name, path in damaged_files(tmp_path).items():
        proc = run_hil(cmd[0], str(path), *cmd[1:], timeout=120)
        assert proc.returncode == 2, (name, proc.stdout, proc.stderr)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "Traceback" not in proc.stderr, (name, proc.stderr)
        assert f"{path} is damaged at byte " in lines[0] and f"hil recover {path}" in lines[0], lines
        # the line says it all: no exception class before it ("hil: DamagedRecordingError: ...")
        assert lines[0].split(": ", 1)[1].startswith(str(path)), lines
        assert "truncated" not in proc.stdout.lower(), (name, proc.stdout)
