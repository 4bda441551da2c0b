"""The compensation filters' one-product step gives the bits of the separate products it replaced."""

from __future__ import annotations

import numpy as np
import pytest

from hil.estimators.compensation import VS_SCHEDULE
from hil.estimators.lti import StateSpace, ZohCache, complementary3, stacked_step
from hil.nav.portable import mm


def _separate(phi: np.ndarray, x: np.ndarray, g0: np.ndarray, u: np.ndarray, g1=None, s=None) -> np.ndarray:
    """The step as it was written before: ``Φ x + Γ0 u + Γ1 s`` (product, then outer products)."""
    out = mm(phi, x) + g0[:, None] * u[None, :]
    return out if g1 is None else out + g1[:, None] * s[None, :]


@pytest.mark.parametrize("n", [1, 2, 3])
def test_stacked_step_is_bit_identical_on_random_matrices(n: int) -> None:
    rng = np.random.default_rng(20 + n)
    for _ in range(5000):
        scale = 10.0 ** rng.uniform(-9, 4, size=5)
        phi = rng.normal(size=(n, n)) * scale[0]
        g0, g1 = rng.normal(size=n) * scale[1], rng.normal(size=n) * scale[2]
        x = rng.normal(size=(n, 6)) * scale[3]
        u, s = rng.normal(size=6) * scale[4], rng.normal(size=6) * 1e-2
        m = np.concatenate((phi, g0[:, None], g1[:, None]), axis=1)
        assert np.array_equal(stacked_step(m, x, u, s), _separate(phi, x, g0, u, g1, s))
        assert np.array_equal(stacked_step(m[:, :-1].copy(), x, u), _separate(phi, x, g0, u))


def test_stacked_step_is_bit_identical_with_the_filters_own_matrices() -> None:
    rng = np.random.default_rng(7)
    tfs = [tf for _, tf in VS_SCHEDULE] + [complementary3(0.07, 0.005, 1e-4)]
    for tf in tfs:
        ss = StateSpace.from_tf(tf)
        coast_ss = StateSpace(ss.a + np.outer(ss.b, ss.c), ss.b, ss.c, 0.0)
        ramp, coast = ZohCache(ss), ZohCache(coast_ss, ramp=False)
        for h_ns in (2_500_000, 1_234_567, 5_000_000, -3_000_000):
            phi, g0, g1 = ramp.get(h_ns)
            phc, gc, _ = coast.get(h_ns)
            for _ in range(200):
                x = rng.normal(size=(ss.order, 6)) * 10.0 ** rng.uniform(-3, 3)
                u, s = rng.normal(size=6) * 30.0, rng.normal(size=6)
                assert np.array_equal(
                    stacked_step(ramp.stacked(h_ns), x, u, s), _separate(phi, x, g0, u, g1, s)
                )
                assert np.array_equal(stacked_step(coast.stacked(h_ns), x, u), _separate(phc, x, gc, u))


def test_the_cached_stacked_matrix_is_ramp_holds_side_by_side() -> None:
    """``ZohCache.stacked`` slices ``[Φ | Γ0 | Γ1]`` out of the one ``e^{M h}`` (no three copies
    joined): byte for byte ``ramp_hold``'s matrices side by side, for the ramp and the coast."""
    from hil.estimators.lti import ramp_hold

    rng = np.random.default_rng(8)
    for _, tf in [*VS_SCHEDULE, (0.0, complementary3(0.07, 0.005, 1e-4))]:
        ss = StateSpace.from_tf(tf)
        coast_ss = StateSpace(ss.a + np.outer(ss.b, ss.c), ss.b, ss.c, 0.0)
        ramp, coast = ZohCache(ss), ZohCache(coast_ss, ramp=False)
        for h_ns in [int(h) for h in rng.integers(-5_000_000, 50_000_000, 200)]:
            phi, g0, g1 = ramp_hold(ss, h_ns * 1e-9)
            want = np.concatenate((phi, g0[:, None], g1[:, None]), axis=1)
            assert ramp.stacked(h_ns).tobytes() == want.tobytes() and ramp.stacked(h_ns).shape == want.shape
            phc, gc, _ = ramp_hold(coast_ss, h_ns * 1e-9)
            want_c = np.concatenate((phc, gc[:, None]), axis=1)
            assert (
                coast.stacked(h_ns).tobytes() == want_c.tobytes()
                and coast.stacked(h_ns).shape == want_c.shape
            )
