"""Run a shell script inside user-mode-linux, where a real SocketCAN ``vcan0`` exists.

This host's kernel has no CAN; Debian's ``user-mode-linux`` is a kernel that runs as a process
and has the CAN modules. The host filesystem is the guest's root (hostfs), so the repository,
its ``.venv`` and the Python behind it work unchanged inside. ``init.sh`` brings up ``vcan0``
(FD-capable), runs the script and halts; ``linux`` always exits 0, so the outcome is read from
``rc.txt``. One slow vCPU: a syscall costs ~130 µs, Python starts in ~1 s.

    python tools/uml/uml.py -- sh -c 'candump -n 1 vcan0 & cansend vcan0 123#00; wait'
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
INIT = HERE / "init.sh"
NOXSTATE = HERE / "noxstate.py"
# glibc picks AVX/AVX-512 string routines by CPUID; with UML's FXSAVE-only fallback (see
# noxstate.py) their upper register halves are not preserved, so the guest runs without them.
GUEST_TUNABLES = (
    "glibc.cpu.hwcaps=-AVX,-AVX2,-AVX512F,-AVX512VL,-AVX512BW,-AVX512DQ,-AVX512CD,-EVEX,"
    "-AVX_Fast_Unaligned_Load,-FMA,-F16C"
)


def needs_noxstate() -> bool:
    """UML <= 6.12 panics on hosts with AMX ("ptrace set fp regs failed, errno = 14").

    ``HIL_UML_NOXSTATE=1``/``0`` forces the workaround on/off.
    """
    forced = os.environ.get("HIL_UML_NOXSTATE")
    if forced is not None:
        return forced == "1"
    try:
        return " amx_tile" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


@dataclass(frozen=True)
class UmlResult:
    rc: int  # the script's exit code; -1 if it never reported one (timeout, boot failure)
    output: str  # the script's stdout+stderr
    console: str  # the kernel console (boot problems show here)
    res_dir: Path  # where the script could leave files (it gets it as $RES)
    wall_s: float


def uml_available() -> bool:
    """True when the ``linux`` (UML) binary and its CAN modules are installed."""
    if shutil.which("linux") is None:
        return False
    mods = Path("/usr/lib/uml/modules")
    return mods.is_dir() and any(mods.glob("*/kernel/drivers/net/can/vcan.ko"))


def run_in_uml(
    script: str, *, timeout_s: float = 300.0, mem: str = "512M", res_dir: Path | None = None
) -> UmlResult:
    """Boot UML, run ``script`` (sh) with ``$RES`` pointing at a host directory, return its outcome."""
    res = Path(res_dir or tempfile.mkdtemp(prefix="hil-uml-")).resolve()
    res.mkdir(parents=True, exist_ok=True)
    test = res / "test.sh"
    test.write_text(script)
    for name in ("rc.txt", "out.txt"):
        (res / name).unlink(missing_ok=True)
    prefix: list[str] = []
    extra: list[str] = []
    if needs_noxstate():
        prefix = [sys.executable, str(NOXSTATE)]
        extra = [f"GLIBC_TUNABLES={GUEST_TUNABLES}"]
    cmd = [
        *prefix,
        "linux",
        f"mem={mem}",
        "root=/dev/root",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        f"init={INIT}",
        f"TEST={test}",
        f"RES={res}",
        *extra,
        "con=null",
        "con0=fd:0,fd:1",
    ]
    t0 = time.monotonic()
    console_path = res / "console.txt"
    with open(console_path, "wb") as console, open(os.devnull, "rb") as devnull:
        proc = subprocess.Popen(
            cmd, stdin=devnull, stdout=console, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            # SIGTERM to the linux process ends it and its helper threads/processes.
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    wall = time.monotonic() - t0
    rc_file = res / "rc.txt"
    rc = int(rc_file.read_text().strip() or -1) if rc_file.exists() else -1
    out = (res / "out.txt").read_text(errors="replace") if (res / "out.txt").exists() else ""
    return UmlResult(
        rc=rc, output=out, console=console_path.read_text(errors="replace"), res_dir=res, wall_s=wall
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="run a command inside user-mode-linux with vcan0 up")
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--mem", default="512M")
    ap.add_argument("--cwd", default=os.getcwd())
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args(argv)
    command = [c for c in args.command if c != "--"] or ["ip", "-details", "link", "show", "vcan0"]
    if not uml_available():
        sys.stderr.write("user-mode-linux is not installed: run tools/uml/install.sh\n")
        return 2
    script = f"cd {shlex.quote(args.cwd)}\n{shlex.join(command)}\n"
    r = run_in_uml(script, timeout_s=args.timeout, mem=args.mem)
    sys.stdout.write(r.output)
    sys.stderr.write(f"[uml] rc={r.rc} wall={r.wall_s:.1f}s res={r.res_dir}\n")
    return r.rc if r.rc >= 0 else 3


if __name__ == "__main__":
    sys.exit(main())
