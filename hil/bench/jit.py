"""``hil bench jit``: the fusion with its kernels compiled (``HIL_JIT=1``) against Python (``0``).

One ``hil sim --record`` (compiled, the default), then ``hil rerun --core fusion --verify`` of it
by both, alternating (Python first on even repeats), each a child process measured by its own
rusage (:func:`hil.bench.offline.run_child`: user + system, which a busy machine slows far less
than wall time). The Python reruns verify the compiled recording bit for bit, which is the kernels'
contract (:mod:`hil.runtime.jit`). Also timed: a process that imports numba and loads the cached
kernels, which every compiled process pays once, against one that only imports the switch.
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


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hil bench jit", description=__doc__)
    ap.add_argument("--scenario", default="straight_level", help="hil sim's scenario")
    ap.add_argument("--duration", type=float, default=600.0, help="rig seconds simulated")
    ap.add_argument("--repeat", type=int, default=2, help="reruns of each kind (alternating order)")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
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
            loaded = run_child(_TREE, ["-c", _LOAD], {"HIL_JIT": "1"})[0]
            load_cpu = loaded - run_child(_TREE, ["-c", _IMPORT])[0]
        except RuntimeError as err:
            print(f"hil bench jit: {err}", file=sys.stderr)
            return 1
        rows: dict[str, list[float]] = {"0": [], "1": []}
        verified: dict[str, list[bool]] = {"0": [], "1": []}
        for i in range(a.repeat):
            for j in ("0", "1") if i % 2 == 0 else ("1", "0"):
                rerun = ["-c", _RUN, "rerun", str(rec), "--core", "fusion", "--verify"]
                cpu, _wall, rc = run_child(_TREE, rerun, {"HIL_JIT": j})
                rows[j].append(cpu)
                verified[j].append(rc == 0)  # --verify exits 1 on the first differing output
    py, cc = sum(rows["0"]) / a.repeat, sum(rows["1"]) / a.repeat
    body = "\n".join(
        [
            f"`hil sim --scenario {a.scenario} --duration {a.duration:g} --record` with the kernels compiled "
            f"({sim_cpu:.1f} s of CPU, {sim_wall:.1f} s wall: {a.duration / sim_wall:.2f}× real time on the "
            f"wall clock, the fusion in its worker), then `hil rerun --core fusion --verify` of it with "
            f"`HIL_JIT=0` and `HIL_JIT=1`, {a.repeat} each, alternating; CPU of each child (user + system). "
            f"Load average (1 min) {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end on "
            f"{os.cpu_count()} cores: compare the ratio.",
            "",
            "| rerun --core fusion --verify | CPU s per run | mean | × real time (CPU) | verified |",
            "| --- | --- | ---: | ---: | --- |",
            f"| Python (`HIL_JIT=0`) | {', '.join(f'{c:.1f}' for c in rows['0'])} | {py:.1f} | "
            f"{a.duration / py:.2f} | {'all' if all(verified['0']) else 'FAILED'} |",
            f"| compiled (`HIL_JIT=1`) | {', '.join(f'{c:.1f}' for c in rows['1'])} | {cc:.1f} | "
            f"{a.duration / cc:.2f} | {'all' if all(verified['1']) else 'FAILED'} |",
            "",
            f"CPU ratio compiled / Python: **{cc / py:.3f}** (per pair: "
            f"{', '.join(f'{c / p:.3f}' for p, c in zip(rows['0'], rows['1'], strict=True))}). "
            f"Importing numba and loading the cached kernels (`jit.enable()` compiled them): "
            f"{load_cpu:.2f} s of CPU per process, in the compiled figures above.",
        ]
    )
    print(body)
    if not a.no_write:
        write_section("jit", body, command_line())
    return 0 if all(verified["0"] + verified["1"]) else 1
