"""``hil bench jit``: the fusion with its kernels compiled against Python (``HIL_JIT=0``), both
ways they are compiled: numba's cached kernels (``HIL_JIT=numba``) and those built ahead of time
(:mod:`hil.runtime.aot`, what ``HIL_JIT=1`` loads where ``make`` built them).

One ``hil sim --record`` (compiled, the default), then ``hil rerun --core fusion --verify`` of it
each way, in turn (the order rotated each repeat), each a child process measured by its own
rusage (:func:`hil.bench.offline.run_child`: user + system, which a busy machine slows far less
than wall time). Every rerun verifies the recording bit for bit, which is the kernels' contract
(:mod:`hil.runtime.jit`). Also timed: a process that loads the kernels each way, which every
compiled process pays once, against one that only imports the switch.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from hil.bench import command_line, write_section
from hil.bench.offline import run_child

_RUN = "import sys; from hil.cli import main; sys.argv[0] = 'hil'; raise SystemExit(main())"
# exits 3 (refused by the runner, named) unless the kernels compile: the ratio must not be Python's
_LOAD = "from hil.runtime import jit; raise SystemExit(0 if jit.enable() == 'compiled' else 3)"
_IMPORT = "import hil.runtime.jit"
_TREE = Path(__file__).resolve().parents[2]


def _source(tmp: Path) -> str:
    """Where a process of this tree takes its compiled kernels from by default
    (``hil.runtime.jit.source``)."""
    import subprocess

    code = "from hil.runtime import jit; jit.enable(); print(jit.source())"
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_")} | {"PYTHONPATH": str(_TREE)}
    res = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=tmp, capture_output=True, text=True, timeout=300
    )
    return res.stdout.strip() or f"no answer ({res.stderr.strip()[-200:]})"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hil bench jit", description=__doc__)
    ap.add_argument("--scenario", default="straight_level", help="hil sim's scenario")
    ap.add_argument("--duration", type=float, default=600.0, help="rig seconds simulated")
    ap.add_argument("--repeat", type=int, default=2, help="reruns of each kind (alternating order)")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    ap.add_argument("--section", default="jit", help="the docs/benchmarks.md section to write")
    a = ap.parse_args(argv)
    if a.duration <= 0 or a.repeat < 1:
        print("hil bench jit: --duration must be > 0 and --repeat >= 1", file=sys.stderr)
        return 2
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="hil-jit-") as d:
        tmp = Path(d)
        rec = tmp / "sim.mcap"
        sim = [
            "sim",
            "--scenario",
            a.scenario,
            "--duration",
            f"{a.duration:g}",
            "--record",
            str(rec),
            "--quiet",
        ]
        try:
            sim_cpu, sim_wall, rc = run_child(_TREE, ["-c", _RUN, *sim], {"HIL_JIT": "1"})
            if rc != 0:
                print(f"hil bench jit: hil sim exited {rc}", file=sys.stderr)
                return 1
            imported = run_child(_TREE, ["-c", _IMPORT])[0]
        except RuntimeError as err:
            print(f"hil bench jit: {err}", file=sys.stderr)
            return 1
        default = _source(tmp)
        ways = ["0", "numba"] + (["1"] if default.startswith("ahead of time") else [])
        load_cpu = {j: run_child(_TREE, ["-c", _LOAD], {"HIL_JIT": j})[0] - imported for j in ways[1:]}
        rows: dict[str, list[float]] = {j: [] for j in ways}
        walls: dict[str, list[float]] = {j: [] for j in ways}
        verified: dict[str, list[bool]] = {j: [] for j in ways}
        for i in range(a.repeat):
            for j in ways[i % len(ways) :] + ways[: i % len(ways)]:
                rerun = ["-c", _RUN, "rerun", str(rec), "--core", "fusion", "--verify"]
                cpu, wall, rc = run_child(_TREE, rerun, {"HIL_JIT": j})
                rows[j].append(cpu)
                walls[j].append(wall)
                verified[j].append(rc == 0)  # --verify exits 1 on the first differing output
    mean = {j: sum(v) / a.repeat for j, v in rows.items()}
    label = {
        "0": "Python (`HIL_JIT=0`)",
        "numba": "numba's cache (`HIL_JIT=numba`)",
        "1": "ahead of time (`HIL_JIT=1`, `make`)",
    }
    lines = [
        f"`hil sim --scenario {a.scenario} --duration {a.duration:g} --record` with the kernels compiled "
        f"({sim_cpu:.1f} s of CPU, {sim_wall:.1f} s wall: {a.duration / sim_wall:.2f}× real time on the "
        f"wall clock, the fusion in its worker), then `hil rerun --core fusion --verify` of it each way, "
        f"{a.repeat} each, in turn; CPU of each child (user + system, its worker included). Load average "
        f"(1 min) {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end on {os.cpu_count()} "
        "cores: compare the ratios.",
        "",
        "| rerun --core fusion --verify | CPU s per run | mean | × real time (CPU) | wall s per run | "
        "kernels loaded, CPU s | verified |",
        "| --- | --- | ---: | ---: | --- | ---: | --- |",
    ]
    for j in ways:
        load = f"{load_cpu[j]:.2f}" if j in load_cpu else "–"
        lines.append(
            f"| {label[j]} | {', '.join(f'{c:.2f}' for c in rows[j])} | {mean[j]:.2f} | "
            f"{a.duration / mean[j]:.2f} | {', '.join(f'{w:.2f}' for w in walls[j])} | {load} | "
            f"{'all' if all(verified[j]) else 'FAILED'} |"
        )
    ratios = [f"numba / Python **{mean['numba'] / mean['0']:.3f}**"]
    if "1" in mean:
        ratios.append(f"ahead of time / numba **{mean['1'] / mean['numba']:.3f}**")
    else:
        ratios.append(f"none built ahead of time here ({default}: `make kernels` builds them)")
    lines += [
        "",
        "CPU ratios: " + "; ".join(ratios) + ". Loading the kernels (`jit.enable()`, less importing "
        "the switch) is in the compiled figures above.",
    ]
    body = "\n".join(lines)
    print(body)
    if not a.no_write:
        write_section(a.section, body, command_line())
    return 0 if all(all(v) for v in verified.values()) else 1
