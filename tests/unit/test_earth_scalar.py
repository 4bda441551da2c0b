"""The one-point paths of ``lla_to_ned`` and ``ned_to_lla`` give the array path's bits exactly."""

from __future__ import annotations

import math

import numpy as np

from hil.nav import earth


def test_one_point_is_the_array_paths_bits() -> None:
    rng = np.random.default_rng(20)
    origins = [(0.9, 0.2, 100.0), (-0.6, 2.9, -30.0), (1.45, -3.0, 5000.0), (0.0, 0.0, 0.0)]
    n_checked = 0
    for o in origins:
        lat = o[0] + rng.normal(0.0, 0.01, 2000)
        lon = o[1] + rng.normal(0.0, 0.01, 2000)
        alt = o[2] + rng.normal(0.0, 300.0, 2000)
        batch = earth.lla_to_ned(lat, lon, alt, *o)  # the array path
        for i in range(0, 2000, 7):
            for a, b, c in ((float(lat[i]), float(lon[i]), float(alt[i])), (lat[i], lon[i], alt[i])):
                one = earth.lla_to_ned(a, b, c, *o)
                assert one.shape == (3,) and one.dtype == np.float64
                assert one.tobytes() == batch[i].tobytes()
            back = earth.ned_to_lla(batch[i], *o)
            ref = earth.ned_to_lla(batch[i : i + 1], *o)  # a batch of one: the array path
            assert [np.asarray(v).tobytes() for v in back] == [np.asarray(v[0]).tobytes() for v in ref]
            n_checked += 1
    assert n_checked > 1000


def test_numpys_float64_sin_and_cos_are_maths() -> None:
    """The one-point paths take sin and cos from math: numpy's float64 loops call the C
    library's, so they must agree bit for bit (arrays and scalars) wherever latitudes and
    longitudes go."""
    rng = np.random.default_rng(21)
    x = np.concatenate([rng.uniform(-3.2, 3.2, 200_000), rng.normal(0.0, 1e-4, 20_000)])
    xs = x.tolist()
    assert np.sin(x).tolist() == [math.sin(v) for v in xs]
    assert np.cos(x).tolist() == [math.cos(v) for v in xs]
    assert [float(np.sin(np.float64(v))) for v in xs[:5000]] == [math.sin(v) for v in xs[:5000]]


def test_radii_of_one_latitude_are_the_array_paths_bits() -> None:
    lat = np.random.default_rng(22).uniform(-1.57, 1.57, 20_000)
    r_m, r_n = earth.radii_of_curvature(lat)
    assert [earth.radii_of_curvature_one(v) for v in lat.tolist()] == list(
        zip(r_m.tolist(), r_n.tolist(), strict=True)
    )
