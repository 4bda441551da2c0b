"""``hil bench ready``: how long each service of ``hil up`` takes to say it is ready.

Time zero of a live run waits for every service's first ready status (``world`` picks it only
then), so the slowest service sets the rig's start-up time. This runs ``hil up`` ``--runs``
times and reads its ``ready after start`` line: seconds from the supervisor spawning each
process to the supervisor receiving its first ready status (``waiting_run`` or ``running``).
With ``--versus REF`` the same runs of another git revision alternate with this tree's, so
before/after share the machine's load (the older tree is exported with ``git archive``).

Readiness is only worth having if it is true: every run's recording is checked for the head of
each of the rig's data streams (its first message, seq 0, recorded) besides the recorder's own
completeness verdict (``replay_ready``). A recorder that said "ready" before its subscription
was declared would lose the first messages after time zero, which no seq gap shows.
"""

from __future__ import annotations

import os
import re
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from hil.bench import command_line, write_section
from hil.runtime.argtypes import OneLineParser, bounded_int, duration_s

RIG = "benchready"
_READY = re.compile(r"ready after start \(s\): (.*)$", re.M)
_CPU = re.compile(r"CPU to ready \(s\): (.*)$", re.M)  # a hil up that prints it (not older ones)
_RUN = "import sys; from hil.cli import main; sys.argv[0] = 'hil'; raise SystemExit(main())"
# What `hil service NAME --options ...` does before the service runs (the interpreter, the
# command line, every import), in a fresh process; its CPU from rusage.
_ENTRY = """
import resource, sys
import hil.runtime.service
hil.runtime.service.run_service = lambda *a, **k: 0  # the service's entry: not run here
from hil.cli import main
main(["service", NAME, "--rig", "x", "--options", "{}"])
r = resource.getrusage(resource.RUSAGE_SELF)
print(r.ru_utime + r.ru_stime)
"""
# streams that begin before the recorder listens (every service's status from its first
# instant, events) are recorded from when it joins; every other stream begins after time zero
_BEFORE_READY = ("/status/", "/event/")


@dataclass
class UpRun:
    """One ``hil up``: readiness per service and what its recording says about the heads."""

    load: float  # 1-minute load average just before the run
    ready_s: dict[str, float]
    cpu_s: dict[str, float] = field(default_factory=dict)  # the process's CPU when first seen ready
    streams: int = 0  # the rig's data streams in the recording
    heads_lost: list[str] = field(default_factory=list)  # streams whose first message is missing
    replay_ready: bool = False


@dataclass
class Side:
    label: str
    tree: Path
    runs: list[UpRun] = field(default_factory=list)
    entry_cpu: dict[str, list[float]] = field(default_factory=dict)  # service -> CPU s per try


def entry_cpu(tree: Path, service: str) -> float:
    """CPU seconds of a fresh ``hil service`` process of ``tree`` up to its service's entry."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_")}
    env["PYTHONPATH"] = str(tree)
    code = _ENTRY.replace("NAME", repr(service))
    r = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{service} ({tree}): {r.stderr.strip()[-500:]}")
    return float(r.stdout.strip())


def entry_table(sides: list[Side]) -> list[str]:
    """Median CPU to the service's entry per tree, and the ratio to the first tree."""
    names = sorted(sides[0].entry_cpu, key=lambda n: -statistics.median(sides[0].entry_cpu[n]))
    head = " | ".join(f"{s.label} CPU s" for s in sides)
    ratio = len(sides) > 1
    lines = [
        f"| service | {head} |" + (" ratio |" if ratio else ""),
        "| --- |" + " ---: |" * (len(sides) + ratio),
    ]
    for n in [*names, "total"]:
        meds = [
            sum(statistics.median(v) for v in s.entry_cpu.values())
            if n == "total"
            else statistics.median(s.entry_cpu[n])
            for s in sides
        ]
        cells = [f"{m:.3f}" for m in meds] + ([f"{meds[-1] / meds[0]:.2f}"] if ratio else [])
        lines.append(f"| {'**total**' if n == 'total' else n} | " + " | ".join(cells) + " |")
    return lines


