"""Small linear algebra and transcendentals that give the same bits on every x86-64 machine.

A recording made on the bench must rerun bit for bit on a laptop. Two parts of a stock numpy
stack break that, both measured on this project's golden replay (``tests/unit/test_portable``):

- ``@``, ``np.dot``, ``np.linalg`` and ``scipy.linalg`` call BLAS/LAPACK, and OpenBLAS picks its
  kernel per CPU (Haswell, SkylakeX, Zen, ...), each with its own summation order and use of
  FMA: a 3 × 3 product already differs in the last bit between kernels.
- numpy's transcendental ufuncs (``arctan2``, ``arctan``, ``arcsin``, ``tan``, ``exp``, ``log``,
  ``power``) are dispatched at run time to SIMD code per CPU (AVX-512 or AVX2), whose results
  differ in the last bit. ``sin``, ``cos``, ``sqrt``, ``hypot`` and ``+ − × ÷`` do not.

So the pure cores that produce published outputs multiply with ``einsum`` (numpy's own loops,
compiled for the baseline, never BLAS), invert 3 × 3 by the adjugate and solve larger systems
by Gauss–Jordan, both in plain arithmetic, and take
transcendentals from :mod:`math` (the C library's, the same on every machine with that libm).
At the rig's sizes ``einsum`` costs ~2.9 µs for a 15 × 15 product where BLAS costs ~1.2 µs;
the functions call its C entry directly (``np.einsum`` with ``optimize`` off does exactly
that, through a Python wrapper that cost as much as a small product).
"""

from __future__ import annotations

import math

import numpy as np

from hil.nav.types import F64

try:  # numpy's einsum without its Python wrapper (what np.einsum calls when optimize is off)
    from numpy._core.multiarray import c_einsum
except ImportError:  # pragma: no cover - numpy < 2
    from numpy.core.multiarray import c_einsum


def mm(a: F64, b: F64) -> F64:
    """``a @ b`` for 2-D ``a``, 2-D ``b``."""
    return c_einsum("ij,jk->ik", a, b)  # type: ignore[no-any-return]


def mmt(a: F64, b: F64) -> F64:
    """``a @ b.T`` without forming the transpose."""
    return c_einsum("ij,kj->ik", a, b)  # type: ignore[no-any-return]


def mv(a: F64, x: F64) -> F64:
    """``a @ x`` for 2-D ``a`` and 1-D ``x`` (a row vector times a matrix, ``x @ a``, is
    ``mv(a.T, x)``)."""
    return c_einsum("ij,j->i", a, x)  # type: ignore[no-any-return]


def dot(x: F64, y: F64) -> float:
    """``x · y`` for 1-D vectors."""
    return float(c_einsum("i,i->", x, y))


def norm(x: F64) -> float:
    """Euclidean norm of a 1-D vector."""
    return math.sqrt(dot(x, x))


def solve(a: F64, b: F64) -> F64:
    """``a⁻¹ b`` (``b`` 1-D or 2-D): 3 × 3 through :func:`inv`, larger by Gauss–Jordan
    elimination with partial pivoting.

    For the small, well-conditioned systems of the cores (innovation covariances, an
    observability matrix of order ≤ 4). Raises ``np.linalg.LinAlgError`` on a singular ``a``.
    """
    n = a.shape[0]
    vec = b.ndim == 1
    if a.shape == (3, 3):  # the cores' usual case: the closed-form inverse is exact arithmetic too
        ai = inv(a)
        return mv(ai, b) if vec else mm(ai, b)
    m = np.concatenate([np.array(a, dtype=float), np.array(b, dtype=float).reshape(n, -1)], axis=1)
    for col in range(n):
        piv = col + int(np.argmax(np.abs(m[col:, col])))
        if m[piv, col] == 0.0:
            raise np.linalg.LinAlgError("singular matrix")
        if piv != col:
            m[[col, piv]] = m[[piv, col]]
        m[col] = m[col] / m[col, col]
        for r in range(n):
            if r != col and m[r, col] != 0.0:
                m[r] = m[r] - m[r, col] * m[col]
    x = m[:, n:]
    return x[:, 0].copy() if vec else x.copy()


def inv(a: F64) -> F64:
    """``a⁻¹``: the adjugate over the determinant for 3 × 3 (the innovation covariances of a
    GNSS position or velocity fix, at 1-10 Hz; ~4x faster than elimination), else :func:`solve`."""
    if a.shape != (3, 3):
        return solve(a, np.eye(a.shape[0]))
    (p, q, r), (s, t, u), (v, w, x) = a.tolist()
    c0, c1, c2 = t * x - u * w, u * v - s * x, s * w - t * v  # cofactors of the first row
    det = p * c0 + q * c1 + r * c2
    if det == 0.0:
        raise np.linalg.LinAlgError("singular matrix")
    adj = (
        (c0, r * w - q * x, q * u - r * t),
        (c1, p * x - r * v, r * s - p * u),
        (c2, q * v - p * w, p * t - q * s),
    )
    return np.array(adj) / det


def expm(m: F64) -> F64:
    """``e^M`` by scaling and squaring of a Taylor series.

    ``M`` is scaled by 2^-s until its 1-norm is at most 1/8, the series is summed until a term
    no longer changes the sum (11 terms at that norm, for a 5 × 5 test matrix), and the
    result squared s times. For the rig's small, stable filter matrices this agrees with
    scipy's Padé ``expm`` to ~1e-15 relative, and it is a fixed sequence of plain arithmetic.
    """
    norm1 = float(np.abs(m).sum(axis=0).max())
    s = 0 if norm1 <= 0.125 else math.ceil(math.log2(norm1 / 0.125))
    a = m / float(2**s)
    n = m.shape[0]
    out = np.eye(n)
    term = np.eye(n)
    absolute = np.abs
    for k in range(1, 40):
        term = c_einsum("ij,jk->ik", term, a) / k
        if not (absolute(term) > absolute(out) * 1e-18).any():  # np.any's wrapper, without it
            break
        out = out + term
    for _ in range(s):
        out = c_einsum("ij,jk->ik", out, out)
    return out  # type: ignore[no-any-return]


_ATAN2 = np.frompyfunc(math.atan2, 2, 1)


def atan2(y: F64 | float, x: F64 | float) -> F64:
    """Elementwise ``atan2`` from :mod:`math` (numpy's own is SIMD-dispatched per CPU)."""
    return np.asarray(_ATAN2(y, x), dtype=float)
