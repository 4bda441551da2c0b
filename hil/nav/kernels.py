"""What the cores compute with numpy or CPython at IMU rate, in the forms :mod:`hil.runtime.jit`
compiles with the same bits.

numpy's ``einsum`` (:mod:`hil.nav.portable`) is what the cores multiply with in Python. Compiled
code cannot call it, so a kernel here spells out the order in which einsum adds its terms; and
where CPython and a compiler compute one expression differently, the kernel does it CPython's way.
The tests hold each compiled kernel to the Python bits on random inputs (``tests/unit/test_jit.py``):

- ``"ij,jk->ik"`` (:func:`hil.nav.portable.mm`): the reduction over ``j`` is strided, and einsum
  adds its terms one by one in ``j``'s order onto a zero.

- ``"ij,kj->ik"`` (:func:`hil.nav.portable.mmt`) on C-contiguous operands: the reduction over
  ``j`` is contiguous in both, and einsum runs numpy's SIMD dot product compiled for the x86-64
  baseline (two-lane SSE2, no FMA): two lanes (even and odd ``j``), unrolled by four with the
  last pair added first, a zero-padded tail, then the lanes' sum added onto the zero output.
  :mod:`hil.runtime.jit` checks this against einsum when it loads the kernels and keeps the
  Python one where a numpy built otherwise (wider lanes, FMA) adds differently.

- ``x**2`` (:func:`hil.nav.strapdown._sq`): CPython calls the C library's ``pow``, which is not
  ``x * x`` in about one value in a thousand; numba (LLVM) turns ``x**2`` and ``pow(x, 2.0)`` into
  ``x * x``. :func:`libm_square` calls ``pow`` through a name the compiler does not rewrite
  (``_pow``, bound by :mod:`hil.runtime.jit` to ``pow`` declared ``nobuiltin``).

- ``math.hypot`` (:func:`ecef_to_lla_one`): compiled, the C library's ``hypot``, which is what
  numpy's ``np.hypot`` in the Python one calls (CPython's own ``math.hypot`` is another algorithm).

- numpy's reductions and Python's int conversions (:func:`expm`): a column sum adds in row order
  from the first entry, ``max`` lets a NaN win, and where ``math.ceil`` or ``float(2**s)`` would
  raise in Python the kernel raises the same exception.

Only ever run compiled: in Python these loops are slower than the einsum forms they copy.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from hil.nav.earth import A_M, B_M, E2, EP2
from hil.nav.types import F64

#: Whether :mod:`hil.runtime.jit` has put the compiled kernels in place in this process (the
#: fusion's status counts it as ``kernels.compiled``).
compiled = False
#: Whether they came from the module built ahead of time (``hil.runtime.aot``), not numba's
#: compiler: ``kernels.ahead_of_time`` in the fusion's status (an image or a checkout that built
#: none compiles them at each start, seconds of a core)
ahead_of_time = False

_pow = math.pow  # Python's: the C library's pow, as float.__pow__ calls it; compiled: see jit


def libm_square(x: float) -> float:
    """``x**2`` with CPython's bits: ``pow(x, 2)`` of the C library."""
    return _pow(x, 2.0)


def ramp_step(m: F64, x: F64, u: F64, s: F64, h_s: float) -> None:
    """``x ← M [x; u; s]``, ``u ← u + s h``, in place: :func:`hil.estimators.compensation._ramp_step`,
    in loops (in place: two arrays built and handed back to Python cost more than the step)."""
    n, c = x.shape
    out = np.empty((n, c))
    for i in range(n):
        for k in range(c):
            acc = 0.0
            for j in range(n):
                acc += m[i, j] * x[j, k]
            acc += m[i, n] * u[k]
            acc += m[i, n + 1] * s[k]
            out[i, k] = acc
    for i in range(n):
        for k in range(c):
            x[i, k] = out[i, k]
    for k in range(c):
        u[k] = u[k] + s[k] * h_s


