"""What the cores compute with numpy or CPython at IMU rate, in the forms :mod:`hil.runtime.jit`
compiles with the same bits.

numpy's ``einsum`` (:mod:`hil.nav.portable`) is what the cores multiply with in Python. Compiled
code cannot call it, so a kernel here spells out the order in which einsum adds its terms; and
where CPython and a compiler compute one expression differently, the kernel does it CPython's way.
The tests hold each compiled kernel to the Python bits on random inputs (``tests/unit/test_jit.py``):

- ``"ij,jk->ik"`` (:func:`hil.nav.portable.mm`): the reduction over ``j`` is strided, and einsum
  adds its terms one by one in ``j``'s order onto a zero.

- ``x**2`` (:func:`hil.nav.strapdown._sq`): CPython calls the C library's ``pow``, which is not
  ``x * x`` in about one value in a thousand; numba (LLVM) turns ``x**2`` and ``pow(x, 2.0)`` into
  ``x * x``. :func:`libm_square` calls ``pow`` through a name the compiler does not rewrite
  (``_pow``, bound by :mod:`hil.runtime.jit` to ``pow`` declared ``nobuiltin``).

Never called from Python: there the einsum forms and ``x**2`` are faster.
"""

from __future__ import annotations

import math

import numpy as np

from hil.nav.types import F64

#: Whether :mod:`hil.runtime.jit` has put the compiled kernels in place in this process (the
#: fusion's status counts it as ``kernels.compiled``).
compiled = False

_pow = math.pow  # Python's: the C library's pow, as float.__pow__ calls it; compiled: see jit


def libm_square(x: float) -> float:
    """``x**2`` with CPython's bits: ``pow(x, 2)`` of the C library."""
    return _pow(x, 2.0)


def ramp_step(m: F64, x: F64, u: F64, s: F64, h_s: float) -> tuple[F64, F64]:
    """``(M [x; u; s], u + s h)``: :func:`hil.estimators.compensation._ramp_step`, in loops."""
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
    u2 = np.empty(c)
    for k in range(c):
        u2[k] = u[k] + s[k] * h_s
    return out, u2
