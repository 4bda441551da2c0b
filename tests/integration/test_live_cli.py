"""The live rig's command line, as QA met it: a service run with ``--options`` and no ``--rig``,
and bad input to ``hil up`` / ``hil fault`` refused up front -- exit 2, one line, nothing started,
nothing sent, nothing on disk changed."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO, hil_cmd, run_hil


def _one_line(proc: subprocess.CompletedProcess[str], what: object) -> str:
    assert proc.returncode == 2, (what, proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr + proc.stdout, (what, proc.stderr)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, (what, proc.stderr)
    return lines[0]


@pytest.fixture
def service_procs() -> Iterator[list[subprocess.Popen[str]]]:
    """Services a test starts; any still running at the end is killed and reaped."""
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.communicate(timeout=60)


@pytest.mark.parametrize("hil_rig", [None, "svc_env_rig"])
def test_a_service_with_options_and_no_rig_runs_on_the_default_rig(
    tmp_path: Path, hil_rig: str | None, service_procs: list[subprocess.Popen[str]]
) -> None:
    # docs/gnss-wire.md and docs/dut.md run services this way: it crashed in check_name (rig None)
    env = {k: v for k, v in os.environ.items() if k != "HIL_RIG"}
    if hil_rig:
        env["HIL_RIG"] = hil_rig
    rec = tmp_path / "alone.mcap"
    proc = subprocess.Popen(
        hil_cmd("service", "recorder", "--options", f'{{"path": "{rec}"}}'),
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    service_procs.append(proc)
    deadline = time.monotonic() + 120
    while not rec.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate(timeout=60)
    assert rec.exists()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, (out[-2000:], err[-2000:])
    assert "Traceback" not in err


def test_a_bad_hil_rig_for_a_service_is_one_line_naming_it(tmp_path: Path) -> None:
    proc = run_hil(
        "service",
        "recorder",
        "--options",
        f'{{"path": "{tmp_path / "x.mcap"}"}}',
        env={"HIL_RIG": "bad rig!"},
    )
    assert "HIL_RIG 'bad rig!' is not a valid name" in _one_line(proc, "HIL_RIG")
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.parametrize(
    "name", ["missing_dbc", "field_not_in_dbc", "not_toml", "bad_estimator", "garbage_dbc"]
)
def test_hil_up_refuses_a_bad_dut_mapping_before_anything_starts(tmp_path: Path, name: str) -> None:
    from tests.unit.test_dut_mapping_checks import BAD, spoiled_mapping

    how, why = BAD[name]
    mapping = spoiled_mapping(tmp_path, how)
    rec = tmp_path / "run.mcap"
    for emulator in ([], ["--dut-emulator", "truth"]):
        proc = run_hil("up", "--dut", str(mapping), *emulator, "--duration", "2", "--record", str(rec))
        line = _one_line(proc, (name, emulator))
        assert line.startswith("hil: --dut ") and why in line, line
        assert "hil up: rig" not in proc.stdout
        assert not rec.exists() and not rec.with_suffix(".logs").exists()


REFUSED_UP = [
    ["--estimators", "bogus"],
    ["--cpu-affinity", "99"],
    ["--gnss-messages", "FOO,BAR", "--gnss-protocol", "nmea"],
    ["--gnss-serial", "/nonexistent/dir/x"],
    ["--feedback", "bogus"],
    ["--gnss-tcp", "nonsense"],
    ["--gnss-tcp", "127.0.0.1:99999"],
    ["--can-interface", "nosuchiface"],
    ["--can-interface", "socketcan", "--channel", "nosuchcan0"],
    ["--record-include", "**/["],
]


@pytest.mark.parametrize("args", REFUSED_UP, ids=[" ".join(a) for a in REFUSED_UP])
def test_a_refused_hil_up_leaves_the_earlier_recording_where_it_was(tmp_path: Path, args: list[str]) -> None:
    from tests.replay.helpers import GOLDEN

    rec = tmp_path / "F.mcap"
    shutil.copy(GOLDEN, rec)
    before = sorted(p.name for p in tmp_path.iterdir())
    proc = run_hil("up", "--record", str(rec), "--duration", "2", *args, cwd=tmp_path)
    line = _one_line(proc, args)
    assert "held an earlier recording" not in proc.stderr, line
    assert "hil up: rig" not in proc.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert rec.read_bytes() == GOLDEN.read_bytes()


@pytest.mark.parametrize("cmd", ["up", "sim"])
def test_a_record_pattern_that_can_match_no_key_is_refused(tmp_path: Path, cmd: str) -> None:
    rec = tmp_path / "run.mcap"
    proc = run_hil(cmd, "--record-include", "**/[", "--duration", "1", "--record", str(rec), cwd=tmp_path)
    assert "--record-include '**/['" in _one_line(proc, cmd)
    assert not rec.exists()


FAULTS_REFUSED = [
    (["gnss_outage", "--target", "bad target!"], "--target 'bad target!'"),
    (["kill_service", "--target", "fusion;rm"], "--target 'fusion;rm'"),
    (["gnss_outage", "--duration", "1e7"], "--duration"),
    (["imu_frame_loss", "--param", "percent=5", "--param", "percent=6"], "--param percent: given twice"),
    (["can_burst_error", "--param", "frames=1.5"], "frames counts"),
    (["gnss_jump", "--param", "n_m=1e308"], "n_m must be in"),
]


@pytest.mark.parametrize(("args", "named"), FAULTS_REFUSED, ids=[" ".join(a) for a, _ in FAULTS_REFUSED])
def test_hil_fault_refuses_a_command_the_rig_would_throw_away(args: list[str], named: str) -> None:
    # --rig of no running rig: a command that got past the checks would say "went nowhere", exit 1
    proc = run_hil("fault", *args, "--rig", "no_such_rig_here", "--wait", "0")
    assert named in _one_line(proc, args)
    assert "sent" not in proc.stdout