def filter_output(x: F64, c: F64, d: float, u: F64) -> F64:
    """:func:`hil.estimators.compensation._filter_output` in loops: ``"ij,j->i"`` of ``x.T`` (whose
    reduction is strided) adds its terms in ``j``'s order onto a zero, then ``+ d u``."""
    n, k = x.shape
    out = np.empty(k)
    for i in range(k):
        acc = 0.0
        for j in range(n):
            acc += x[j, i] * c[j]
        out[i] = acc + d * u[i]
    return out


def covariance_step(f: F64, dt_s: float, p: F64, qc: F64) -> tuple[F64, F64]:
    """:func:`hil.estimators.ekf15.covariance_step` (``Φ = I + FΔ + (FΔ)²/2``, ``Φ P Φ' + Q_c Δ``)
    in loops; ``f`` and ``p`` C-contiguous.

    ``F`` is sparse (a sixth of a 15-state one is not zero), and so is ``Φ``: the products skip
    zero terms. That keeps einsum's bits: its sums start at +0 and add ``x·y + s``, so a sum is
    never −0, and adding a ±0 product to it changes nothing -- as long as the other factor is
    finite (``0·∞`` is NaN): a term is skipped only where it is."""
    n = f.shape[0]
    fd = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            fd[i, j] = f[i, j] * dt_s
    sq = _mm(fd, fd)
    phi = np.empty((n, n))
    for i in range(n):
        for k in range(n):
            phi[i, k] = ((1.0 if i == k else 0.0) + fd[i, k]) + 0.5 * sq[i, k]
    out = _mmt(_mm(phi, p), phi)
    for i in range(n):
        for k in range(n):
            out[i, k] = out[i, k] + qc[i, k] * dt_s
    return phi, out


def _finite_rows(a: F64) -> F64:
    """Per row of ``a``, whether every entry is finite (1.0) or not (0.0)."""
    out = np.ones(a.shape[0])
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            if not math.isfinite(a[i, j]):
                out[i] = 0.0
                break
    return out


def _mm(a: F64, b: F64) -> F64:
    """``"ij,jk->ik"``: each output term added in ``j``'s order onto a zero; a zero ``a[i, j]``
    skipped where row ``j`` of ``b`` is finite (:func:`covariance_step`)."""
    n, m = a.shape
    c = b.shape[1]
    finite = _finite_rows(b)
    out = np.zeros((n, c))
    for i in range(n):
        for j in range(m):
            x = a[i, j]
            if x == 0.0 and finite[j] == 1.0:
                continue
            for k in range(c):
                out[i, k] += x * b[j, k]
    return out


def _lane_order(n: int) -> npt.NDArray[np.int64]:
    """The ``j`` of a length-``n`` reduction in the order numpy's baseline SIMD dot product takes
    them (module docstring): blocks of eight, their pairs last first, then the tail in pairs.
    Even ``j`` go to one lane, odd to the other."""
    order = np.empty(n, dtype=np.int64)
    t = 0
    j = 0
    while n - j >= 8:
        for off in (6, 7, 4, 5, 2, 3, 0, 1):
            order[t] = j + off
            t += 1
        j += 8
    while j < n:
        order[t] = j
        t += 1
        j += 1
    return order


def _mmt(a: F64, b: F64) -> F64:
    """``"ij,kj->ik"`` on C-contiguous operands, as numpy's baseline SIMD dot product adds each
    term (module docstring); a zero ``b[k, j]`` skipped where row ``i`` of ``a`` is finite."""
    n = a.shape[1]
    ni = a.shape[0]
    nk = b.shape[0]
    order = _lane_order(n)
    nz = np.empty((nk, n), dtype=np.int64)  # per row of b: its non-zero j, in the lanes' order
    count = np.zeros(nk, dtype=np.int64)
    for k in range(nk):
        c = 0
        for t in range(n):
            j = order[t]
            if b[k, j] != 0.0:
                nz[k, c] = j
                c += 1
        count[k] = c
    finite = _finite_rows(a)
    out = np.empty((ni, nk))
    for i in range(ni):
        for k in range(nk):
            l0 = 0.0
            l1 = 0.0
            if finite[i] == 1.0:
                for t in range(count[k]):
                    j = nz[k, t]
                    if j & 1:
                        l1 = a[i, j] * b[k, j] + l1
                    else:
                        l0 = a[i, j] * b[k, j] + l0
            else:
                for t in range(n):
                    j = order[t]
                    if j & 1:
                        l1 = a[i, j] * b[k, j] + l1
                    else:
                        l0 = a[i, j] * b[k, j] + l0
            out[i, k] = 0.0 + (l0 + l1)
    return out


