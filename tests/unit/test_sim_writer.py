"""``hil sim`` with its recording written by a second process writes this process's file byte for
byte, and a writer that fails (a full file) or dies is a clear error, never a hang, with what it
flushed before still readable."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from hil.messages import Event, encode
from hil.record.mcapio import RecordingError, read_session
from hil.runners.sim import SimOptions, run_sim
from hil.runners.sim_writer import RemoteWriter

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="the writer is forked")

REPO = Path(__file__).resolve().parents[2]


def test_the_writer_process_writes_this_process_file_and_its_parts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Split parts (each a new writer, its channels registered anew), a record filter and the
    free INS alone (a third process beside the worker that runs the pipeline's tail)."""
    from hil.runners import sim

    forked: list[int] = []

    class Counted(RemoteWriter):  # the real writer process, counted: each part forks its own
        def __init__(self, path: str | Path) -> None:
            super().__init__(path)
            forked.append(self.pid)

    monkeypatch.setattr(sim, "RemoteWriter", Counted)
    parts: dict[bool, list[bytes]] = {}
    for remote in (False, True):
        rec = tmp_path / f"w{int(remote)}" / "s.mcap"
        opts = SimOptions(
            scenario="straight_level",
            duration_s=5.0,
            record=rec,
            estimators=["ins"],
            split_s=2.0,
            record_exclude=["status/world"],
            writer_process=remote,
        )
        res = run_sim(opts)
        assert res.messages > 10_000
        parts[remote] = [p.read_bytes() for p in sorted(rec.parent.glob("*.mcap"))]
    assert len(parts[False]) == 3 and len(forked) == 3 and len(set(forked)) == 3
    assert parts[True] == parts[False]


def test_a_file_that_cannot_be_opened_is_the_same_error(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    with pytest.raises(RecordingError, match=r"cannot open .*a-file/s\.mcap for writing"):
        RemoteWriter(blocker / "s.mcap")


def test_a_writer_that_dies_is_an_error_and_keeps_what_it_flushed(tmp_path: Path) -> None:
    rec = tmp_path / "s.mcap"
    w = RemoteWriter(rec)
    try:
        put = w.bind("hil/t/event/sim", Event)
        for i in range(50):
            ev = Event(seq=i, stamp_ns=i * 1000, kind="k", source="s", detail="d")
            put(encode(ev), i * 1000, i * 1000, i)
        w.flush()
        assert w.tell() > 0  # a round trip: the chunk is in the file
        os.kill(w.pid, signal.SIGKILL)
        with pytest.raises(RecordingError, match=r"writer process for .*s\.mcap died"):
            for _ in range(200):  # the first send after its death may still fit the socket's buffer
                put(b"{}", 0, 0, 0)
                w.flush()
                w.tell()
    finally:
        w.abandon()
    s = read_session(rec)
    assert len(s.by_topic("hil/t/event/sim")) == 50


# the writer process from Python (the command line has no switch for it: beside the worker that
# runs the pipeline's tail it was slower); the error as the command line would say it
_WRITER_PROCESS = """
import sys
from pathlib import Path
from hil.record.mcapio import RecordingError
from hil.runners.sim import SimOptions, run_sim
opts = SimOptions(scenario="static", duration_s=60, estimators=["ins"], record=Path(sys.argv[1]),
                  fusion_worker=False, writer_process=True)
try:
    run_sim(opts)
except RecordingError as err:
    sys.exit(f"hil: RecordingError: {err}")
"""


@pytest.mark.parametrize("where", ["default", "--one-process", "writer process"])
def test_a_full_file_is_one_line_and_exit_2_with_the_flushed_part_readable(
    tmp_path: Path, where: str
) -> None:
    """The file size limit (``ulimit -f``) stands for a full disk: the write fails with EFBIG
    (Python ignores SIGXFSZ), in the writer process or in this one, and the command says so in
    one line (the writer process's error names the file)."""
    import resource

    rec = tmp_path / "s.mcap"

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))

    if where == "writer process":
        cmd = [sys.executable, "-c", _WRITER_PROCESS, str(rec)]
    else:
        cmd = [sys.executable, "-m", "hil.cli", "sim", "--scenario", "static", "--duration", "60"]
        cmd += ["--estimators", "ins", "--record", str(rec), "--quiet"]
        cmd += [] if where == "default" else [where]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, preexec_fn=limit, timeout=240)
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    if where == "writer process":
        assert p.returncode == 1, p.stderr  # sys.exit with the line
        assert lines == [f"hil: RecordingError: cannot write {rec}: File too large"], p.stderr
    else:  # the file is written by this process (the worker, if any, runs the tail)
        assert p.returncode == 2, p.stderr
        assert lines == ["hil: OSError: [Errno 27] File too large"], p.stderr
    assert "Traceback" not in p.stderr
    s = read_session(rec)
    assert s.truncated and len(s.records) > 1000
