"""``hil bench offline REF``: ``hil sim`` and ``hil rerun`` × real time, this tree against REF.

Issue 20's offline targets are ratios of rig seconds to CPU seconds on one core, so that is what
this measures: each child's own rusage (user + system), which a busy machine slows far less than
wall time. Both revisions run in the same session, alternating (REF first on even repeats), so the
before/after ratio shares the load. REF runs from a temporary ``git worktree`` with the same Python
environment (as ``hil bench versus`` does). Every run:

- ``hil sim --scenario S --duration D --record`` (every default estimator, or ``--estimators``:
  ``ins`` for the 12000 s static target's configuration; everything recorded);
- ``hil rerun --core fusion --verify`` and ``--core timesync --verify`` of REF's recording (the same
  file for both trees, so the rerun figures compare like with like and the verify checks that
  this tree reproduces REF's outputs bit for bit);
- the start-up alone (``import hil.runners.sim, hil.record.rerun``), which every run pays;
- this tree's ``hil sim --one-process`` too (the fusion kept in the sim's process), beside REF's
  ``hil sim`` (which has one process only).

CPU counts a child's reaped children (``wait4``: the sim's fusion worker), so it is the work
done; wall time says what the second core gave, and only on a machine with a core to spare.

``--imu-rate`` runs the sim at that rate (1 kHz and up is where 11bb66d's sim hung). Every run has
a time limit (``--timeout``) and its own process group: one still going then is killed with its
worker, and the bench stops with a line that names it.

``--instructions S`` also counts, with valgrind's cachegrind, the instructions each process of
each tree's ``hil sim`` executes (the sim's own process and its forked worker), for an S-second
sim less a 2-second one (the start-up), per rig second. A count does not move with the machine's
speed or load, so both trees run at once, and a change of a few percent shows where time
ratios on a VM whose speed moves by a third within minutes cannot: the process with the larger
count is the one the sim's wall time waits for. Take S of 30 or more: one tree against itself
came out 0.966 over 1 rig second (start-up varies with the hash seed and the first windows) and
within 0.05 % over 38.

The two trees' recordings are compared topic by topic (log time, publish time, sequence, payload:
what ``tools/recording_diff.py`` compares). ``--profile`` adds each tree's cProfile top entries
of one ``hil sim``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import os
import pstats
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from hil.bench import command_line, write_section
from hil.bench.versus import ref_tree, remove_ref_tree, warm_kernels
from hil.estimators.registry import ESTIMATORS
from hil.fusion.core import FREE_INS

_RUN = "import sys; from hil.cli import main; sys.argv[0] = 'hil'; raise SystemExit(main())"
_IMPORT = "import hil.runners.sim, hil.record.rerun"
_STEPS = ("start-up", "sim", "sim, one process", "rerun fusion", "rerun timesync")


@dataclass
class Tree:
    label: str
    path: Path
    cpu: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in _STEPS})
    wall: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in _STEPS})
    verify_failed: list[str] = field(default_factory=list)


def _env(tree: Path, extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_")}
    env["PYTHONPATH"] = str(tree)
    return env | (extra or {})


def compile_bytecode(tree: Path) -> None:
    """Both trees with their bytecode compiled, as an installed rig runs: where
    ``PYTHONDONTWRITEBYTECODE`` is set (CI images, some sandboxes) every run would otherwise
    compile each module it imports again, ~0.1 s of every command's CPU."""
    dirs = [str(tree / d) for d in ("hil", "services") if (tree / d).is_dir()]
    subprocess.run([sys.executable, "-m", "compileall", "-q", *dirs], check=False, stdout=subprocess.DEVNULL)


def _cpu_of(tree: Path, argv: list[str]) -> tuple[float, int]:
    """CPU seconds (user + system) of one child and its exit code."""
    cpu, _wall, rc = run_child(tree, argv)
    return cpu, rc


