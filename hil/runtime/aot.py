"""The navigation kernels compiled ahead of time: one extension module, imported in a millisecond.

Loading numba's cached kernels costs every process that runs the fusion ~0.45 s before its first
input (importing numba ~0.2 s, its compiler's set-up and the 17 cached kernels ~0.25 s): an eighth
of a two-minute rerun, and of every test that starts a fusion. numba's ahead-of-time compiler
(``numba.pycc``) builds the same kernels (:func:`hil.runtime.jit._compile_kernels`, their own
Python source, callees and signatures) into a C extension that needs neither numba nor LLVM when
it loads. It is the same code generator without fast-math: no reassociation, no fused
multiply-add (its target is the generic x86-64 CPU, which has none), the same libm calls, so the
bits are the JIT's and the Python kernels' (checked when it loads, as the JIT's are, and by
``tests/unit/test_aot.py``). :mod:`hil.runtime.prebuilt` finds and loads it.

``python -m hil.runtime.aot`` builds it (``make`` does, after installing; ~10 s, a C compiler
needed). Its name carries a digest of the kernels' sources, numba's and numpy's versions and the
interpreter, so an edited kernel or an upgraded numba leaves it unused (not wrong) until it is
built again, and :func:`hil.runtime.jit.enable` loads numba's kernels as before, said in one line
on stderr (:func:`hil.runtime.prebuilt.load`). Where no module was built (no compiler, a Docker
image), nothing changes but the start-up time, and nothing is said. Its operands file records the
module's size and sha256, checked before it is loaded: a file cut short was mapped, and killed
the process that read past its end (SIGBUS).

The entry points unbox their operands without numba's type dispatch: an array of another dtype or
layout would be read as if it were right. The kernels whose callers may pass such operands and
rely on numba refusing them (``TypeError``) to run the Python one instead (the covariance
prediction, the updates, ``expm``: ``hil.runtime.jit._PLACES``) are wrapped to check their array
operands (dtype, dimensions, C order where compiled for it, writeable) and raise it as numba's
dispatcher does. The others are called as they are: their callers pass arrays they made
themselves, of the type compiled for (a compensation filter's state and its cached ``[Φ|Γ]``,
the IMU block's rows, the streams' rows), and a check on each call would cost more than the
kernel (``ramp_step``: 0.41 µs unchecked, 1.22 µs checked, 0.70 µs through numba's dispatcher)."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Mapping
from pathlib import Path

from hil.runtime.prebuilt import DIR_ENV, PREFIX, ArrayArg, digest, directories, file_name, module_record


def build(out_dir: Path | None = None, env: Mapping[str, str] | None = None) -> Path:
    """Compile every kernel (:func:`hil.runtime.jit._compile_kernels`) into the extension module
    for these sources, written (atomically, beside a JSON of each entry point's array operands
    and the module's size and sha256, which the loader checks before it maps it) to ``out_dir``,
    else ``HIL_KERNELS_DIR`` (refused, ``RuntimeError``, where it is no directory this user may
    write: not built elsewhere behind the back of whoever named it), else the first writable of
    :func:`directories`; its path. A module already there is replaced (renamed over, never
    written in place: a process that has it mapped keeps its own)."""
    import shutil
    import tempfile

    from hil.runtime import jit

    dig = digest()
    if dig is None:
        raise RuntimeError("numba is not installed: pip install numba")
    target = out_dir if out_dir is not None else _target(os.environ if env is None else env)
    target.mkdir(parents=True, exist_ok=True)
    numba = jit._import_numba()
    from numba.core import types as nbtypes
    from numba.core.codegen import AOTCPUCodegen
    from numba.pycc import CC

    compiled = jit._compile_kernels(numba)
    operands: dict[str, list[ArrayArg]] = {}  # each entry point's array operands to check
    with tempfile.TemporaryDirectory(dir=target) as tmp:
        cc = CC(PREFIX + dig)
        cc.output_dir = tmp
        cc.verbose = False
        # for this CPU, as numba's JIT compiles: its model and the features it reports (a VM may
        # hide some its model has), not the generic x86-64 (~0.3 s slower a two-minute rerun)
        cc.target_cpu = "host"
        # the kernels whose callers may pass other operands, and take the Python one for them
        checked = {key for key, _homes, fallback in jit._PLACES.values() if fallback}
        for name in sorted(compiled):  # those put in place and those the tests call (libm_square)
            sig = compiled[name].nopython_signatures[0]
            cc.export(name, sig)(compiled[name].py_func)
            arrays = [
                (i, t.ndim, t.layout == "C", t.mutable)
                for i, t in enumerate(sig.args)
                if isinstance(t, nbtypes.Array)
            ]
            operands[name] = arrays if name in checked else []
        features = AOTCPUCodegen._customize_tm_features
        AOTCPUCodegen._customize_tm_features = AOTCPUCodegen._get_host_cpu_features  # type: ignore[method-assign]
        try:
            cc.compile()
        finally:
            AOTCPUCodegen._customize_tm_features = features  # type: ignore[method-assign]
        built = Path(tmp) / file_name(dig)
        spec = Path(tmp) / (PREFIX + dig + ".json")
        spec.write_text(json.dumps({"module": module_record(built.read_bytes()), "operands": operands}))
        final = target / built.name
        os.replace(spec, target / spec.name)  # the operands first: a module is never found without
        shutil.move(str(built), str(final))
    return final


def _target(env: Mapping[str, str]) -> Path:
    """Where :func:`build` writes without ``--dir``: ``HIL_KERNELS_DIR`` (made if missing) or
    refused, else the first writable of the others."""
    dirs = directories(env)
    if not env.get(DIR_ENV):
        return _writable(dirs)
    d = dirs[0]
    why = ""
    try:
        d.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        why = "is not a directory"
    except OSError as err:
        why = f"cannot be made ({err.strerror or err})"
    if not why and not os.access(d, os.W_OK | os.X_OK):
        why = "may not be written by this user"
    if why:
        raise RuntimeError(
            f"{DIR_ENV}={env[DIR_ENV]} {why}: set it to a directory this user may write, or unset it "
            f"(then the first writable of {', '.join(map(str, dirs[1:]))})"
        )
    return d


def _writable(dirs: list[Path]) -> Path:
    for d in dirs:
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(d, os.W_OK):
            return d
    among = ", ".join(map(str, dirs))
    raise RuntimeError(f"no writable directory for the kernels among {among}: set {DIR_ENV}")


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(
        prog="python -m hil.runtime.aot",
        description="Build the navigation kernels ahead of time (a C compiler needed): every "
        "process that runs the fusion then starts ~0.45 s sooner, with the same bits.",
    )
    p.add_argument(
        "--dir",
        type=Path,
        default=None,
        help=f"where to write it (default: ${DIR_ENV}, refused if it cannot be written; unset, the first "
        "writable of the package's __pycache__ and ~/.cache/hil)",
    )
    a = p.parse_args(argv)
    try:
        path = build(a.dir)
    except Exception as err:  # no compiler, no numba: the JIT path still works
        sys.stderr.write(
            f"hil: the kernels were not built ahead of time ({type(err).__name__}: {err}); "
            "numba's cached kernels are used instead (start-up ~0.45 s slower)\n"
        )
        return 1
    sys.stdout.write(f"built {path}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