def parse_ready(stdout: str, line: re.Pattern[str] = _READY) -> dict[str, float]:
    """``hil up``'s ``ready after start (s): recorder 1.23, world 1.10, ...`` as a dict."""
    m = line.search(stdout)
    if m is None:
        return {}
    out: dict[str, float] = {}
    for part in m[1].split(","):
        name, _, value = part.strip().rpartition(" ")
        if name:
            out[name] = float(value)
    return out


def stream_heads(path: Path, rig: str) -> tuple[int, list[str], bool]:
    """(data streams, those whose first recorded message is not seq 0, replay_ready)."""
    from hil.record.mcapio import read_session

    s = read_session(path)
    first: dict[str, int] = {}
    for r in s.records:
        if r.topic.startswith(f"hil/{rig}/") and r.topic not in first:
            first[r.topic] = r.sequence
    data = {t: q for t, q in first.items() if not any(p in t for p in _BEFORE_READY)}
    lost = sorted(t.removeprefix(f"hil/{rig}/") for t, q in data.items() if q != 0)
    return len(data), lost, bool(s.meta("completeness", "replay_ready"))


def one_up(tree: Path, tmp: Path, duration: float, scenario: str, n: int) -> UpRun:
    """``hil up`` of ``tree`` in a process of its own (``PYTHONPATH``), as a user runs it."""
    rec = tmp / f"ready-{n}.mcap"
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_")}
    env["PYTHONPATH"] = str(tree)
    load = os.getloadavg()[0]
    args = ["up", "--duration", f"{duration:g}", "--scenario", scenario, "--rig", RIG, "--record", str(rec)]
    r = subprocess.run(
        [sys.executable, "-c", _RUN, *args, "--quiet"], cwd=tree, env=env, capture_output=True, text=True
    )
    if r.returncode != 0:
        raise RuntimeError(f"hil up ({tree}) exited {r.returncode}:\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
    run = UpRun(load, parse_ready(r.stdout), parse_ready(r.stdout, _CPU))
    run.streams, run.heads_lost, run.replay_ready = stream_heads(rec, RIG)
    for p in tmp.glob(f"ready-{n}*"):
        if p.is_file():
            p.unlink()
    return run


def export_tree(ref: str, tmp: Path) -> Path:
    """REF's files in a directory of their own (``git archive``: the shared repository's
    worktrees and refs are left alone)."""
    here = Path(__file__).resolve().parents[2]
    tree = tmp / "ref"
    tree.mkdir()
    archive = subprocess.run(["git", "archive", ref], cwd=here, capture_output=True)
    if archive.returncode != 0:
        raise RuntimeError(f"cannot export {ref!r}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    return tree


def _fmt(xs: list[float]) -> tuple[str, str]:
    return (f"{statistics.median(xs):.2f}", f"{max(xs):.2f}") if xs else ("–", "–")


def table(sides: list[Side]) -> list[str]:
    """Median and max seconds to ready per service, and of the slowest (what time zero waits for)."""
    names = sorted(
        {n for s in sides for r in s.runs for n in r.ready_s},
        key=lambda n: -statistics.median([r.ready_s.get(n, 0.0) for r in sides[0].runs]),
    )
    head = " | ".join(f"{s.label} median s | {s.label} max s | {s.label} CPU s" for s in sides)
    lines = [f"| service | {head} |", "| --- |" + " ---: | ---: | ---: |" * len(sides)]
    for n in [*names, "slowest (time zero waits for it)"]:
        cells = []
        for s in sides:
            slowest = n.startswith("slowest")
            xs = (
                [max(r.ready_s.values()) for r in s.runs if r.ready_s]
                if slowest
                else [r.ready_s[n] for r in s.runs if n in r.ready_s]
            )
            cpu = [r.cpu_s[n] for r in s.runs if n in r.cpu_s]
            cells += [*_fmt(xs), f"{statistics.median(cpu):.2f}" if cpu and not slowest else "–"]
        label = f"**{n}**" if n.startswith("slowest") else n
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def checks(sides: list[Side]) -> list[str]:
    out = []
    for s in sides:
        loads = [r.load for r in s.runs]
        lost = sorted({t for r in s.runs for t in r.heads_lost})
        out.append(
            f"- {s.label}: {len(s.runs)} runs, load (1 min) before each {min(loads):.2f}–{max(loads):.2f} "
            f"(median {statistics.median(loads):.2f}); recordings replay_ready "
            f"{sum(r.replay_ready for r in s.runs)}/{len(s.runs)}; data streams recorded from their "
            f"first message: {sum(r.streams - len(r.heads_lost) for r in s.runs)} of "
            f"{sum(r.streams for r in s.runs)}" + (f" (heads lost: {', '.join(lost)})" if lost else "")
        )
    return out


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench ready", description=__doc__)
    ap.add_argument("--runs", type=bounded_int(1, 100), default=5, help="hil up runs (of each tree)")
    ap.add_argument("--duration", type=duration_s, default=3.0, help="rig seconds of each run")
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument(
        "--entry-tries",
        type=bounded_int(0, 100),
        default=7,
        help="fresh processes per service and tree timed to the service's entry (0: skip)",
    )
    ap.add_argument("--versus", default=None, metavar="REF", help="also REF's hil up, alternating")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    here = Path(__file__).resolve().parents[2]
    with tempfile.TemporaryDirectory(prefix="hil-ready-") as d:
        tmp = Path(d)
        sides = [Side("this tree", here)]
        if a.versus:
            try:
                sides.insert(0, Side(a.versus[:10], export_tree(a.versus, tmp)))
            except RuntimeError as err:
                print(f"hil bench ready: {err}", file=sys.stderr)
                return 2
        n = 0
        for i in range(a.runs):
            for s in sides if i % 2 == 0 else sides[::-1]:
                try:
                    s.runs.append(one_up(s.tree, tmp, a.duration, a.scenario, n))
                except RuntimeError as err:
                    print(f"hil bench ready: {err}", file=sys.stderr)
                    return 1
                n += 1
                print(f"{s.label} run {len(s.runs)}: {s.runs[-1].ready_s}", file=sys.stderr, flush=True)
        services = sorted({name for s in sides for r in s.runs for name in r.ready_s})
        for i in range(a.entry_tries):
            for name in services:
                for s in sides if i % 2 == 0 else sides[::-1]:
                    try:
                        s.entry_cpu.setdefault(name, []).append(entry_cpu(s.tree, name))
                    except RuntimeError as err:
                        print(f"hil bench ready: {err}", file=sys.stderr)
                        return 1
    body = "\n".join(
        [
            f"`hil up --duration {a.duration:g} --scenario {a.scenario} --quiet`, {a.runs} runs"
            + (f" of each tree, alternating ({sides[0].label} first)" if a.versus else "")
            + "; seconds from the supervisor spawning a service to its first ready status "
            "(`hil up`'s `ready after start` line); CPU s: the median of the service process's CPU "
            "seconds when the supervisor first saw it ready (`CPU to ready`, printed by `hil up` "
            "since this bench; – where the tree does not print it), which the machine's load does "
            "not stretch. Every service starts at once on this machine's "
            f"{os.cpu_count()} cores, beside whatever else runs on them (load below).",
            "",
            *table(sides),
            "",
            *checks(sides),
        ]
        + (
            [
                "",
                f"CPU seconds of a fresh `hil service NAME` process up to the service's entry (the "
                "interpreter, the command line, every import; what each service pays before it can "
                f"open its session), median of {a.entry_tries} per service and tree, alternating:",
                "",
                *entry_table(sides),
            ]
            if a.entry_tries
            else []
        )
    )
    print(body)
    if not a.no_write:
        write_section("ready", body, command_line())
    return 0