def run_child(
    tree: Path,
    argv: list[str],
    extra_env: dict[str, str] | None = None,
    timeout_s: float | None = None,
) -> tuple[float, float, int]:
    """CPU seconds (user + system, with the children it reaped), wall seconds and exit code of
    one child (``HIL_*`` from this environment left out, ``extra_env`` added). One still running
    ``timeout_s`` after it started is killed with everything it started (a revision that hangs
    is a result, not a bench that never ends): a ``RuntimeError`` that says so."""
    t0 = time.monotonic()
    with tempfile.TemporaryFile() as err_file:
        proc = subprocess.Popen(
            [sys.executable, *argv],
            cwd=tree,
            env=_env(tree, extra_env),
            stdout=subprocess.DEVNULL,
            stderr=err_file,
            start_new_session=True,  # its own process group: a timeout kills its workers too
        )
        status, ru = _wait(proc, timeout_s)
        wall = time.monotonic() - t0
        err_file.seek(0)
        err = err_file.read().decode(errors="replace").strip()
    what = " ".join(argv[2:5])
    if status is None or ru is None:
        raise RuntimeError(
            f"{what} in {tree} did not finish in {timeout_s:g} s: killed (it hangs, or needs a "
            "longer --timeout)"
        )
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"{what} in {tree} exited {proc.returncode}: {err[-300:]}")
    return ru.ru_utime + ru.ru_stime, wall, proc.returncode


