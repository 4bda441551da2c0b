"""ekf15 on the UAV survey (tactical IMU): accurate, consistent, deterministic."""

from __future__ import annotations

import numpy as np

from hil.bench.seeds_uav import run_uav


def test_ekf15_beats_free_ins_and_is_consistent() -> None:
    a = run_uav(60.0, 4, ("ekf15", "compvs"))
    late = a["t"] >= 20.0
    hp = np.linalg.norm(a["pos"]["ekf15"][late, :2], axis=1)
    assert np.sqrt(np.mean(hp**2)) < 3.0
    assert np.sqrt(np.mean(np.linalg.norm(a["pos"]["compvs"][late, :2], axis=1) ** 2)) < 10.0
    # NEES of 6 dof: its time mean must be near 6, not orders of magnitude off
    assert 1.0 < float(np.mean(a["nees"][late])) < 15.0


def test_ekf15_is_bit_identical_on_replay() -> None:
    a = run_uav(5.0, 4, ("ekf15",))
    b = run_uav(5.0, 4, ("ekf15",))
    assert np.array_equal(a["pos"]["ekf15"], b["pos"]["ekf15"])