def _inv3(a: F64) -> F64:
    """:func:`hil.nav.portable.inv` of a 3 x 3: the adjugate over the determinant, each entry
    divided as numpy divides an array by a float; a zero determinant raises as there."""
    p, q, r = a[0, 0], a[0, 1], a[0, 2]
    s, t, u = a[1, 0], a[1, 1], a[1, 2]
    v, w, x = a[2, 0], a[2, 1], a[2, 2]
    c0, c1, c2 = t * x - u * w, u * v - s * x, s * w - t * v
    det = p * c0 + q * c1 + r * c2
    if det == 0.0:
        raise np.linalg.LinAlgError("singular matrix")
    out = np.empty((3, 3))
    out[0, 0], out[0, 1], out[0, 2] = c0 / det, (r * w - q * x) / det, (q * u - r * t) / det
    out[1, 0], out[1, 1], out[1, 2] = c1 / det, (p * x - r * v) / det, (r * s - p * u) / det
    out[2, 0], out[2, 1], out[2, 2] = c2 / det, (q * v - p * w) / det, (p * t - q * s) / det
    return out


def _mv(a: F64, x: F64) -> F64:
    """``"ij,j->i"`` (:func:`hil.nav.portable.mv`) on C-contiguous operands: each row's reduction
    is contiguous in both, numpy's SIMD dot product as in :func:`_mmt`."""
    return _mmt(a, x.reshape((1, x.shape[0])))[:, 0].copy()


def kf_update(p: F64, y: F64, h: F64, r: F64) -> tuple[F64, F64, float]:
    """:func:`hil.estimators.ekf15.kf_update` (the Joseph-form update of a GNSS position or
    velocity fix) in loops, for a 3-row ``h``; operands C-contiguous. Any other ``h`` raises
    ``TypeError``, as a call with operands a kernel was not compiled for does, so the caller
    (:mod:`hil.runtime.jit`'s fallback) runs the Python one."""
    n, m = p.shape[0], h.shape[0]
    if m != 3 or h.shape[1] != n or y.shape[0] != 3 or r.shape[0] != 3 or r.shape[1] != 3:
        raise TypeError("kf_update is compiled for a 3-row measurement only")
    ph = _mmt(p, h)
    s = _mm(h, ph)
    for i in range(3):
        for j in range(3):
            s[i, j] = s[i, j] + r[i, j]
    s_inv = _inv3(s)
    v = _mv(s_inv, y)
    nis = _mmt(y.reshape((1, 3)), v.reshape((1, 3)))[0, 0]
    k = _mm(ph, s_inv)
    kh = _mm(k, h)
    ikh = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            ikh[i, j] = (1.0 if i == j else 0.0) - kh[i, j]
    return _mv(k, y), _joseph(p, ikh, k, r), nis


def _joseph(p: F64, ikh: F64, k: F64, r: F64) -> F64:
    """``(I − K H) P (I − K H)' + K R K'`` in einsum's orders, and its symmetric part as
    ``0.5 * (P+ + P+')`` makes it: the end of every Joseph-form update here."""
    n = p.shape[0]
    a = _mmt(_mm(ikh, p), ikh)
    b = _mmt(_mm(k, r), k)
    out = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.5 * ((a[i, j] + b[i, j]) + (a[j, i] + b[j, i]))
    return out


def corrector_innovation(p: F64, y: F64, r: F64) -> tuple[F64, float]:
    """:func:`hil.estimators.feedback.corrector_innovation` in loops: ``S = P_vv + R`` by the
    adjugate, the NIS as einsum's dot (:func:`kf_update`'s)."""
    s = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            s[i, j] = p[i, j] + r[i, j]
    s_inv = _inv3(s)
    v = _mv(s_inv, y)
    return s_inv, _mmt(y.reshape((1, 3)), v.reshape((1, 3)))[0, 0]


