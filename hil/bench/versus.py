"""``hil bench versus REF``: this checkout against another git revision, in one run.

A before/after figure is only honest as a ratio taken under the same load, so both revisions run
in the same session: ``hil sim`` of both at once (one per core, the order swapped each repeat),
then ``hil bench rig`` of each in turn (a live rig needs the whole machine), alternating. The
older revision runs from a temporary ``git worktree`` of REF with the same Python environment.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader

from hil.bench import command_line, write_section
from hil.runtime.argtypes import OneLineParser, bounded_int, duration_s, seconds

_RUN = "import sys; from hil.cli import main; sys.argv[0] = 'hil'; raise SystemExit(main())"
_ROW = re.compile(r"^\| (\w+) \| ([0-9.]+) \| [0-9.]+ % \|$")


@dataclass
class SimRun:
    wall_s: float
    cpu_s: float
    counts: dict[str, int]


@dataclass
class Side:
    label: str
    tree: Path
    sims: list[SimRun] = field(default_factory=list)
    rig_cpu: list[dict[str, float]] = field(default_factory=list)
    sim_extra: list[str] = field(default_factory=list)  # this side's own hil sim flags


def _env(tree: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_")}
    env["PYTHONPATH"] = str(tree)
    return env


def _hil(tree: Path, args: list[str], **kw: object) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-c", _RUN, *args], cwd=tree, env=_env(tree), **kw)  # type: ignore[call-overload]


def _topic_counts(path: Path) -> dict[str, int]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        return {}
    topics = {cid: ch.topic for cid, ch in summary.channels.items()}
    return {topics[c]: n for c, n in summary.statistics.channel_message_counts.items()}


def sims_side_by_side(sides: list[Side], sim_args: list[str], repeat: int, tmp: Path) -> None:
    """Both revisions' ``hil sim`` at once; wall and CPU time from each child's own rusage."""
    for i in range(repeat):
        order = sides if i % 2 == 0 else sides[::-1]
        procs = {}
        for s in order:
            rec = tmp / f"{s.label}-{i}.mcap"
            procs[s.label] = (
                _hil(s.tree, ["sim", *sim_args, *s.sim_extra, "--record", str(rec), "--quiet"]),
                time.perf_counter(),
                rec,
            )
        for s in order:
            proc, t0, rec = procs[s.label]
            _, status, ru = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                raise RuntimeError(f"{s.label}: hil sim exited {proc.returncode}")
            s.sims.append(SimRun(wall, ru.ru_utime + ru.ru_stime, _topic_counts(rec)))
            rec.unlink()


def rigs_in_turn(sides: list[Side], duration_s: float, scenario: str, repeat: int) -> None:
    """Each revision's ``hil bench rig`` alone on the machine, alternating, CPU per service."""
    for i in range(repeat):
        for s in sides if i % 2 == 0 else sides[::-1]:
            args = ["bench", "rig", "--duration", f"{duration_s:g}", "--scenario", scenario, "--no-write"]
            r = _hil(s.tree, args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            out, _ = r.communicate()
            if r.returncode != 0:
                raise RuntimeError(f"{s.label}: hil bench rig exited {r.returncode}")
            rows = (_ROW.match(line) for line in out.decode().splitlines())
            s.rig_cpu.append({m[1]: float(m[2]) for m in rows if m})


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


def sim_table(sides: list[Side], rig_s: float) -> list[str]:
    ref, head = sides
    lines = [
        "| revision | runs | wall s (mean) | CPU s (mean) | rig s per CPU s |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for s in sides:
        wall, cpu = _mean([r.wall_s for r in s.sims]), _mean([r.cpu_s for r in s.sims])
        lines.append(f"| {s.label} | {len(s.sims)} | {wall:.1f} | {cpu:.1f} | {rig_s / cpu:.2f} |")
    pairs = [h.cpu_s / r.cpu_s for r, h in zip(ref.sims, head.sims, strict=True)]
    lines += ["", f"CPU time {head.label}/{ref.label} per pair: " + ", ".join(f"{p:.3f}" for p in pairs)]
    lines.append(
        f"mean ratio **{_mean(pairs):.3f}** (below 1: {head.label} is faster). CPU time is the measure: "
        "wall time includes waiting for a core when the machine is busy."
    )
    a, b = ref.sims[0].counts, head.sims[0].counts
    same = sorted(t for t in a.keys() & b.keys() if a[t] == b[t])
    differ = sorted(t for t in a.keys() & b.keys() if a[t] != b[t])
    only = sorted(a.keys() ^ b.keys())
    changed = ", ".join(f"{t} ({a[t]}→{b[t]})" for t in differ) or "none"
    lines.append(
        f"Messages per topic: {len(same)} topics with equal counts; differing: {changed}; "
        f"in one only: {', '.join(only) or 'none'}."
    )
    return lines


def rig_table(sides: list[Side]) -> list[str]:
    ref, head = sides
    names = sorted({n for s in sides for run in s.rig_cpu for n in run}, key=lambda n: -_cpu(ref, n))
    lines = [
        f"| service | {ref.label} CPU s | {head.label} CPU s | ratio |",
        "| --- | ---: | ---: | ---: |",
    ]
    for n in [*names, "total"]:
        r, h = _cpu(ref, n), _cpu(head, n)
        lines.append(f"| {n} | {r:.2f} | {h:.2f} | {h / r:.3f} |" if r else f"| {n} | – | {h:.2f} | – |")
    return lines


def _cpu(side: Side, name: str) -> float:
    runs = side.rig_cpu
    return _mean([sum(run.values()) if name == "total" else run.get(name, 0.0) for run in runs])


def warm_kernels(tree: Path) -> None:
    """The tree's compiled kernels as on a machine that has run the rig before: built ahead of
    time where its revision has them (``python -m hil.runtime.aot``, as ``make`` does), else in
    numba's cache (``hil.runtime.jit``): REF's fresh worktree would otherwise compile them
    (~10 s of CPU) in its first timed run, whose mean then favoured this tree (until 2026-12-05:
    the sim rows of the sections before ``offline-session21``, where REF's cache was cold,
    carry that bias)."""
    code = "from hil.runtime import jit; jit.enable(); print(getattr(jit, 'source', lambda: '')())"
    r = subprocess.run(
        [sys.executable, "-c", code], env=_env(tree), cwd=tree, check=False, capture_output=True, text=True
    )
    if (tree / "hil" / "runtime" / "aot.py").is_file() and "ahead of time" not in r.stdout:
        # a revision with kernels built ahead of time runs them once installed (make builds
        # them): so must its fresh worktree here, or it is timed on numba's (until 2026-12-07,
        # session 37: sections with a REF after 901864e ran REF on numba's kernels)
        subprocess.run(
            [sys.executable, "-m", "hil.runtime.aot"],
            env=_env(tree),
            cwd=tree,
            check=False,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )


def ref_tree(ref: str, tmp: Path) -> Path:
    top = subprocess.run(
        ["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True, cwd=Path(__file__).parent
    )
    if top.returncode != 0:
        raise RuntimeError("hil bench versus needs a git checkout of hil (git rev-parse failed)")
    tree = tmp / "ref"
    r = subprocess.run(
        ["git", "worktree", "add", "--detach", str(tree), ref],
        capture_output=True,
        text=True,
        cwd=top.stdout.strip(),
    )
    if r.returncode != 0:
        raise RuntimeError(f"cannot check out {ref!r}: {r.stderr.strip()}")
    return tree


def remove_ref_tree(tree: Path) -> None:
    """Undo ``ref_tree`` (the worktree and git's record of it); quiet if it is already gone."""
    subprocess.run(
        ["git", "worktree", "remove", "--force", str(tree)], cwd=Path(__file__).parent, capture_output=True
    )


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench versus", description=__doc__)
    ap.add_argument("ref", help="the git revision to compare against (e.g. a commit before a change)")
    ap.add_argument("--scenario", default="uav_survey", help="hil sim's scenario")
    ap.add_argument("--duration", type=duration_s, default=300.0, help="hil sim's rig seconds")
    ap.add_argument("--repeat", type=bounded_int(1, 100), default=2, help="pairs of each")
    ap.add_argument("--rig-duration", type=seconds, default=60.0, help="hil bench rig's seconds (0: skip)")
    ap.add_argument("--rig-scenario", default="straight_level")
    ap.add_argument(
        "--this-args",
        default="",
        help="extra hil sim flags for this tree only, to ask it for the work REF does "
        "(e.g. '--feedback none --ekf-calibration none' against a tree from before those)",
    )
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    head_tree = Path(__file__).resolve().parents[2]
    with tempfile.TemporaryDirectory(prefix="hil-versus-") as d:
        tmp = Path(d)
        try:
            tree = ref_tree(a.ref, tmp)
        except RuntimeError as err:
            print(f"hil bench versus: {err}", file=sys.stderr)
            return 2
        try:
            sides = [Side(a.ref[:10], tree), Side("this tree", head_tree, sim_extra=a.this_args.split())]
            for side in sides:  # both trees' kernels compiled before anything is timed
                warm_kernels(side.tree)
            load = os.getloadavg()[0]
            sims_side_by_side(
                sides, ["--scenario", a.scenario, "--duration", f"{a.duration:g}"], a.repeat, tmp
            )
            if a.rig_duration > 0:
                rigs_in_turn(sides, a.rig_duration, a.rig_scenario, a.repeat)
        finally:
            remove_ref_tree(tree)
    lines = [
        f"`hil sim --scenario {a.scenario} --duration {a.duration:g} --record` of both revisions at once "
        f"(one per core), {a.repeat} pairs, order swapped each pair; load average before: {load:.2f}."
        + (f" This tree's sim also had `{a.this_args}`." if a.this_args else ""),
        "",
        *sim_table(sides, a.duration),
    ]
    if a.rig_duration > 0:
        lines += [
            "",
            f"`hil bench rig --duration {a.rig_duration:g} --scenario {a.rig_scenario}` of each in turn, "
            f"{a.repeat} each, alternating; CPU per service (mean):",
            "",
            *rig_table(sides),
        ]
    body = "\n".join(lines)
    print(body)
    if not a.no_write:
        write_section("versus", body, command_line())
    return 0
