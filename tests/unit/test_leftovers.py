"""The suite's leftover check (tests/conftest.py) on tests written to leak, run by a real pytest.

GIVEN tests that fail (or pass) while leaving a Zenoh session with a subscriber open (its
"pyo3-closure" thread once kept pytest from exiting for 18 minutes), a child process running, or
a non-daemon thread
THEN each such test is failed by name, what it left is closed or killed, and pytest exits on its
own, promptly, with a failing status.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

LEAKY = """
import subprocess, threading, time
import zenoh

def _session():
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    s = zenoh.open(c)
    s.declare_subscriber("leak/**", lambda _s: None)
    return s

KEEP = []

def test_fails_and_leaks_a_session():
    KEEP.append(_session())
    assert False, "the test's own failure"

def test_passes_but_leaks_a_process():
    p = subprocess.Popen(["sleep", "600"])
    open("sleep.pid", "w").write(str(p.pid))
    KEEP.append(p)

def test_leaks_a_thread():
    ev = threading.Event()
    KEEP.append(ev)
    threading.Thread(target=ev.wait, args=(3600.0,), name="leaky-worker").start()

def test_clean():
    s = _session()
    s.close()
"""


def test_leaks_are_named_cleaned_up_and_pytest_still_exits(tmp_path: Path) -> None:
    (tmp_path / "conftest.py").write_text(
        "from tests.conftest import _no_leftovers, pytest_sessionfinish, pytest_unconfigure  # noqa: F401\n"
    )
    (tmp_path / "test_leaky.py").write_text(LEAKY)
    env = dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    env["HIL_TEST_LEFTOVER_GRACE_S"] = "1"  # each leaky test waits this long for its leftovers
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "--rootdir",
            str(tmp_path),
            str(tmp_path),
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,  # the bug this guards against was a hang (the leaky thread waits an hour)
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    assert "test_fails_and_leaks_a_session left behind: 1 Zenoh session(s) left open (closed now)" in out, (
        out[-3000:]
    )
    assert "test_passes_but_leaks_a_process left behind: process(es) left running (killed now)" in out
    assert "sleep 600" in out
    assert "test_leaks_a_thread left behind: non-daemon thread(s) left running: leaky-worker" in out
    summary = [ln for ln in out.splitlines() if ln.startswith(("FAILED", "ERROR"))]
    assert len(summary) == 4 and not any("test_clean" in ln for ln in summary), summary
    assert "non-daemon threads still running at exit: ['leaky-worker']; exiting 1" in out
    # the sleep was killed, not left to the machine
    pid = int((tmp_path / "sleep.pid").read_text())
    assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split(")")[1][:3]
