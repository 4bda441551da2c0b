"""Compiled twins of the fusion's per-IMU-sample kernels, with the bits of the Python ones.

Per IMU sample the fusion steps seven strapdown mechanisations (the free INS, the five feedback
INS and ekf15's) and every compensation filter's state; in Python a strapdown step is ~7.5 µs of
float arithmetic and ``math`` calls, a filter step ~10 µs of numpy calls on (3, 6) arrays.
:func:`enable` compiles them with numba and rebinds the module globals their callers look up:

- the strapdown's :func:`hil.nav.strapdown._step` and its rotation-vector quaternion, from their
  own Python source, unchanged (~2 µs a step), and a feedback INS's run of steps between two
  covariance predictions (:func:`hil.nav.strapdown._corrected_run`: the fusion hands its estimators
  the IMU samples since they were last read in one block, ``hil.estimators.base.ImuBlock``);
- the compensation filter's :func:`hil.estimators.compensation._ramp_step`, an einsum in Python,
  as the loop form :func:`hil.nav.kernels.ramp_step` that adds einsum's terms in einsum's order,
  and its output ``C x + D u`` (:func:`hil.estimators.compensation._filter_output`, read at every
  solution) as :func:`hil.nav.kernels.filter_output`, checked against einsum when it loads;
- the covariance prediction of ekf15 and of the feedback INS's corrector
  (:func:`hil.estimators.ekf15.covariance_step`, ``Φ P Φ' + Q``: einsum products in Python) as
  :func:`hil.nav.kernels.covariance_step`, whose products add in einsum's orders, and the
  feedback corrector's whole prediction around it and ekf15's F written in place
  (:func:`hil.estimators.feedback._corrector_prediction`,
  :func:`hil.estimators.ekf15.write_dynamics`, from their own Python source); checked against
  einsum on random operands here before it is put in place (a numpy built for wider SIMD lanes
  or FMA adds differently: then the Python one stays, said on stderr);
- ekf15's Joseph-form update of a GNSS position or velocity fix
  (:func:`hil.estimators.ekf15.kf_update`: einsum products, the 3 x 3 adjugate inverse) as
  :func:`hil.nav.kernels.kf_update` (~10 µs against ~39 for 15 states), checked the same way;
  and the feedback corrector's update of a velocity fix (:func:`hil.estimators.feedback.corrector_innovation`
  and ``corrector_joseph``, on the same products), checked the same way;
- the ZOH filters' ``e^{Ah}`` (:func:`hil.nav.portable.expm` as ``hil.estimators.lti.expm``: the
  IMU's ns stamps make most step lengths new, so it runs after every fix and clock wander) as
  :func:`hil.nav.kernels.expm` (~2 µs against ~70), checked the same way;
- the output predictor's float arithmetic (:func:`hil.fusion.predictor._advance`, a sample onto its
  running sums, :func:`hil.fusion.predictor._carry`, a horizon state carried to the newest
  sample, biases out, and :func:`hil.fusion.predictor.carry_rows`, every stream of an output
  sample carried and converted to latitude, longitude and height in one call), from their own
  Python source, unchanged;
- every published solution's latitude, longitude and height
  (:func:`hil.nav.earth._ecef_to_lla_one`) as :func:`hil.nav.kernels.ecef_to_lla_one`, checked
  the same way (it calls the C library's ``hypot``, which numpy's is);
- the strapdown's ``x**2`` as CPython computes it, the C library's ``pow``
  (:func:`hil.nav.kernels.libm_square`), where a compiler would multiply.

numba compiles without fast-math, so LLVM neither reassociates nor fuses a multiply and an add,
``math.sin``/``cos``/``tan`` call the same libm and ``sqrt`` is the IEEE one: a recording made
with the kernels compiled reruns bit for bit with them in Python and back, and each compiled
kernel gives its Python one's bits on random inputs (``tests/unit/test_jit.py``).

Where the kernels were built ahead of time for these sources (:mod:`hil.runtime.aot`, which
``make`` runs after installing) they load from that extension module and numba is not imported:
~0.1 s instead of ~0.55 s of every process that runs the fusion. ``HIL_JIT=numba`` takes numba's
kernels even then. ``HIL_JIT=0`` keeps everything in Python (numba is then not even imported).
numba's machine code is cached on disk (numba's cache: ``__pycache__`` beside the source, else the
user's cache directory, or ``NUMBA_CACHE_DIR``): the first process compiles (a few seconds), the
next ones import numba and load it (~0.6 s of CPU; numba is told there is no BLAS,
:func:`_import_numba`). Where no cache directory is writable, every process compiles.
The runners call :func:`enable` before they build the fusion (``hil sim``, ``hil rerun``, and so a
campaign's runs); the live fusion service starts :func:`enable_in_background` before it reports
ready, and its core runs the Python kernels until the compiled ones are in place -- the same bits,
so nothing depends on when that happens. The fusion's own (pure) code knows nothing of this: it
calls the module functions it always called. Here, not in :mod:`hil.nav`, because it reads the
environment and files and may start a thread.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import sys
import threading
import types
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from hil.runtime import prebuilt
from hil.runtime.heap import freeze_startup, offline_collector

JIT_ENV = "HIL_JIT"

#: What was done, for the fusion's status: "compiled", "compiled (<kernels> in Python)" (a kernel that did
#: not give the Python one's bits here), "python (HIL_JIT=0)", "python (<why>)".
_state: str | None = None
#: The Python kernels :func:`enable` replaced, by name (the reference the tests hold it to).
_python: dict[str, Callable[..., Any]] = {}
_lock = threading.Lock()
#: The compiled kernels by name (``libm_square``, ``_rotvec_quat``, ``_step``, ``_corrected_run``,
#: ``ramp_step``, ``_advance``, ``_carry``, ``covariance_step``, ``_corrector_prediction``,
#: ``write_dynamics``, ``expm``, ``kf_update``, ``corrector_innovation``, ``corrector_joseph``,
#: ``ecef_to_lla_one``).
_compiled: dict[str, Any] = {}


#: ``HIL_JIT=numba``: numba's kernels even where a module was built ahead of time
_NUMBA_ONLY = "numba"
#: where the compiled kernels came from: "ahead of time (<module path>)", "numba's cache"
_source = ""


def source() -> str:
    """Where this process's compiled kernels came from ("" when they are not compiled)."""
    return _source


