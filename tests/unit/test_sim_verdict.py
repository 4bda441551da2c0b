"""hil sim's exit code says whether the run navigated: a fusion that refused much of its IMU input
is a failed run, whatever else went well."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.cli import main


@pytest.mark.parametrize(("late", "rc"), [(900, 1), (50, 0)])
def test_hil_sim_exits_1_when_its_fusion_refused_much_of_the_imu_input(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, late: int, rc: int
) -> None:
    """A run whose fusion refused a tenth or more of its IMU samples as late went to its end and
    exited 0 (QA): its navigation had stopped. A real 2 s sim, its fusion's last counters then
    given such a refusal (the time sync no longer lets a clock step cause one in a sim)."""
    from hil.runners import sim

    real = sim.run_sim

    def run(opts: sim.SimOptions) -> sim.SimResult:
        res = real(opts)
        assert res.fusion_counts["consumed"] > 800  # the fusion's own last status, as recorded
        res.fusion_counts["dropped_late.imu"] = late
        return res

    monkeypatch.setattr(sim, "run_sim", run)
    record = tmp_path / "run.mcap"
    argv = ["sim", "--scenario", "straight_level", "--duration", "2", "--quiet", "--record", str(record)]
    assert main(argv) == rc
    out, err = capsys.readouterr()
    assert out.startswith("hil sim: 2 s of rig time") and record.is_file()
    failed = [ln for ln in err.splitlines() if ln.startswith("hil sim: FAILED:")]
    said = f"hil sim: FAILED: the fusion refused {late} IMU samples as late (dropped_late.imu)"
    assert [ln.startswith(said) for ln in failed] == ([True] if rc else [])
