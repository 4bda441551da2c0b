"""A `hil up` killed with SIGKILL leaves no services behind: each notices its supervisor is gone."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, hil_cmd

pytestmark = pytest.mark.slow


def _children(pid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (reaped by init later) counts as gone
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[1].split()[0] != "Z"
    except OSError:
        return False


def test_services_stop_themselves_when_the_supervisor_is_killed(tmp_path: Path) -> None:
    sup = subprocess.Popen(
        hil_cmd(
            "up", "--duration", "60", "--record", str(tmp_path / "o.mcap"), "--quiet", "--rig", "orphans"
        ),
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        kids: list[int] = []
        while time.monotonic() < deadline and len(kids) < 7:
            time.sleep(0.5)
            kids = _children(sup.pid)
        assert len(kids) >= 7, kids
        time.sleep(2.0)
        sup.send_signal(signal.SIGKILL)
        sup.wait(timeout=10)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and any(_alive(k) for k in kids):
            time.sleep(0.3)
        left = [k for k in kids if _alive(k)]
        assert not left, f"services still running after their supervisor died: {left}"
    finally:
        for k in _children(sup.pid):
            os.kill(k, signal.SIGKILL)
