"""The one-vector paths of ``cross`` and ``quat_multiply`` (floats, no stack) give the bits of
their batched paths: the same products and differences, signed zeros included."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from hil.nav.attitude import quat_multiply
from hil.nav.earth import cross


@pytest.mark.parametrize(("product", "size", "seed"), [(cross, 3, 31), (quat_multiply, 4, 32)])
def test_the_product_of_one_pair_is_the_batched_product_bit_for_bit(
    product: Callable[[np.ndarray, np.ndarray], np.ndarray], size: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    a, b = (rng.normal(size=(20000, size)) * 10.0 ** rng.integers(-12, 6, size=(20000, size)) for _ in "ab")
    for x in (a, b):
        x[rng.random(size=x.shape) < 0.15] = 0.0
        x[rng.random(size=x.shape) < 0.15] = -0.0
    batched = product(a, b)
    for k in range(a.shape[0]):
        one = product(a[k], b[k])
        assert one.shape == (size,) and one.tobytes() == batched[k].tobytes(), k


def test_cross_of_one_pair_takes_sequences_too() -> None:
    assert cross([1.0, 0.0, 0.0], (0.0, 1.0, 0.0)).tolist() == [0.0, 0.0, 1.0]
