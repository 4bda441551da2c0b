"""hil bench ekf: ekf15's Kalman algebra against filterpy's on the same inputs."""

from __future__ import annotations

import numpy as np
import pytest

from hil.bench.ekf import FilterPyEkf15, difference, make_stream, run
from hil.estimators.ekf15 import Ekf15

pytest.importorskip("filterpy")


def test_filterpy_peer_gives_the_same_state_and_covariance() -> None:
    """Same model (Φ, Q_d, H, R), same closed loop: the algebra alone differs, so must agree to
    rounding. 20 s of uav_survey with the seed GNSS model: 8000 IMU steps, 2000 covariance
    propagations, 21 fixes of two sequential updates each."""
    s = make_stream(20.0)
    ours = Ekf15("ekf15", s.init, **s.params)
    peer = FilterPyEkf15("ekf15", s.init, **s.params)
    predicted = []
    kf_predict = peer.kf.predict
    peer.kf.predict = lambda **kw: predicted.append(kf_predict(**kw))  # type: ignore[method-assign]
    run(ours, s)
    run(peer, s)
    # every propagation was filterpy's: a peer that fell back on ours would agree to the bit
    assert len(predicted) >= 2000
    assert ours.health()["gnss_fused"] == peer.health()["gnss_fused"] == 2 * s.n_gnss
    d = difference(ours, peer)
    assert d["p_rel"] < 1e-9
    assert d["pos_m"] < 1e-9 and d["vel_mps"] < 1e-9 and d["q"] < 1e-9
    assert d["b_a"] < 1e-9 and d["b_g"] < 1e-9
    # and the updates did move the state: the comparison is not of two idle filters
    assert np.linalg.norm(ours.b_a) > 1e-5


def test_difference_sees_a_different_measurement_noise() -> None:
    """The check is sensitive: the same peer told a 10 % larger R differs far beyond 1e-9."""
    s = make_stream(5.0)
    ours = Ekf15("ekf15", s.init, **s.params)
    peer = FilterPyEkf15("ekf15", s.init, **s.params)
    run(ours, s)
    update = peer._update
    peer._update = lambda y, h, r: update(y, h, 1.1 * r)  # type: ignore[method-assign]
    run(peer, s)
    assert difference(ours, peer)["p_rel"] > 1e-4