def _wanted(env: Mapping[str, str]) -> tuple[bool, str]:
    value = env.get(JIT_ENV, "").strip().lower()
    if value in ("", "1", "on", "yes", "true"):
        return True, ""
    if value == _NUMBA_ONLY:
        return True, _NUMBA_ONLY
    if value in ("0", "off", "no", "false"):
        return False, f"python ({JIT_ENV}={value})"
    sys.stderr.write(
        f"hil: warning: {JIT_ENV}={value!r} is not 0, 1 or {_NUMBA_ONLY}; the navigation kernels are "
        f"compiled (set {JIT_ENV}=0 to keep them in Python)\n"
    )
    return True, ""


def _sources_digest(numba: Any) -> str:
    """A digest of every file whose code the kernels compile or inline, and of numba's version.

    numba's cache keys an entry on its own function's file and bytecode only: a kernel that calls
    another (``_step`` calls ``_sq``) would keep the old callee's machine code after an edit of the
    callee alone. The digest goes into each compiled twin's name, so any edit compiles anew."""
    from hil.estimators import compensation, ekf15, feedback
    from hil.fusion import predictor
    from hil.nav import attitude, earth, kernels, strapdown

    h = hashlib.sha256(numba.__version__.encode())
    kernel_sources = (strapdown, kernels, compensation, earth, attitude, predictor, feedback, ekf15)
    for mod in (*kernel_sources, sys.modules[__name__]):
        h.update(Path(str(mod.__file__)).read_bytes())
    return h.hexdigest()[:12]


def _compile(
    numba: Any, fn: Callable[..., Any], signature: str, digest: str, inline: bool = False, **callees: Any
) -> Any:
    """``fn`` compiled for ``signature``, its global names in ``callees`` bound to compiled
    kernels (numba resolves a callee at compile time and needs it compiled too); ``inline``: into
    its compiled callers (a small helper whose call would cost more than its work)."""
    g = dict(fn.__globals__)
    g.update(callees)
    twin = types.FunctionType(fn.__code__, g, fn.__name__, fn.__defaults__, fn.__closure__)
    twin.__module__, twin.__qualname__ = fn.__module__, f"{fn.__qualname__}_{digest}"
    how = "always" if inline else "never"
    try:
        return numba.njit(signature, cache=True, inline=how)(twin)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return numba.njit(signature, cache=False, inline=how)(twin)


