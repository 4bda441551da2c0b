"""``hil sim`` whose file cannot grow (a full disk) stops with one line and exit code 2, whether
a worker runs the pipeline's tail or not, and what it flushed before stays readable."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hil.record.mcapio import read_session

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("where", ["default", "--one-process"])
def test_a_full_file_is_one_line_and_exit_2_with_the_flushed_part_readable(
    tmp_path: Path, where: str
) -> None:
    """The file size limit (``ulimit -f``) stands for a full disk: the write fails with EFBIG
    (Python ignores SIGXFSZ) in the sim's own process, which writes the file, and the command
    says so in one line; the worker, if any, is stopped."""
    import resource

    rec = tmp_path / "s.mcap"

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))

    cmd = [sys.executable, "-m", "hil.cli", "sim", "--scenario", "static", "--duration", "60"]
    cmd += ["--estimators", "ins", "--record", str(rec), "--quiet"]
    cmd += [] if where == "default" else [where]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, preexec_fn=limit, timeout=240)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    # the file it could not write, named (it was "hil: OSError: [Errno 27] File too large")
    assert lines == [f"hil: writing {rec} failed: File too large; what was flushed before stays readable"], (
        p.stderr
    )
    s = read_session(rec)
    assert s.truncated and len(s.records) > 1000
