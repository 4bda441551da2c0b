"""hil bench campaign's conditions line says other work held the cores only when the load says so."""

from __future__ import annotations

import os

from hil.bench.campaign import _conditions


def test_a_quiet_run_is_not_blamed_on_other_work_and_a_loaded_one_is() -> None:
    cores = os.cpu_count() or 1
    quiet = _conditions([f"{cores + 0.3:.1f}", "1.8", "1.7"], killed=False, workers=2)
    loaded = _conditions(["1.0", f"{cores + 3:.1f}", f"{cores + 2:.1f}"], killed=True, workers=2)
    assert "other work held cores" not in quiet and "killed-worker" not in quiet
    assert "other work held cores" in loaded and "killed-worker" in loaded
    assert f"on {cores} cores" in quiet and "up to 2 workers" in quiet