def _wait(proc: subprocess.Popen[bytes], timeout_s: float | None) -> tuple[int | None, Any]:
    """``wait4`` of ``proc``: its status and rusage, or (None, None) after ``timeout_s``. Its
    process group is killed once it is done, timed out, or this process is interrupted."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        while True:
            pid, status, ru = os.wait4(proc.pid, 0 if deadline is None else os.WNOHANG)
            if pid:
                return status, ru
            if deadline is not None and time.monotonic() >= deadline:
                return None, None
            time.sleep(0.05)
    finally:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)  # what it left behind, or all of it
        with contextlib.suppress(ChildProcessError):
            os.waitpid(proc.pid, 0)


def digests(path: Path) -> dict[str, tuple[int, str]]:
    """Per topic: message count and SHA-256 of its (log, publish, sequence, payload) sequence."""
    acc: dict[str, tuple[int, hashlib._Hash]] = {}
    with open(path, "rb") as fh:
        for _s, ch, msg in make_reader(fh).iter_messages(log_time_order=False):
            n, h = acc.get(ch.topic, (0, hashlib.sha256()))
            h.update(f"{msg.log_time} {msg.publish_time} {msg.sequence} {len(msg.data)}\n".encode())
            h.update(msg.data)
            acc[ch.topic] = (n + 1, h)
    return {t: (n, h.hexdigest()) for t, (n, h) in acc.items()}


def run_pair(
    trees: list[Tree], sim_args: list[str], tmp: Path, i: int, timeout_s: float | None = None
) -> dict[str, Path]:
    """One repeat: each tree's start-up and sim, then both trees' reruns of REF's recording
    (each run killed after ``timeout_s``: a ``RuntimeError``)."""
    order = trees if i % 2 == 0 else trees[::-1]
    recs = {}

    def measure(t: Tree, step: str, argv: list[str]) -> int:
        cpu, wall, rc = run_child(t.path, argv, timeout_s=timeout_s)
        t.cpu[step].append(cpu)
        t.wall[step].append(wall)
        return rc

    for t in order:
        measure(t, "start-up", ["-c", _IMPORT])
        rec = tmp / f"{'ref' if t is trees[0] else 'head'}-{i}.mcap"
        measure(t, "sim", ["-c", _RUN, "sim", *sim_args, "--record", str(rec), "--quiet"])
        if t is trees[0]:  # REF has one process only: its sim is the anchor of both rows
            t.cpu["sim, one process"].append(t.cpu["sim"][-1])
            t.wall["sim, one process"].append(t.wall["sim"][-1])
        else:
            one = tmp / f"head-one-{i}.mcap"
            measure(
                t,
                "sim, one process",
                ["-c", _RUN, "sim", *sim_args, "--record", str(one), "--quiet", "--one-process"],
            )
            recs["one process"] = one
        recs[t.label] = rec
    for t in order:
        for core in ("fusion", "timesync"):
            argv = ["-c", _RUN, "rerun", str(recs[trees[0].label]), "--core", core, "--verify"]
            if measure(t, f"rerun {core}", argv) != 0:
                t.verify_failed.append(core)
    return recs


_COUNT_BASE_S = 2.0  # the counted sim's start-up and first windows, taken off each count


def _sim_instructions(tree: Path, sim_args: list[str], rig_s: float, tmp: Path) -> subprocess.Popen[bytes]:
    """``hil sim`` of ``rig_s`` under cachegrind (instructions only), started: each process
    (the sim's own, its forked worker) writes its count to ``tmp/cg-<rig_s>/<pid>``."""
    args = list(sim_args)
    args[args.index("--duration") + 1] = f"{rig_s:g}"
    out = tmp / f"cg-{rig_s:g}"
    out.mkdir(exist_ok=True)
    argv = ["valgrind", "--tool=cachegrind", "--cache-sim=no", f"--cachegrind-out-file={out}/%p"]
    argv += [sys.executable, "-c", _RUN, "sim", *args, "--record", str(out / "sim.mcap"), "--quiet"]
    return subprocess.Popen(
        argv,
        cwd=tree,
        env=_env(tree),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def _counts(out: Path, pid: int) -> tuple[int, int]:
    """(the sim's own process, its workers) instructions from cachegrind's files in ``out``."""
    own = workers = 0
    for f in out.iterdir():
        if not f.name.isdigit():
            continue
        ir = next((int(x.split()[1]) for x in f.read_text().splitlines() if x.startswith("summary:")), 0)
        if int(f.name) == pid:
            own += ir
        else:
            workers += ir
    return own, workers


def count_instructions(
    trees: list[Tree], sim_args: list[str], rig_s: float, tmp: Path, timeout_s: float
) -> list[str]:
    """Each tree's ``hil sim`` of ``rig_s`` and of ``_COUNT_BASE_S`` under cachegrind, both trees at
    once (a count does not depend on what else runs: the figure for a VM whose speed moves by
    a third within minutes); per process, the instructions of the rig seconds in between."""
    runs: dict[tuple[str, str], tuple[subprocess.Popen[bytes], Path]] = {}
    # a first short run, not counted: a tree that runs numba's kernels (none built ahead of time)
    # finds its cache keyed to the host's CPU, which valgrind's virtual one is not, and compiles
    # them in its first run (seen: ~50 G instructions of a worker)
    for stage, dur in (("warm", _COUNT_BASE_S), ("base", _COUNT_BASE_S), ("counted", rig_s)):
        started: list[subprocess.Popen[bytes]] = []
        try:
            for t in trees:
                d = tmp / f"count-{'ref' if t is trees[0] else 'head'}-{stage}"
                d.mkdir(exist_ok=True)
                started.append(_sim_instructions(t.path, sim_args, dur, d))
                runs[(t.label, stage)] = (started[-1], d / f"cg-{dur:g}")
            for t, proc in zip(trees, started, strict=True):
                status, _ru = _wait(proc, timeout_s)
                if status is None or os.waitstatus_to_exitcode(status) not in (0, 1):
                    raise RuntimeError(f"hil sim under cachegrind in {t.path} failed or did not finish")
        finally:  # one failed or this process was interrupted: the other tree's run goes too
            for proc in started:
                if proc.returncode is None and proc.poll() is None:
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
    per: dict[str, tuple[float, float]] = {}
    for t in trees:
        (p1, d1), (p0, d0) = runs[(t.label, "counted")], runs[(t.label, "base")]
        (o1, w1), (o0, w0) = _counts(d1, p1.pid), _counts(d0, p0.pid)
        n = rig_s - _COUNT_BASE_S
        per[t.label] = ((o1 - o0) / n, (w1 - w0) / n)
    (ro, rw), (ho, hw) = per[trees[0].label], per[trees[1].label]
    g = 1e-6
    return [
        f"| process | {trees[0].label} M instructions per rig s | this tree | ratio |",
        "| --- | ---: | ---: | ---: |",
        f"| the sim's own | {ro * g:.1f} | {ho * g:.1f} | {ho / ro:.3f} |",
        f"| its worker | {rw * g:.1f} | {hw * g:.1f} | {hw / rw if rw else float('nan'):.3f} |",
        f"| both | {(ro + rw) * g:.1f} | {(ho + hw) * g:.1f} | {(ho + hw) / (ro + rw):.3f} |",
    ]


def profile_top(tree: Path, hil_args: list[str], tmp: Path, n: int) -> list[str]:
    """cProfile of one ``hil ...`` run by ``tree``: the top ``n`` functions by own time.

    The profiler's clock is the process's CPU time, not the wall clock: on a shared machine a
    wall-clock profile charges a function for the time the process waited for a core.
    """
    out = tmp / f"{tree.name}.prof"
    code = (
        "import cProfile, sys, time; from hil.cli import main; sys.argv = ['hil', *sys.argv[2:]]; "
        "p = cProfile.Profile(time.process_time); rc = p.runcall(main); p.dump_stats(sys.argv_out)"
    )
    code = code.replace("sys.argv_out", repr(str(out)))
    _cpu_of(tree, ["-c", code, "--", *hil_args])
    st = pstats.Stats(str(out))
    total = st.total_tt  # type: ignore[attr-defined]
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:n]  # type: ignore[attr-defined]
    lines = ["| own % | cumulative % | calls | function |", "| ---: | ---: | ---: | --- |"]
    for (file, line, fn), (_cc, calls, tt, ct, _callers) in rows:
        where = file.replace(str(tree) + "/", "").split("site-packages/")[-1]
        lines.append(
            f"| {100 * tt / total:.1f} | {100 * ct / total:.1f} | {calls} | `{where}:{line}({fn})` |"
        )
    return lines


def run_profiles(
    trees: list[Tree], sim_args: list[str], rec: Path, tmp: Path, n: int
) -> list[tuple[str, list[str]]]:
    """Each tree's cProfile top ``n`` of ``hil sim`` and of ``hil rerun --core fusion`` of ``rec``."""
    out = []
    for t in trees:
        sim = ["sim", *sim_args, "--record", str(tmp / "profile.mcap"), "--quiet"]
        if t is not trees[0]:  # the profiler sees its own process only: keep the fusion in it
            sim.append("--one-process")
        one = " --one-process" if t is not trees[0] else ""
        label = f"`hil sim {' '.join(sim_args)} --record{one}`, {t.label}"
        out.append((label, profile_top(t.path, sim, tmp, n)))
    for t in trees:
        rerun = ["rerun", str(rec), "--core", "fusion", "--verify"]
        out.append((f"`hil rerun --core fusion --verify`, {t.label}", profile_top(t.path, rerun, tmp, n)))
    return out


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


def table(trees: list[Tree], rig_s: float) -> list[str]:
    ref, head = trees
    lines = [
        f"| step | {ref.label} CPU s | {ref.label} × real time | this tree CPU s | this tree × real time "
        f"| CPU ratio | {ref.label} wall s | this tree wall s | this tree × real time (wall) | wall ratio |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for step in _STEPS:
        r, h = _mean(ref.cpu[step]), _mean(head.cpu[step])
        wr, wh = _mean(ref.wall[step]), _mean(head.wall[step])
        xr = "–" if step == "start-up" else f"{rig_s / r:.2f}"
        xh = "–" if step == "start-up" else f"{rig_s / h:.2f}"
        xw = "–" if step == "start-up" else f"{rig_s / wh:.2f}"
        cpu = f"| {step} | {r:.2f} | {xr} | {h:.2f} | {xh} | {h / r:.3f} "
        lines.append(cpu + f"| {wr:.2f} | {wh:.2f} | {xw} | {wh / wr:.3f} |")
    return lines


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hil bench offline", description=__doc__)
    ap.add_argument("ref", help="the git revision to compare against (the tree before a change)")
    ap.add_argument("--scenario", default="uav_survey", help="hil sim's scenario")
    ap.add_argument("--duration", type=float, default=60.0, help="rig seconds simulated")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each tree (alternating order)")
    ap.add_argument(
        "--estimators", default="", help="hil sim's --estimators (comma-separated; default: the defaults)"
    )
    ap.add_argument(
        "--imu-rate", type=int, default=None, help="hil sim's --imu-rate (Hz; default: the scenario's)"
    )
    ap.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help="kill a run still going after S seconds and stop with exit 1 (default: 600 + 20 s per rig s)",
    )
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="add each tree's top N (cProfile)")
    ap.add_argument(
        "--instructions",
        type=float,
        default=0.0,
        metavar="S",
        help="also count each tree's instructions per rig second of an S-second sim under valgrind's "
        "cachegrind, per process (needs valgrind; ~2 s of wall time per rig second)",
    )
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    ap.add_argument("--section", default="offline", help="the docs/benchmarks.md section to write")
    a = ap.parse_args(argv)
    if a.duration <= 0 or a.repeat < 1:
        print("hil bench offline: --duration must be > 0 and --repeat >= 1", file=sys.stderr)
        return 2
    if a.instructions and a.instructions <= _COUNT_BASE_S:
        print(f"hil bench offline: --instructions needs more than {_COUNT_BASE_S:g} rig s", file=sys.stderr)
        return 2
    if a.instructions and shutil.which("valgrind") is None:
        print("hil bench offline: --instructions needs valgrind (apt install valgrind)", file=sys.stderr)
        return 2
    if a.timeout is not None and a.timeout <= 0:
        print("hil bench offline: --timeout must be > 0 seconds", file=sys.stderr)
        return 2
    if a.imu_rate is not None:
        from hil.nav.scenario import ScenarioError, load_scenario, scenario_overrides

        try:
            scenario_overrides(load_scenario(a.scenario), imu_rate_hz=a.imu_rate)
        except ScenarioError as err:
            print(f"hil bench offline: --imu-rate {a.imu_rate}: {err}", file=sys.stderr)
            return 2
    estimators = [e for e in a.estimators.split(",") if e]
    unknown = [e for e in estimators if e not in ESTIMATORS and e != FREE_INS]
    if unknown:
        print(
            f"hil bench offline: unknown estimator {unknown[0]!r} in --estimators; known: "
            f"{', '.join(sorted(ESTIMATORS))} (and {FREE_INS!r}, the free INS alone)",
            file=sys.stderr,
        )
        return 2
    head_path = Path(__file__).resolve().parents[2]
    sim_args = ["--scenario", a.scenario, "--duration", f"{a.duration:g}"]
    if estimators:
        sim_args += ["--estimators", ",".join(estimators)]
    if a.imu_rate is not None:
        sim_args += ["--imu-rate", str(a.imu_rate)]
    timeout_s = a.timeout if a.timeout is not None else 600.0 + 20.0 * a.duration
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="hil-offline-") as d:
        tmp = Path(d)
        try:
            ref_path = ref_tree(a.ref, tmp)
        except RuntimeError as err:
            print(f"hil bench offline: {err}", file=sys.stderr)
            return 2
        try:
            trees = [Tree(a.ref[:10], ref_path), Tree("this tree", head_path)]
            for t in trees:
                compile_bytecode(t.path)
                warm_kernels(t.path)
            same: list[str] = []
            differ: list[str] = []
            for i in range(a.repeat):
                recs = run_pair(trees, sim_args, tmp, i, timeout_s)
                if i == 0:
                    dr, dh, d1 = (digests(recs[k]) for k in (trees[0].label, trees[1].label, "one process"))
                    same = sorted(t for t in dr.keys() & dh.keys() if dr[t] == dh[t])
                    differ = sorted(set(dr) ^ set(dh) | {t for t in dr.keys() & dh.keys() if dr[t] != dh[t]})
                    if d1 != dh:  # the worker's file is the one-process file, byte for byte
                        differ.append("(this tree: --one-process differs from the default)")
                kept = recs.pop(trees[0].label) if i == 0 else None  # REF's first, for the rerun profiles
                for r in recs.values():
                    r.unlink()
                if kept is not None:
                    first_ref = kept
            profiles = run_profiles(trees, sim_args, first_ref, tmp, a.profile) if a.profile else []
            counted = (
                count_instructions(trees, sim_args, a.instructions, tmp, 120.0 + 10.0 * a.instructions)
                if a.instructions
                else []
            )
        except RuntimeError as err:
            print(f"hil bench offline: {err}", file=sys.stderr)
            return 1
        finally:
            remove_ref_tree(ref_path)
    body = report(a, trees, sim_args, (load0[0], os.getloadavg()[0]), same, differ, profiles, counted)
    print(body)
    if not a.no_write:
        write_section(a.section, body, command_line())
    return 1 if differ or any(t.verify_failed for t in trees) else 0


