"""The live rig's command line, as QA met it: a service run with ``--options`` and no ``--rig``,
and bad input to ``hil up`` / ``hil fault`` refused up front -- exit 2, one line, nothing started,
nothing sent, nothing on disk changed."""

from __future__ import annotations

import os
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