def _import_numba() -> Any:
    """numba, told that there is no BLAS. Its array maths checks at import whether scipy's BLAS
    is there (for ``np.dot`` in compiled code) by importing ``scipy.linalg``: ~0.2 s of every
    start of a process that loads the kernels. They never call BLAS (whose sums differ by CPU:
    :mod:`hil.nav.portable`), so ``scipy.linalg`` is hidden for that import only; a later
    ``import scipy.linalg`` works as ever."""
    blocked = "scipy.linalg"
    hide = blocked not in sys.modules and "numba.np.arraymath" not in sys.modules
    if hide:
        sys.modules[blocked] = None  # type: ignore[assignment]  # import raises ImportError
    try:
        import numba
        import numba.np.arraymath  # its BLAS check runs now, with the module hidden
    finally:
        if hide and sys.modules.get(blocked, 0) is None:
            del sys.modules[blocked]
    return numba


def _libm_pow(numba: Any) -> Any:
    """``pow(x, y)`` of the C library, called as such: declared ``nobuiltin`` so that LLVM does
    not rewrite ``pow(x, 2.0)`` into ``x * x`` (not CPython's bits; :func:`hil.nav.kernels.libm_square`)."""
    from llvmlite import ir
    from numba.core import cgutils
    from numba.core import types as nbtypes

    def libm_pow(typingctx: Any, x: Any, y: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            fnty = ir.FunctionType(ir.DoubleType(), [ir.DoubleType(), ir.DoubleType()])
            fn = cgutils.get_or_insert_function(builder.module, fnty, "pow")
            fn.attributes.add("nobuiltin")
            return builder.call(fn, args)

        return nbtypes.float64(nbtypes.float64, nbtypes.float64), codegen

    return numba.extending.intrinsic(libm_pow)


def enable(env: Mapping[str, str] | None = None) -> str:
    """Compile (or load) the kernels once per process and put them in place; returns the state.
    The runners call it before they build the fusion (``hil sim``, ``hil rerun``, a campaign's
    runs); the fusion's own code does not know about it."""
    global _state
    if _state is not None:
        return _state
    with _lock:
        if _state is None:
            _state = _enable(os.environ if env is None else env)
        return _state


def enable_for_run() -> str:
    """:func:`enable`, then everything loaded so far frozen out of the collector's reach and its
    threshold raised (``hil.runtime.heap.offline_collector``): what a process that runs the
    fusion offline does before its first input (``hil sim``'s and ``hil rerun``'s workers)."""
    how = enable()
    offline_collector()
    return how


def enable_in_background(env: Mapping[str, str] | None = None) -> threading.Thread:
    """:func:`enable` in a daemon thread: a live service loads its kernels while it starts, and is
    ready without waiting for them (the first compile on a machine takes seconds). Then numba's
    objects (~80k) are frozen out of the collector's reach, as the service's start-up was
    (``hil.runtime.heap.freeze_startup``)."""

    def load() -> None:
        enable(env)
        freeze_startup()

    t = threading.Thread(target=load, name="hil-jit", daemon=True)
    t.start()
    return t


def _enable(env: Mapping[str, str]) -> str:
    global _source
    on, why = _wanted(env)
    if not on:
        return why
    from hil.nav import kernels

    built = None if why == _NUMBA_ONLY else prebuilt.load(env=env)
    lacking = sorted({key for key, _homes, _fb in _PLACES.values()} - set(built[0])) if built else []
    if built is not None and lacking:  # a module whose operands file names fewer kernels
        sys.stderr.write(f"hil: warning: {built[1]} lacks {', '.join(lacking)}; numba's kernels are used\n")
        built = None
    if built is not None:  # the module built ahead of time (hil.runtime.aot): numba not imported
        _compiled.update(built[0])
        _source = f"ahead of time ({built[1]})"
    else:
        try:
            numba = _import_numba()
        except ImportError:
            return "python (numba is not installed: pip install numba)"
        try:
            _compiled.update(_compile_kernels(numba))
        except Exception as err:  # a numba or LLVM that cannot build them: Python's kernels, said why
            sys.stderr.write(
                f"hil: warning: the navigation kernels stay in Python: {type(err).__name__}: {err}\n"
            )
            return f"python (compiling failed: {type(err).__name__})"
        _source = "numba's cache"
    for name, (_key, homes, _fallback) in _PLACES.items():
        _python.setdefault(name, _get(homes[0]))
    kernels.compiled = True
    kernels.ahead_of_time = built is not None
    kept = []
    for name, (key, homes, fallback) in _PLACES.items():
        check = _CHECKS.get(name)  # the kernels that follow numpy's loops or libm: checked here first
        differs = check(_compiled[key], _python[name]) if check is not None else ""
        if differs:
            kept.append(name)
            sys.stderr.write(
                f"hil: warning: {name} stays in Python: compiled, it differs from the Python one in "
                f"the last bits ({differs}; this numpy or C library computes otherwise)\n"
            )
            continue
        kernel = _with_fallback(_compiled[key], _python[name]) if fallback else _compiled[key]
        for home in homes:
            _put(home, kernel)
    return f"compiled ({', '.join(kept)} in Python)" if kept else "compiled"


def _compile_kernels(numba: Any) -> dict[str, Any]:
    """Every kernel compiled (or loaded from numba's cache), by its ``_compiled`` name."""
    from hil.estimators import ekf15, feedback
    from hil.nav import kernels, strapdown

    f8 = "float64"
    state16 = f"UniTuple({f8}, 16)"
    mat, vec = f"{f8}[:, :]", f"{f8}[:]"
    d = _sources_digest(numba)
    square = _compile(numba, kernels.libm_square, f"{f8}({f8})", d, _pow=_libm_pow(numba))
    rotvec = _compile(numba, strapdown._rotvec_quat, f"UniTuple({f8}, 4)({f8}, {f8}, {f8})", d)
    step = _compile(
        numba,
        strapdown._step,
        f"{state16}({state16}, {', '.join([f8] * 7)})",
        d,
        _rotvec_quat=rotvec,
        _sq=square,
    )
    t3, t9 = f"UniTuple({f8}, 3)", f"UniTuple({f8}, 9)"
    run = _compile(
        numba,
        strapdown._corrected_run,
        f"Tuple(({state16}, {t3}, {t3}, {f8}))({state16}, {f8}[:, ::1], int64, int64, "
        f"UniTuple({f8}, 6), {t9}, {t9}, {t3}, {t3}, {f8}, boolean, boolean, boolean)",
        d,
        _step=step,
    )
    ramp = _compile(numba, kernels.ramp_step, f"none({mat}, {mat}, {vec}, {vec}, {f8})", d)
    output = _compile(numba, kernels.filter_output, f"{f8}[::1]({mat}, {vec}, {f8}, {vec})", d)
    cmat = f"{f8}[:, ::1]"
    finite = _compile(numba, kernels._finite_rows, f"{f8}[::1]({cmat})", d, inline=True)
    order = _compile(numba, kernels._lane_order, "int64[::1](int64)", d, inline=True)
    mm = _compile(numba, kernels._mm, f"{cmat}({cmat}, {cmat})", d, _finite_rows=finite)
    mmt = _compile(numba, kernels._mmt, f"{cmat}({cmat}, {cmat})", d, _finite_rows=finite, _lane_order=order)
    cov = _compile(
        numba,
        kernels.covariance_step,
        f"Tuple(({cmat}, {cmat}))({cmat}, {f8}, {cmat}, {mat})",
        d,
        _mm=mm,
        _mmt=mmt,
    )
    cnb = _compile(numba, strapdown.c_nb_floats, f"UniTuple({f8}, 9)({f8}, {f8}, {f8}, {f8})", d, True)
    frame = _compile(
        numba, ekf15._frame_terms, f"UniTuple({f8}, 14)({', '.join([f8] * 9)})", d, True, c_nb_floats=cnb
    )
    blocks = _compile(
        numba,
        ekf15._write_error_blocks,
        f"{cmat}({cmat}, int64, int64, int64, int64, UniTuple({f8}, 14))",
        d,
        True,
    )
    corrector = _compile(
        numba,
        feedback._corrector_prediction,
        f"Tuple(({cmat}, {f8}, {f8}, {f8}))({', '.join([f8] * 9)}, {cmat}, {mat}, {f8}, {f8}, {f8})",
        d,
        _frame_terms=frame,
        _write_error_blocks=blocks,
        covariance_step=cov,
    )
    kron3 = _compile(numba, ekf15._kron3, f"{cmat}({f8}, {f8}, {f8})", d, True)
    ekf = _compile(
        numba,
        ekf15.write_dynamics,
        f"UniTuple({f8}, 3)({cmat}, {', '.join([f8] * 12)}, boolean, boolean, int64)",
        d,
        _frame_terms=frame,
        _write_error_blocks=blocks,
        mm=mm,
        _kron3=kron3,
    )
    expm = _compile(numba, kernels.expm, f"{cmat}({cmat})", d, _mm=mm)
    lla = _compile(
        numba, kernels.ecef_to_lla_one, f"UniTuple({f8}, 3)({f8}, {f8}, {f8})", d, libm_square=square
    )
    return dict(
        libm_square=square,
        _rotvec_quat=rotvec,
        _step=step,
        _corrected_run=run,
        ramp_step=ramp,
        filter_output=output,
        **_compile_predictor(numba, d, rotvec, lla),
        covariance_step=cov,
        _corrector_prediction=corrector,
        write_dynamics=ekf,
        expm=expm,
        **_compile_update(numba, d, mm, mmt),
        ecef_to_lla_one=lla,
    )


def _compile_predictor(numba: Any, d: str, rotvec: Any, lla: Any) -> dict[str, Any]:
    """The output predictor's kernels (:mod:`hil.fusion.predictor`): its step onto the running
    sums, the carry of one horizon state and of one sample's every stream with its geodesy
    (``lla``: the compiled ECEF to latitude, longitude, height)."""
    from hil.fusion import predictor
    from hil.nav import earth

    f8, cmat = "float64", "float64[:, ::1]"
    qmul = _compile(numba, predictor._qmul, f"UniTuple({f8}, 4)({', '.join([f8] * 8)})", d, inline=True)
    rot = _compile(numba, predictor._rot, f"UniTuple({f8}, 3)({', '.join([f8] * 7)})", d, inline=True)
    motion_callees = {"_qmul": qmul, "_rot": rot, "_rotvec_quat": rotvec}
    unbiased = _compile(
        numba,
        predictor._unbiased,
        f"UniTuple({f8}, 10)({', '.join([f8] * 17)})",
        d,
        True,
        **motion_callees,
    )
    advance = _compile(
        numba, predictor._advance, f"UniTuple({f8}, 11)({', '.join([f8] * 18)})", d, **motion_callees
    )
    carry = _compile(
        numba,
        predictor._carry,
        f"UniTuple({f8}, 10)({', '.join([f8] * 22)}, boolean, {', '.join([f8] * 6)})",
        d,
        _unbiased=unbiased,
        **motion_callees,
    )
    rows_sig = f"{cmat}({cmat}, {', '.join([f8] * 24)})"
    ecef = _compile(numba, earth.ned_to_ecef_floats, f"UniTuple({f8}, 3)({', '.join([f8] * 15)})", d, True)
    rows = _compile(
        numba, predictor.carry_rows, rows_sig, d, _carry=carry, _ecef_to_lla_one=lla, ned_to_ecef_floats=ecef
    )
    return {"_advance": advance, "_carry": carry, "carry_rows": rows}


def _compile_update(numba: Any, digest: str, mm: Any, mmt: Any) -> dict[str, Any]:
    """The Joseph-form updates of a GNSS fix on the compiled einsum-order products ``mm`` and
    ``mmt``: ekf15's of a 3-row fix (:func:`hil.nav.kernels.kf_update`) and the feedback
    corrector's of a velocity difference (its innovation and its update)."""
    from hil.nav import kernels

    f8, cmat, vec = "float64", "float64[:, ::1]", "float64[::1]"
    inv3 = _compile(numba, kernels._inv3, f"{cmat}({cmat})", digest, True)
    mv = _compile(numba, kernels._mv, f"{vec}({cmat}, {vec})", digest, True, _mmt=mmt)
    joseph_end = _compile(
        numba, kernels._joseph, f"{cmat}({cmat}, {cmat}, {cmat}, {cmat})", digest, True, _mm=mm, _mmt=mmt
    )
    products = {"_mm": mm, "_mmt": mmt, "_inv3": inv3, "_mv": mv, "_joseph": joseph_end}
    update_sig = f"Tuple(({vec}, {cmat}, {f8}))({cmat}, {vec}, {cmat}, {cmat})"
    update = _compile(numba, kernels.kf_update, update_sig, digest, **products)
    innovation_sig = f"Tuple(({cmat}, {f8}))({cmat}, {vec}, {cmat})"
    innovation = _compile(numba, kernels.corrector_innovation, innovation_sig, digest, **products)
    joseph = _compile(
        numba,
        kernels.corrector_joseph,
        f"Tuple(({cmat}, {vec}))({cmat}, {cmat}, {vec}, {cmat})",
        digest,
        **products,
    )
    return {"kf_update": update, "corrector_innovation": innovation, "corrector_joseph": joseph}


def _get(home: str) -> Any:
    module, attr = home.split(":")
    return getattr(importlib.import_module(module), attr)


def _put(home: str, value: Any) -> None:
    module, attr = home.split(":")
    setattr(importlib.import_module(module), attr, value)


def _output_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_covariance_differs`, for a compensation filter's output ``C x + D u`` (orders 1
    to 3, six channels; ``D`` zero or not, signed zeros in the state)."""
    import numpy as np

    rng = np.random.default_rng(28)
    for trial in range(300):
        n = 1 + trial % 3
        x = rng.normal(size=(n, 6)) * 10.0 ** rng.uniform(-6, 3)
        x[rng.random((n, 6)) < 0.1] = -0.0
        c, u = rng.normal(size=n), rng.normal(size=6)
        d = 0.0 if trial % 2 else float(rng.normal())
        if compiled(x, c, d, u).tobytes() != python(x, c, d, u).tobytes():
            return f"operands {trial}"
    return ""


def _lla_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_covariance_differs`, for the ECEF to latitude, longitude and height of one
    point: numpy's ``hypot`` against the C library's, ``sin``/``cos``/``atan2``/``pow``."""
    import numpy as np

    rng = np.random.default_rng(22)
    for _ in range(500):
        x, y, z = (rng.normal(0.0, 1.0, 3) * 6.4e6 * rng.uniform(0.9, 1.1)).tolist()
        if compiled(x, y, z) != python(x, y, z):
            return f"({x!r}, {y!r}, {z!r})"
    return ""


def _expm_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_covariance_differs`, for ``e^M``: the ZOH filters' ramp-hold matrices (orders 1
    to 3, steps from a nanosecond to seconds) and dense ones whose norm needs squaring."""
    import numpy as np

    rng = np.random.default_rng(21)
    for trial in range(60):
        n = 2 + trial % 7
        m = rng.normal(0.0, 1.0, (n, n)) * (rng.random((n, n)) < 0.6) * 10.0 ** rng.uniform(-9, 1)
        if trial % 3 == 0:  # [[A, B, 0], [0, 0, 1], [0, 0, 0]] h
            m[n - 2 :, :] = 0.0
            m[n - 2, n - 1] = m[0, 0] or 1e-3
            m[: n - 2, n - 1] = 0.0
        got, want = compiled(m), python(m)
        if got.tobytes() != want.tobytes():
            return f"{n} x {n}"
    return ""


def _covariance_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """Which of a few random operands the compiled covariance prediction does not give einsum's
    bytes for ("" when it does for all): sizes of every ekf15 configuration and the corrector's."""
    import numpy as np

    rng = np.random.default_rng(20)
    for n in (12, 15, 21, 24, 33, 39):
        f = rng.normal(0.0, 1.0, (n, n)) * (rng.random((n, n)) < 0.3)
        f[rng.random((n, n)) < 0.1] = -0.0
        a = rng.normal(0.0, 1.0, (n, n))
        p = a @ a.T
        qc = np.diag(rng.random(n))
        got, want = compiled(f, 0.01, p, qc), python(f, 0.01, p, qc)
        if any(g.tobytes() != w.tobytes() for g, w in zip(got, want, strict=True)):
            return f"{n} x {n}"
    return ""


def _prediction_operands(rng: Any, n: int) -> tuple[list[float], Any, Any]:
    """A unit attitude quaternion, a covariance of ``n`` states over twelve decades and a
    diagonal process noise: the operands of :func:`_corrector_differs` and :func:`_dynamics_differs`."""
    import numpy as np

    q = rng.normal(size=4)
    a = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-6, 0, size=(n, n))
    return (q / np.linalg.norm(q)).tolist(), a @ a.T, np.diag(rng.random(n) * 1e-6)


