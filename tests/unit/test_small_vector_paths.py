"""The one-vector paths of ``cross`` and ``quat_multiply`` (floats, no stack) give the bits of
their batched paths: the same products and differences, signed zeros included."""

from __future__ import annotations

import numpy as np

from hil.nav.attitude import quat_multiply
from hil.nav.earth import cross


def _operands(rng: np.random.Generator, n: int, size: int) -> np.ndarray:
    x = rng.normal(size=(n, size)) * 10.0 ** rng.integers(-12, 6, size=(n, size))
    x[rng.random(size=x.shape) < 0.15] = 0.0
    x[rng.random(size=x.shape) < 0.15] = -0.0
    return x


def test_cross_of_one_pair_is_the_batched_cross_bit_for_bit() -> None:
    rng = np.random.default_rng(31)
    a, b = _operands(rng, 20000, 3), _operands(rng, 20000, 3)
    batched = cross(a, b)
    for k in range(a.shape[0]):
        one = cross(a[k], b[k])
        assert one.shape == (3,) and one.tobytes() == batched[k].tobytes(), k
    assert cross([1.0, 0.0, 0.0], (0.0, 1.0, 0.0)).tolist() == [0.0, 0.0, 1.0]  # sequences too


def test_quat_multiply_of_one_pair_is_the_batched_product_bit_for_bit() -> None:
    rng = np.random.default_rng(32)
    p, q = _operands(rng, 20000, 4), _operands(rng, 20000, 4)
    batched = quat_multiply(p, q)
    for k in range(p.shape[0]):
        one = quat_multiply(p[k], q[k])
        assert one.shape == (4,) and one.tobytes() == batched[k].tobytes(), k
