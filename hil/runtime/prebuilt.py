"""The navigation kernels built ahead of time (:mod:`hil.runtime.aot` builds them), found and
loaded: what :func:`hil.runtime.jit.enable` tries before numba. Apart from the builder so that
loading them imports neither numba nor :mod:`hil.runtime.jit`."""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import json
import os
import sys
import sysconfig
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

#: where the module is looked for and built: this directory, then beside the package, then the
#: user's cache
DIR_ENV = "HIL_KERNELS_DIR"
PREFIX = "hil_kernels_"
_KERNEL_SOURCES = (
    "hil/nav/strapdown.py",
    "hil/nav/kernels.py",
    "hil/estimators/compensation.py",
    "hil/nav/earth.py",
    "hil/nav/attitude.py",
    "hil/fusion/predictor.py",
    "hil/estimators/feedback.py",
    "hil/estimators/ekf15.py",
    "hil/runtime/jit.py",
    "hil/runtime/aot.py",
    "hil/runtime/prebuilt.py",
)
#: an array operand's check: its place, dimensions, C order required, written to
ArrayArg = tuple[int, int, bool, bool]


def _root() -> Path:
    return Path(__file__).resolve().parents[2]


def digest() -> str | None:
    """The kernels' sources, numba's and numpy's versions, the interpreter and the machine, in 12
    hex digits; None where numba is not installed. Reads numba's version file, not numba (whose
    import is what this module saves)."""
    spec = importlib.util.find_spec("numba")
    if spec is None or spec.origin is None:
        return None
    import numpy

    h = hashlib.sha256()
    h.update((Path(spec.origin).parent / "_version.py").read_bytes())
    h.update(f"{numpy.__version__} {sys.version} {sysconfig.get_platform()}".encode())
    h.update(_cpu().encode())
    root = _root()
    for rel in _KERNEL_SOURCES:
        h.update((root / rel).read_bytes())
    return h.hexdigest()[:12]