def corrector_joseph(p: F64, s_inv: F64, y: F64, r: F64) -> tuple[F64, F64]:
    """:func:`hil.estimators.feedback.corrector_joseph` in loops: ``K = P[:, :3] S⁻¹``, ``I − K H``
    as ``eye`` with ``K`` taken from its first three columns, Joseph's form in einsum's orders."""
    n = p.shape[0]
    pv = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            pv[i, j] = p[i, j]
    k = _mm(pv, s_inv)
    ikh = np.eye(n)
    for i in range(n):
        for j in range(3):
            ikh[i, j] -= k[i, j]
    return _joseph(p, ikh, k, r), _mv(k, y)


def expm(m: F64) -> F64:
    """:func:`hil.nav.portable.expm` in loops (the ZOH filters' ``e^{A h}``, at every step length
    not seen before: the IMU's stamps are ns-exact, so most are new); ``m`` C-contiguous.

    numpy's ``np.abs(m).sum(axis=0)`` adds each column's entries in row order, starting from the
    first (no pairwise summation: the reduction is not along the contiguous axis)."""
    n = m.shape[0]
    norm1 = 0.0
    for k in range(n):
        col = abs(m[0, k])
        for i in range(1, n):
            col = col + abs(m[i, k])
        if k == 0 or col > norm1 or math.isnan(col):  # numpy's max: a NaN wins
            norm1 = col
    # Python's exceptions where its int conversions fail (a non-finite or huge matrix): never a
    # garbage exponent (the fusion takes an estimator that raises out, and says why)
    s = 0
    if not norm1 <= 0.125:
        r = math.log2(norm1 / 0.125)
        if math.isnan(r):
            raise ValueError("cannot convert float NaN to integer")
        if math.isinf(r):
            raise OverflowError("cannot convert float infinity to integer")
        s = math.ceil(r)
        if s > 1023:
            raise OverflowError("int too large to convert to float")
    scale = math.ldexp(1.0, s)  # float(2**s), exactly
    a = np.empty((n, n))
    for i in range(n):
        for k in range(n):
            a[i, k] = m[i, k] / scale
    out = np.eye(n)
    term = np.eye(n)
    for k in range(1, 40):
        term = _mm(term, a)
        significant = False
        for i in range(n):
            for j in range(n):
                term[i, j] = term[i, j] / k
                if abs(term[i, j]) > abs(out[i, j]) * 1e-18:
                    significant = True
        if not significant:
            break
        for i in range(n):
            for j in range(n):
                out[i, j] = out[i, j] + term[i, j]
    for _ in range(s):
        out = _mm(out, out)
    return out


_AM2 = A_M * A_M  # CPython's A_M**2: pow of an integer-valued float, exact either way


def ecef_to_lla_one(x: float, y: float, z: float) -> tuple[float, float, float]:
    """:func:`hil.nav.earth._ecef_to_lla_one` (Bowring's start, two iterations; every published
    solution's latitude, longitude and height). ``math.hypot`` compiled is the C library's
    ``hypot``, which is numpy's ``np.hypot`` that the Python one calls (CPython's own
    ``math.hypot`` is another algorithm); ``sl**2`` is CPython's ``pow`` (:func:`libm_square`)."""
    lon = math.atan2(y, x)
    p = math.hypot(x, y)
    beta = math.atan2(z * A_M, p * B_M)
    sb, cb = math.sin(beta), math.cos(beta)
    lat = math.atan2(z + EP2 * B_M * (sb * sb * sb), p - E2 * A_M * (cb * cb * cb))
    for _ in range(2):
        sl = math.sin(lat)
        r_n = A_M / math.sqrt(1.0 - E2 * libm_square(sl))
        h = p * math.cos(lat) + z * sl - _AM2 / r_n
        lat = math.atan2(z, p * (1.0 - E2 * r_n / (r_n + h)))
    sl = math.sin(lat)
    r_n = A_M / math.sqrt(1.0 - E2 * libm_square(sl))
    h = p * math.cos(lat) + z * sl - _AM2 / r_n
    return lat, lon, h
