"""Bad input refused up front, as a user meets it: exit 2, one line on stderr naming what was wrong,
no traceback, and (``hil up``) no process started -- for absurd numbers on the command line, a
scenario with a NaN or impossible value, and a corrupt, foreign or non-MCAP file."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from mcap.writer import Writer

from tests.conftest import REPO, run_hil
from tests.replay.helpers import GOLDEN


def _one_line(proc, what: str) -> str:  # type: ignore[no-untyped-def]
    assert proc.returncode == 2, (what, proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr + proc.stdout, (what, proc.stderr)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, (what, proc.stderr)
    return lines[0]


ABSURD = [
    (["up", "--duration", "inf"], "--duration"),
    (["up", "--duration", "nan"], "--duration"),
    (["up", "--duration", "1e300"], "--duration"),
    (["up", "--duration", "-1"], "--duration"),
    (["up", "--speed", "inf"], "--speed"),
    (["up", "--speed", "nan"], "--speed"),
    (["up", "--speed", "1e300"], "--speed"),
    (["up", "--speed", "-1"], "--speed"),
    (["up", "--restart", "-1"], "--restart"),
    (["up", "--restart", "1e300"], "--restart"),
    (["up", "--restart", "inf"], "--restart"),
    (["up", "--estimators", "ekf15,nosuch"], "nosuch"),
    (["sim", "--duration", "1e300"], "--duration"),
    (["sim", "--duration", "1e12"], "--duration"),
    (["sim", "--duration", "inf"], "--duration"),
    (["sim", "--estimators", "nosuch"], "nosuch"),
    # a repeated name ran that estimator twice (every solution published twice); an empty list
    # quietly ran the defaults
    (["sim", "--estimators", "ekf15,ekf15"], "ekf15 more than once"),
    (["up", "--estimators", "ekf15, ekf15"], "ekf15 more than once"),
    (["sim", "--estimators", ""], "names no estimator"),
    (["sim", "--estimators", ","], "names no estimator"),
    (["up", "--estimators", ""], "names no estimator"),
    (["sim", "--estimators", "ekf15,,kfvel"], "empty name"),
    (["replay", str(GOLDEN), "--rate", "inf"], "--rate"),
    (["replay", str(GOLDEN), "--start", "nan"], "--start"),
    (["replay", str(GOLDEN), "--end", "-1"], "--end"),
    (["monitor", "--duration", "inf"], "--duration"),
    (["fault", "kill_service", "--target", "fusion", "--duration", "nan"], "--duration"),
    (["bench", "soak", "--duration", "inf"], "--duration"),
    (["service", "world", "--speed", "inf"], "--speed"),
]


@pytest.mark.parametrize(("args", "named"), ABSURD, ids=[" ".join(a) for a, _ in ABSURD])
def test_absurd_numbers_are_refused_before_anything_starts(
    tmp_path: Path, args: list[str], named: str
) -> None:
    rec = tmp_path / "run.mcap"
    extra = ["--record", str(rec)] if args[0] in ("up", "sim") else []
    proc = run_hil(*args, *extra, timeout=120, cwd=tmp_path)
    line = _one_line(proc, args)
    assert named in line, line
    # nothing started: no banner, no service logs, no recording
    assert "hil up: rig" not in proc.stdout
    assert not rec.exists() and not rec.with_suffix(".logs").exists()


SCENARIOS = {
    "gyro_arw_dprh": '[imu]\npreset = "tactical"\ngyro_arw_dprh = nan\n',
    "accel_range_g": "[imu]\naccel_range_g = 0\n",
    "gnss.pos_sigma_m": "[gnss]\npos_sigma_m = -1.0\n",
    "gnss.hdop": "[gnss]\nhdop = inf\n",
    "origin.alt_m": "[origin]\nalt_m = nan\n",
    "duration_s": "duration_s = 1e300\n",
    "event[0].t_start_s": '[[event]]\nkind = "gnss_outage"\nt_start_s = nan\nt_end_s = 5.0\n',
    # a division by zero (ZeroDivisionError) and a KeyError came out raw
    "segment[0].yaw_rate_dps": '[[segment]]\nkind = "turn"\nyaw_rate_dps = 0.0\nangle_deg = 90.0\n',
    "segment[0].roll_rate_dps": (
        '[[segment]]\nkind = "coordinated_turn"\nyaw_rate_dps = 5.0\nroll_rate_dps = 0.0\nangle_deg = 90.0\n'
    ),
    "segment[0] (rates) needs euler_rate_dps": '[[segment]]\nkind = "rates"\nduration_s = 3.0\n',
}


@pytest.mark.parametrize("key", list(SCENARIOS))
@pytest.mark.parametrize("cmd", ["sim", "up"])
def test_a_scenario_with_a_bad_value_is_refused_at_load_naming_the_key(
    tmp_path: Path, key: str, cmd: str
) -> None:
    text = SCENARIOS[key]
    if not text.startswith("duration_s"):
        text = "duration_s = 10.0\n" + text
    path = tmp_path / "bad.toml"
    path.write_text(text)
    rec = tmp_path / "run.mcap"
    proc = run_hil(cmd, "--scenario", str(path), "--duration", "2", "--record", str(rec), cwd=tmp_path)
    line = _one_line(proc, key)
    assert key in line, line
    assert not rec.exists() and not rec.with_suffix(".logs").exists()


def _bad_files(tmp: Path) -> dict[str, Path]:
    foreign = tmp / "foreign.mcap"
    with open(foreign, "wb") as fh:  # a well-formed MCAP another tool wrote
        w = Writer(fh)
        w.start(profile="", library="someone-else 1.0")
        sid = w.register_schema("foo.Bar", "jsonschema", b'{"type": "object"}')
        cid = w.register_channel("/foo", message_encoding="json", schema_id=sid)
        for i in range(50):
            w.add_message(cid, log_time=i * 10**7, publish_time=i * 10**7, data=json.dumps({"x": i}).encode())
        w.finish()
    files = {"foreign": foreign}
    for name, blob in {
        "eight_bytes": GOLDEN.read_bytes()[:8],
        "text": b"not an mcap file\n" * 4,
        "empty": b"",
    }.items():
        files[name] = tmp / f"{name}.mcap"
        files[name].write_bytes(blob)
    return files


COMMANDS = {
    "report": ["report", "{f}", "--no-progress", "--out", "{tmp}/out"],
    "replay": ["replay", "{f}", "--afap", "--no-progress"],
    "rerun": ["rerun", "{f}", "--verify"],
    "export": [],
}


@pytest.mark.parametrize("cmd", list(COMMANDS))
def test_corrupt_foreign_and_non_mcap_files_are_refused_with_one_line(tmp_path: Path, cmd: str) -> None:
    import subprocess

    for name, path in _bad_files(tmp_path).items():
        if cmd == "export":
            proc = subprocess.run(
                [sys.executable, "-m", "hil.record.foxglove", str(path), str(tmp_path / "x.mcap")],
                capture_output=True,
                text=True,
                timeout=120,
                cwd=REPO,
            )
        else:
            args = [a.format(f=path, tmp=tmp_path) for a in COMMANDS[cmd]]
            proc = run_hil(*args, timeout=120)
        line = _one_line(proc, (cmd, name))
        assert str(path) in line, line
        if name == "foreign":
            assert "not a hil recording" in line, line
        assert not (tmp_path / "out" / "report.html").exists()