def report(
    a: argparse.Namespace,
    trees: list[Tree],
    sim_args: list[str],
    load: tuple[float, float],
    same: list[str],
    differ: list[str],
    profiles: list[tuple[str, list[str]]],
    counted: list[str] | None = None,
) -> str:
    verify = ", ".join(
        f"{t.label} {'failed ' + '/'.join(t.verify_failed) if t.verify_failed else 'bit-identical'}"
        for t in trees
    )
    which = "these estimators" if a.estimators else "every default estimator"
    lines = [
        f"`hil sim {' '.join(sim_args)} --record` ({which}, everything recorded), then "
        f"`hil rerun --core fusion|timesync --verify` of {trees[0].label}'s recording, by each tree in "
        f"turn, {a.repeat} run(s) each; × real time = {a.duration:g} rig s / CPU s of the child (user + "
        "system, with the fusion worker it reaps: all the work), and × real time (wall) = rig s / wall s "
        "(what a second core gave, when one was free); this tree's `hil sim` puts the pipeline's tail in "
        "a worker when two CPUs are available (the fusion; with a light fusion the CAN bridge, GNSS "
        "emulator and time sync too), `--one-process` keeps it in one (REF's sim anchors both rows). "
        f"Load average (1 min) {load[0]:.1f} at the start, {load[1]:.1f} at the end on "
        f"{os.cpu_count()} cores (the bench's own processes count in it): CPU time stretches when other "
        "work shares the cores, for both trees alike, so the ratios are the figure to compare.",
        "",
        *table(trees, a.duration),
        "",
        f"Recordings of the two trees: {len(same)} topics identical (log time, publish time, sequence, "
        f"payload); differing or in one only: {', '.join(differ) or 'none'}. Rerun --verify of "
        f"{trees[0].label}'s recording: {verify}.",
    ]
    if counted:
        lines += [
            "",
            f"Instructions (valgrind's cachegrind) of `hil sim` with `--duration {a.instructions:g}`, less "
            f"those of `--duration {_COUNT_BASE_S:g}` (start-up), per rig second: the work itself, whatever "
            "the machine's speed or load.",
            "",
            *counted,
        ]
    for label, top in profiles:
        lines += ["", f"cProfile of {label}, top {a.profile} by own time:"]
        lines += ["", *top]
    return "\n".join(lines)