def _cpu() -> str:
    """This CPU's model and flags (the module is compiled for them: another CPU builds its own)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        import platform

        return platform.processor() or platform.machine()
    lines = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags", "Features", "CPU part"))]
    return "\n".join(dict.fromkeys(lines))


def directories(env: Mapping[str, str] | None = None) -> list[Path]:
    """Where the module may be: ``HIL_KERNELS_DIR``, the package's ``__pycache__``, the user's
    cache directory (the first writable one is where :func:`build` writes)."""
    env = os.environ if env is None else env
    out = [Path(env[DIR_ENV])] if env.get(DIR_ENV) else []
    out.append(Path(__file__).resolve().parent / "__pycache__")
    cache = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    out.append(Path(cache) / "hil")
    return out


def file_name(dig: str) -> str:
    return PREFIX + dig + (importlib.machinery.EXTENSION_SUFFIXES[0])


def load(
    dirs: Iterable[Path] | None = None, env: Mapping[str, str] | None = None
) -> tuple[dict[str, Callable[..., Any]], Path] | None:
    """The kernels built for these sources (by their ``hil.runtime.jit._compiled`` names, array
    operands checked) and the module's path; None when none was built for them, or it is not
    used: then numba's kernels run, said in one line on stderr whenever there is something to
    say (a module found and why it is not used, a named directory that is none; nothing where
    no module was ever built and none is named: a checkout without a C compiler).

    ``dirs``: where to look, each one named (say so where it is not a directory or cannot be
    searched); default :func:`directories` of ``env`` (the process's), of which only
    ``HIL_KERNELS_DIR`` is named (the package's ``__pycache__`` and the user's cache may well
    not exist). A module is loaded only once its size and sha256 are those its build recorded
    in its operands file: a file cut short or written over would be mapped, and read past its
    end (SIGBUS) or run as whatever it holds."""
    dig = digest()
    if dig is None:
        return None
    if dirs is None:
        env = os.environ if env is None else env
        dirs = directories(env)
        named = {dirs[0]: f"{DIR_ENV}={env[DIR_ENV]}"} if env.get(DIR_ENV) else {}
    else:
        dirs = list(dirs)
        named = {d: str(d) for d in dirs}
    notes: list[str] = []  # why a directory named gave nothing
    searched: list[Path] = []
    for d in dirs:
        path = d / file_name(dig)
        spec_path = path.with_name(PREFIX + dig + ".json")
        try:
            if not d.is_dir():
                if d in named:
                    notes.append(f"{named[d]} {'is not a directory' if d.exists() else 'does not exist'}")
                continue
            found, has_operands = path.is_file(), spec_path.is_file()
        except OSError as err:  # a directory that may not be searched (its mode, its parent's)
            notes.append(f"{named.get(d, d)} cannot be searched ({err.strerror or err})")
            continue
        searched.append(d)
        if not found:
            continue
        if not has_operands:
            _not_used(path, f"it has no operands file ({spec_path.name})")
            return None
        try:
            spec_text = spec_path.read_text()
            data = path.read_bytes()  # read once: the bytes checked are those loaded, unless replaced
            built = json.loads(spec_text)
            if not isinstance(built, dict) or not isinstance(built.get("module"), dict):
                _not_used(path, f"{spec_path.name} records no size and sha256 of it (an older builder's)")
                return None
            differs = _differs(data, built["module"])
            if differs:
                _not_used(path, differs)
                return None
            operands = built["operands"]
            spec = importlib.util.spec_from_file_location(PREFIX + dig, path)
            assert spec is not None and spec.loader is not None
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            kernels = {name: _guarded(getattr(module, name), name, a) for name, a in operands.items()}
        except (OSError, ImportError, ValueError, TypeError, AttributeError, AssertionError, KeyError) as err:
            _not_used(path, f"it does not load ({err})")
            return None
        if notes:
            _warn(f"{'; '.join(notes)}: the kernels built ahead of time in {path} are used")
        return kernels, path
    stale = _newest_other(searched)
    if stale is not None:
        notes.append(f"{stale} was built for other sources ({OTHER_SOURCES})")
    if notes:
        _warn(f"{'; '.join(notes)}: {NUMBA_USED}; {BUILD_IT}")
    return None


#: what makes another digest
OTHER_SOURCES = "a kernel edited since, or another numba, numpy, Python or CPU"
#: what runs instead
NUMBA_USED = "numba's kernels are used (compiled on a machine's first use, ~12 s)"
#: what to run for a module of these sources
BUILD_IT = "`make kernels` (python -m hil.runtime.aot) builds them for these sources"


def _warn(line: str) -> None:
    sys.stderr.write(f"hil: warning: {line}\n")


def _not_used(path: Path, why: str) -> None:
    _warn(f"{path} is not used: {why}; {NUMBA_USED}; {BUILD_IT}")


def module_record(data: bytes) -> dict[str, Any]:
    """What the builder records of the module it wrote, and the loader checks before it maps it."""
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def _differs(data: bytes, recorded: Mapping[str, Any]) -> str:
    """Why these bytes are not the module its build recorded; "" when they are."""
    if len(data) != recorded.get("bytes"):
        return f"it is {len(data)} bytes, not the {recorded.get('bytes')} built (cut short, or written over)"
    if hashlib.sha256(data).hexdigest() != recorded.get("sha256"):
        return "its sha256 is not that of the module built (written over)"
    return ""


def _newest_other(dirs: Iterable[Path]) -> Path | None:
    """The newest module for other sources in these directories (None: there is none)."""
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    found: list[tuple[float, Path]] = []
    for d in dirs:
        try:
            for entry in os.scandir(d):
                if entry.name.startswith(PREFIX) and entry.name.endswith(suffix) and entry.is_file():
                    found.append((entry.stat().st_mtime, Path(entry.path)))
        except OSError:
            continue
    return max(found)[1] if found else None


def _guarded(fn: Callable[..., Any], name: str, arrays: list[ArrayArg]) -> Callable[..., Any]:
    """``fn`` behind a check of its array operands (``TypeError`` as numba's dispatcher raises for
    operands it was not compiled for); ``fn`` itself when none is to be checked."""
    if not arrays:
        return fn
    import numpy as np

    nd, f8 = np.ndarray, np.dtype(np.float64)
    checks = [tuple(a) for a in arrays]

    def kernel(*args: Any) -> Any:
        for i, ndim, c_order, written in checks:
            a = args[i]
            if (
                type(a) is not nd
                or (a.dtype is not f8 and a.dtype != f8)
                or a.ndim != ndim
                or (c_order and not a.flags.c_contiguous)
                or (written and not a.flags.writeable)
            ):
                raise TypeError(f"{name}: operand {i} is not the array it was compiled for")
        return fn(*args)

    kernel.__name__ = kernel.__qualname__ = name
    return kernel
