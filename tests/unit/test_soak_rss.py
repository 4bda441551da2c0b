"""The soak's RSS figures: a leak moves the fitted trend, a trimmed heap's saw-tooth does not."""

from __future__ import annotations

import math

import numpy as np

from hil.bench.soak import rss_growth, rss_second_half_growth, rss_trend_growth


def _series(values: list[float], every_s: float = 10.0) -> list[tuple[float, int]]:
    return [(every_s * (k + 1), int(v)) for k, v in enumerate(values)]


def test_a_linear_leak_reads_the_same_in_every_figure() -> None:
    s = _series([60_000 + 20 * k for k in range(180)])  # 20 KiB per 10 s sample
    base, last, g = rss_growth(s)
    assert base == 60_000 + 20 * 18 and last == 60_000 + 20 * 179
    assert math.isclose(rss_trend_growth(s), g, rel_tol=1e-9)
    assert rss_second_half_growth(s) > 0


def test_a_sawtooth_without_trend_has_no_trend_but_any_single_sample_can_mislead() -> None:
    rng = np.random.default_rng(7)
    s = _series(list(60_000 + rng.uniform(-3_000, 3_000, 180)))
    assert abs(rss_trend_growth(s)) < 2.0
    # the same series, read at two single samples, can look like a 10 % leak
    low_then_high = list(s)
    low_then_high[18] = (low_then_high[18][0], 57_000)
    low_then_high[-1] = (low_then_high[-1][0], 63_000)
    assert rss_growth(low_then_high)[2] > 10.0
    assert abs(rss_trend_growth(low_then_high)) < 2.5


def test_too_few_samples_are_nan_not_an_error() -> None:
    assert math.isnan(rss_trend_growth(_series([1, 2])))
    assert math.isnan(rss_growth(_series([1]))[2])