def _corrector_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_covariance_differs`, for the feedback corrector's prediction, which calls the
    compiled covariance step: where that one stays in Python, this one must too."""
    import numpy as np

    rng = np.random.default_rng(25)
    for trial in range(40):
        q, p, qc = _prediction_operands(rng, 12)
        args = (*q, *rng.normal(0.0, 0.5, 3).tolist(), 0.05, float(rng.uniform(-1.5, 1.5)))
        dv = rng.normal(0.0, 0.1, 3).tolist()
        got, want = compiled(*args, p, qc, *dv), python(*args, p, qc, *dv)
        if got[0].tobytes() != want[0].tobytes() or got[1:] != want[1:]:
            return f"operands {trial}"
    return ""


def update_operands(rng: Any, n: int, lever: bool) -> tuple[Any, Any, Any, Any]:
    """A covariance of ``n`` states over twelve decades, an innovation, a GNSS fix's ``H`` (the
    identity on 3 of the states; ``lever``: a skew block and a dense one besides, as ekf15's
    velocity row with an antenna arm) and its diagonal ``R``: the operands of
    :func:`_update_differs` and the tests."""
    import numpy as np

    a = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-6, 0, size=(n, n))
    h = np.zeros((3, n))
    h[:, 3:6] = np.eye(3)
    if lever:
        x, y, z = rng.normal(0.0, 0.5, 3).tolist()
        h[:, 6:9] = ((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0))
        h[:, 12:15] = rng.normal(0.0, 0.5, (3, 3))
    r = np.diag(rng.uniform(0.01, 4.0, 3))
    return a @ a.T + np.eye(n) * 1e-9, rng.normal(0.0, 1.0, 3), h, r


def _update_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_covariance_differs`, for ekf15's Joseph-form update of a fix (every state layout,
    with and without an antenna arm)."""
    import numpy as np

    rng = np.random.default_rng(27)
    for trial in range(36):
        n = (15, 21, 24, 27, 30, 33)[trial % 6]
        p, y, h, r = update_operands(rng, n, lever=trial % 2 == 1)
        got, want = compiled(p, y, h, r), python(p, y, h, r)
        if [got[0].tobytes(), got[1].tobytes(), got[2]] != [want[0].tobytes(), want[1].tobytes(), want[2]]:
            return f"operands {trial} ({n} states)"
    return ""


def _corrector_operands(rng: Any) -> tuple[Any, Any, Any]:
    """A 12-state covariance over twelve decades (one in four with exact zeros and -0 in it, as
    a fresh corrector's diagonal start has), an innovation and a diagonal ``R``."""
    p, y, _h, r = update_operands(rng, 12, lever=False)
    if rng.random() < 0.25:
        p[rng.random((12, 12)) < 0.2] = 0.0
        p[rng.random((12, 12)) < 0.05] = -0.0
    return p, y, r


def _corrector_innovation_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_update_differs`, for the feedback corrector's ``S⁻¹`` and NIS."""
    import numpy as np

    rng = np.random.default_rng(29)
    for trial in range(40):
        p, y, r = _corrector_operands(rng)
        got, want = compiled(p, y, r), python(p, y, r)
        if got[0].tobytes() != want[0].tobytes() or got[1] != want[1]:
            return f"operands {trial}"
    return ""


def _corrector_joseph_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_update_differs`, for the feedback corrector's Joseph-form update."""
    import numpy as np

    rng = np.random.default_rng(30)
    for trial in range(40):
        p, y, r = _corrector_operands(rng)
        s_inv = np.linalg.inv(p[0:3, 0:3] + r)
        got, want = compiled(p, s_inv, y, r), python(p, s_inv, y, r)
        if got[0].tobytes() != want[0].tobytes() or got[1].tobytes() != want[1].tobytes():
            return f"operands {trial}"
    return ""


def _dynamics_differs(compiled: Any, python: Callable[..., Any]) -> str:
    """As :func:`_corrector_differs`, for ekf15's F written in place (its gyro calibration block
    is a compiled einsum product) in every state layout: 15, with the gyro calibration, with
    both, on templates built as ekf15 builds them."""
    import numpy as np

    from hil.estimators.ekf15 import dynamics_template

    rng = np.random.default_rng(26)
    for trial in range(30):
        cal, acal = trial % 3 >= 1, trial % 3 == 2
        f_c, f_p = dynamics_template(cal, acal, 0.0), dynamics_template(cal, acal, 0.0)
        q, _p, _qc = _prediction_operands(rng, 1)
        args = (*q, *rng.normal(0.0, 0.1, 6).tolist(), 0.01, float(rng.uniform(-1.5, 1.5)))
        got = compiled(f_c, *args, cal, acal, 24 if cal else 15)
        want = python(f_p, *args, cal, acal, 24 if cal else 15)
        if got != want or f_c.tobytes() != f_p.tobytes():
            return f"operands {trial}"
    return ""


def _with_fallback(compiled: Any, python: Callable[..., Any]) -> Callable[..., Any]:
    """The compiled kernel, or the Python one for operands it was not compiled for (a matrix that
    is not C-contiguous: einsum may add those in another order too)."""

    def kernel(*args: Any) -> Any:
        try:
            return compiled(*args)
        except TypeError:  # numba: no matching definition for these operands
            return python(*args)

    kernel.__name__ = kernel.__qualname__ = python.__name__
    return kernel


#: Each kernel put in place, by the name of its Python one: the compiled kernel's key in
#: ``_compiled``, the module attributes it replaces (the first holds the Python one, the
#: reference), and whether a call with operands it was not compiled for goes to the Python one.
_PLACES: dict[str, tuple[str, tuple[str, ...], bool]] = {
    "_step": ("_step", ("hil.nav.strapdown:_step",), False),
    "_corrected_run": ("_corrected_run", ("hil.nav.strapdown:_corrected_run",), False),
    "_ramp_step": ("ramp_step", ("hil.estimators.compensation:_ramp_step",), False),
    "_filter_output": ("filter_output", ("hil.estimators.compensation:_filter_output",), False),
    "_advance": ("_advance", ("hil.fusion.predictor:_advance",), False),
    "_carry": ("_carry", ("hil.fusion.predictor:_carry",), False),
    "carry_rows": ("carry_rows", ("hil.fusion.predictor:carry_rows", "hil.fusion.core:carry_rows"), False),
    "covariance_step": (
        "covariance_step",
        ("hil.estimators.ekf15:covariance_step", "hil.estimators.feedback:covariance_step"),
        True,
    ),
    "_corrector_prediction": (
        "_corrector_prediction",
        ("hil.estimators.feedback:_corrector_prediction",),
        True,
    ),
    "write_dynamics": ("write_dynamics", ("hil.estimators.ekf15:write_dynamics",), True),
    "expm": ("expm", ("hil.estimators.lti:expm",), True),
    "kf_update": ("kf_update", ("hil.estimators.ekf15:kf_update",), True),
    "corrector_innovation": ("corrector_innovation", ("hil.estimators.feedback:corrector_innovation",), True),
    "corrector_joseph": ("corrector_joseph", ("hil.estimators.feedback:corrector_joseph",), True),
    "ecef_to_lla_one": (
        "ecef_to_lla_one",
        ("hil.nav.earth:_ecef_to_lla_one", "hil.fusion.predictor:_ecef_to_lla_one"),
        False,
    ),
}
#: The kernels checked against their Python ones before they are put in place.
_CHECKS: dict[str, Callable[[Any, Callable[..., Any]], str]] = {
    "covariance_step": _covariance_differs,
    "_corrector_prediction": _corrector_differs,
    "write_dynamics": _dynamics_differs,
    "expm": _expm_differs,
    "kf_update": _update_differs,
    "corrector_innovation": _corrector_innovation_differs,
    "corrector_joseph": _corrector_joseph_differs,
    "_filter_output": _output_differs,
    "ecef_to_lla_one": _lla_differs,
}


def python_kernel(name: str) -> Callable[..., Any]:
    """The Python kernel ``name`` (a key of ``_PLACES``) as it was before :func:`enable`."""
    return _python.get(name) or _get(_PLACES[name][1][0])  # type: ignore[no-any-return]


def compiled_kernel(name: str) -> Any:
    """The compiled kernel ``name`` (after :func:`enable` compiled them)."""
    return _compiled[name]


def state() -> str:
    """How the kernels run in this process ("not enabled": :func:`enable` was not called)."""
    return _state or "not enabled"
