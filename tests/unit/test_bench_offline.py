"""``hil bench offline``'s judge of "same output": per-topic digests of two recordings."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.bench import offline
from hil.messages import TYPES_BY_NAME
from hil.record.mcapio import SessionWriter


def _rec(path: Path, payloads: list[bytes]) -> Path:
    w = SessionWriter(path, spill_index=False)
    cls = next(iter(TYPES_BY_NAME.values()))
    for i, p in enumerate(payloads):
        w.write(f"hil/t/{i % 2}", cls, p, log_time_ns=1000 + i, publish_time_ns=1000 + i, seq=i)
    w.close()
    return path


def test_digests_tell_a_changed_payload_from_equal_ones(tmp_path: Path) -> None:
    base = [b'{"a": %d}' % i for i in range(20)]
    changed = [*base[:7], b'{"a": -7}', *base[8:]]
    a, b, c = (offline.digests(_rec(tmp_path / n, p)) for n, p in [("a", base), ("b", base), ("c", changed)])
    assert a == b
    assert a["hil/t/0"] == c["hil/t/0"]
    assert a["hil/t/1"] != c["hil/t/1"]
    assert a["hil/t/1"][0] == 10


@pytest.mark.parametrize(
    "argv",
    [
        ["HEAD", "--duration", "0"],
        ["no-such-revision-xyz", "--duration", "1"],
        ["HEAD", "--duration", "1", "--estimators", "ins,ekf16"],
        ["HEAD", "--duration", "1", "--imu-rate", "5"],
        ["HEAD", "--duration", "1", "--timeout", "0"],
        ["HEAD", "--duration", "1", "--instructions", "2"],
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert offline.main([*argv, "--no-write"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hil bench offline:") and "\n" not in err


def test_a_ref_tree_is_timed_with_its_kernels_already_compiled(tmp_path: Path) -> None:
    """REF's fresh worktree has no numba cache and no kernels built ahead of time: ``warm_kernels``
    makes both before anything is timed (else REF's first timed run pays the ~10 s compile and
    its mean favours this tree, and REF runs numba's kernels where this tree runs its own)."""
    from hil.bench.versus import ref_tree, remove_ref_tree, warm_kernels

    tree = ref_tree("HEAD", tmp_path)
    try:
        assert not list(tree.rglob("*.nbi"))
        warm_kernels(tree)
        cached = {p.name.split(".")[0] for p in tree.rglob("*.nbi")}
        assert {"strapdown", "kernels", "predictor"} <= cached, cached
        if shutil.which("cc") or shutil.which("gcc"):  # built as make builds them, as this tree's are
            assert list((tree / "hil" / "runtime" / "__pycache__").glob("hil_kernels_*.so"))
    finally:
        remove_ref_tree(tree)


def _gone(pid: int) -> bool:
    """No such process, or only its zombie left (killed, waiting for whoever reaps orphans)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    return "\nState:\tZ" in status


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads process states in /proc")
def test_a_run_that_hangs_is_killed_with_what_it_started_and_said(tmp_path: Path) -> None:
    """A revision whose sim hangs (as 11bb66d's did at 1 kHz) ends the bench with a line that
    says so, its worker killed too, instead of a bench that never ends."""
    pids = tmp_path / "pids"
    code = (
        "import os, sys, time; os.fork(); open(sys.argv[1], 'a').write(f'{os.getpid()}\\n'); time.sleep(600)"
    )
    with pytest.raises(RuntimeError, match=r"did not finish in 5 s: killed"):
        offline.run_child(tmp_path, ["-c", code, str(pids)], timeout_s=5.0)
    started = [int(x) for x in pids.read_text().split()]
    assert len(started) == 2
    deadline = time.monotonic() + 60.0  # SIGKILL lands asynchronously: a busy machine takes a while
    while not all(_gone(pid) for pid in started) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert all(_gone(pid) for pid in started)


def test_a_run_that_ends_in_time_gives_its_cpu_and_exit_code(tmp_path: Path) -> None:
    cpu, wall, rc = offline.run_child(tmp_path, ["-c", "raise SystemExit(1)"], timeout_s=600.0)
    assert rc == 1 and cpu > 0 and wall > 0
    with pytest.raises(RuntimeError, match="exited 3: boom"):
        offline.run_child(tmp_path, ["-c", "import sys; sys.stderr.write('boom'); raise SystemExit(3)"])


@pytest.mark.parametrize("name", ["seeds_common", "capture", "nosuch", "../cli", ""])
def test_hil_bench_of_what_is_not_a_benchmark_is_one_line_naming_them(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A helper module of hil.bench (no ``main``) was imported and run: an AttributeError
    traceback. Now every non-benchmark is one line that lists the benchmarks, exit 2."""
    from hil import cli

    assert cli.main(["bench", name]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"no benchmark named {name!r}" in err and "offline, pacing" in err, err
    assert cli.main(["bench", "list"]) == 0
    listed = capsys.readouterr().out.split()
    assert (
        "offline" in listed and "rig" in listed and "seeds_common" not in listed and "capture" not in listed
    )


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="needs valgrind (.ci/run installs it)")
def test_instructions_are_counted_per_process_the_forked_worker_apart(tmp_path: Path) -> None:
    """``--instructions`` reads cachegrind's count of each process: the forked child's work is
    the worker's, not the sim's own process's."""
    code = (
        "import os\npid = os.fork()\nif pid == 0:\n    sum(range(3_000_000))\n    os._exit(0)\n"
        "os.waitpid(pid, 0)\n"
    )
    argv = ["valgrind", "--tool=cachegrind", "--cache-sim=no", f"--cachegrind-out-file={tmp_path}/%p"]
    proc = subprocess.Popen([*argv, sys.executable, "-S", "-c", code], stderr=subprocess.DEVNULL)
    try:
        assert proc.wait(timeout=300) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    own, worker = offline._counts(tmp_path, proc.pid)
    assert len(list(tmp_path.iterdir())) == 2
    assert own > 1_000_000 and worker > own + 30_000_000  # ~3e6 additions of Python ints: > 10 each
