"""``hil bench jit``: the fusion with its kernels compiled (``HIL_JIT=1``) against Python (``0``).

One ``hil sim --record`` (compiled, the default), then ``hil rerun --core fusion --verify`` of it
by both, alternating (Python first on even repeats), each a child process measured by its own
rusage (user + system: a busy machine slows it far less than wall time). The Python reruns verify
the compiled recording bit for bit, which is the kernels' contract (:mod:`hil.runtime.jit`). Also
timed: ``import numba`` and loading the cached kernels, which every compiled process pays
once (``--first-compile`` empties numba's cache first and times the compile).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hil.bench import command_line, write_section

_RUN = "import sys; from hil.cli import main; sys.argv[0] = 'hil'; raise SystemExit(main())"
_LOAD = (
    "import time; t = time.process_time(); from hil.runtime import jit; s = jit.enable(); "
    "print(s, time.process_time() - t)"
)
_TREE = Path(__file__).resolve().parents[2]


def _child(argv: list[str], hil_jit: str, tmp: Path) -> tuple[float, float, int, str]:
    """CPU seconds (user + system, with the children it reaped), wall seconds, exit code and the
    last line of stdout of one child."""
    env = dict(os.environ, HIL_JIT=hil_jit, PYTHONPATH=str(_TREE))
    out_path, err_path = tmp / "out.txt", tmp / "err.txt"
    with open(out_path, "wb") as out, open(err_path, "wb") as err:
        t0 = time.monotonic()
        proc = subprocess.Popen([sys.executable, *argv], cwd=_TREE, env=env, stdout=out, stderr=err)
        _pid, status, ru = os.wait4(proc.pid, 0)
        wall = time.monotonic() - t0
    rc = os.waitstatus_to_exitcode(status)
    if rc not in (0, 1):
        raise RuntimeError(
            f"{' '.join(argv[2:5])} exited {rc}: {err_path.read_text(errors='replace')[-300:]}"
        )
    lines = out_path.read_text(errors="replace").strip().splitlines()
    return ru.ru_utime + ru.ru_stime, wall, rc, lines[-1] if lines else ""


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
    loads: list[tuple[str, float]] = []
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
        sim_cpu, sim_wall, rc, _ = _child(["-c", _RUN, *sim], "1", tmp)
        if rc != 0:
            print(f"hil bench jit: hil sim exited {rc}", file=sys.stderr)
            return 1
        _cpu, _w, _rc, loaded = _child(["-c", _LOAD], "1", tmp)
        state, load_cpu = loaded.split()[0], float(loaded.split()[-1])
        rows: dict[str, list[float]] = {"0": [], "1": []}
        verified: dict[str, list[bool]] = {"0": [], "1": []}
        for i in range(a.repeat):
            for j in ("0", "1") if i % 2 == 0 else ("1", "0"):
                rerun = ["-c", _RUN, "rerun", str(rec), "--core", "fusion", "--verify"]
                cpu, _wall, rc, last = _child(rerun, j, tmp)
                rows[j].append(cpu)
                verified[j].append(rc == 0 and "VERIFY OK" in last)
        loads.append(("end", os.getloadavg()[0]))
    py, cc = sum(rows["0"]) / a.repeat, sum(rows["1"]) / a.repeat
    body = "\n".join(
        [
            f"`hil sim --scenario {a.scenario} --duration {a.duration:g} --record` with the kernels compiled "
            f"({sim_cpu:.1f} s of CPU, {sim_wall:.1f} s wall: {a.duration / sim_wall:.2f}× real time on the "
            f"wall clock, the fusion in its worker), then `hil rerun --core fusion --verify` of it with "
            f"`HIL_JIT=0` and `HIL_JIT=1`, {a.repeat} each, alternating; CPU of each child (user + system). "
            f"Load average (1 min) {load0:.1f} at the start, {loads[-1][1]:.1f} at the end on "
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
            f"Importing numba and loading the cached kernels (`jit.enable()`, state `{state}`): "
            f"{load_cpu:.2f} s of CPU per process, in the compiled figures above.",
        ]
    )
    print(body)
    if not a.no_write:
        write_section("jit", body, command_line())
    return 0 if all(verified["0"] + verified["1"]) else 1
