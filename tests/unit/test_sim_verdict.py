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


def test_hil_sim_exits_1_when_its_fusion_refused_its_gnss_fixes_as_late(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """--fusion-lag below the receiver's latency (straight_level: 0.1 s) refused 170 of 199 fixes
    and exited 0, saying nothing but a latency_over_bound event (QA; uav_survey 60 s at 0.01 s:
    285 of ~300, every estimator >1.2 km off). Now a line before the run, and FAILED after it."""
    record = tmp_path / "lag.mcap"
    argv = ["sim", "--scenario", "straight_level", "--duration", "5", "--fusion-lag", "0.001", "--quiet"]
    assert main([*argv, "--record", str(record)]) == 1
    out, err = capsys.readouterr()
    assert out.startswith("hil sim: 5 s of rig time") and record.is_file()
    lines = err.splitlines()
    assert lines[0] == (
        "hil sim: warning: --fusion-lag 0.001 s is below the GNSS receiver's output latency in scenario "
        "'straight_level' (gnss.latency_s 0.1 s + jitter_s 0.002 s): the fusion will refuse its fixes "
        "as late and its estimators go without GNSS; give --fusion-lag above 0.102 s to fuse them"
    )
    failed = [ln for ln in lines if ln.startswith("hil sim: FAILED:")]
    assert len(failed) == 1 and failed[0].startswith("hil sim: FAILED: the fusion refused ")
    assert " of its 49 GNSS fixes as late (dropped_late.gnss)" in failed[0]
    assert "raise the fusion's lag (--fusion-lag, lag_s) above the receiver's latency" in failed[0]
    # hil info says it of the file, from the fusion's own counters
    assert main(["info", str(record)]) == 0
    fusion = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("fusion:")]
    assert fusion == [failed[0].replace("hil sim: FAILED: the fusion ", "fusion:    ")]


@pytest.mark.parametrize("scenario", ["straight_level", "outage"])
def test_a_normal_run_and_a_gnss_outage_exit_0_with_no_warning(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scenario: str
) -> None:
    """The default lag (0.5 s) is above the scenario's receiver latency: no warning; an outage
    is fixes that never came, not fixes refused as late: no FAILED."""
    if scenario == "outage":
        base = Path(__file__).parents[2] / "hil" / "scenarios" / "straight_level.toml"
        path = tmp_path / "outage.toml"
        event = '\n[[event]]\nkind = "gnss_outage"\nt_start_s = 1.0\nt_end_s = 4.0\n'
        path.write_text(base.read_text() + event)
        scenario = str(path)
    record = tmp_path / "run.mcap"
    argv = ["sim", "--scenario", scenario, "--duration", "5", "--quiet", "--record", str(record)]
    assert main(argv) == 0
    _out, err = capsys.readouterr()
    assert err == ""


def test_the_gnss_rule_is_a_tenth_of_the_fixes_handed_to_the_fusion() -> None:
    from hil.record.info import fusion_refusals

    base = {"consumed": 8000, "horizon_lag_ms": 500, "inputs.imu": 8000}
    assert fusion_refusals({**base, "inputs.gnss": 200, "dropped_late.gnss": 19}) == []
    (line,) = fusion_refusals({**base, "inputs.gnss": 200, "dropped_late.gnss": 20})
    assert line.startswith("refused 20 of its 200 GNSS fixes as late (dropped_late.gnss): they reached it ")
    assert "more than its lag (500 ms, horizon_lag_ms) after their time of validity" in line
    # an outage: fewer fixes, none refused
    assert fusion_refusals({**base, "inputs.gnss": 40}) == []
    # a status from before inputs.<sensor>: the IMU rule alone, as it was
    assert fusion_refusals({**base, "dropped_late.gnss": 170}) == []
    # both at once: a line each, the IMU's first
    both = fusion_refusals({**base, "dropped_late.imu": 900, "inputs.gnss": 20, "dropped_late.gnss": 20})
    assert [b.split(" as late")[0] for b in both] == [
        "refused 900 IMU samples",
        "refused 20 of its 20 GNSS fixes",
    ]


def test_a_lag_below_the_receivers_latency_is_said_for_hil_sim_and_hil_up() -> None:
    """``--fusion-lag`` (hil sim and hil up), and a fusion at its default lag (0.5 s)."""
    from dataclasses import replace

    from hil.cli import lag_warning
    from hil.nav.scenario import load_scenario

    s = load_scenario("uav_survey")  # gnss latency 0.08 s + jitter 0.005 s
    assert lag_warning(s, None) is None and lag_warning(s, 0.085) is None
    assert "will refuse its fixes as late" in (lag_warning(s, 0.01) or "")
    assert "will refuse the fixes its jitter takes past it as late" in (lag_warning(s, 0.082) or "")
    slow = replace(s, gnss=replace(s.gnss, latency_s=0.7))
    said = lag_warning(slow, None)
    assert said is not None and said.startswith("the fusion's lag (0.5 s, its default) is below the GNSS ")
    assert said.endswith("give --fusion-lag above 0.705 s to fuse them")


def test_hil_up_takes_the_fusion_lag_and_predictor_as_hil_sim_does() -> None:
    """QA (session 36): the FAILED line for GNSS refused as late says to raise --fusion-lag, which
    hil up did not have. It does now, and it reaches the fusion service's options; unset, the
    fusion's own default (nothing passed)."""
    from hil.cli import build_parser
    from hil.runtime.options import fill_options
    from hil.runtime.supervisor import UpOptions

    a = build_parser().parse_args(["up", "--fusion-lag", "0.3", "--no-output-predictor"])
    assert a.fusion_lag == 0.3 and a.no_output_predictor
    opts = fill_options("fusion", UpOptions(lag_s=a.fusion_lag, output_predictor=not a.no_output_predictor))
    assert opts["lag_s"] == 0.3 and opts["output_predictor"] is False
    assert "lag_s" not in fill_options("fusion", UpOptions())
    assert "lag_s" not in fill_options("timesync", UpOptions(lag_s=0.3))  # the fusion's alone


def test_a_lag_as_long_as_the_run_is_said() -> None:
    """QA (session 36): ``--fusion-lag 60`` on a 10 s run fused nothing (every estimator printed
    the same numbers) and said nothing."""
    from hil.cli import lag_run_warning

    said = lag_run_warning(60.0, 10.0)
    assert said is not None and said.startswith("--fusion-lag 60 s is the whole run (10 s) or more")
    assert lag_run_warning(0.5, 10.0) is None and lag_run_warning(None, 10.0) is None
    assert lag_run_warning(10.0, None) is None  # hil up without --duration: until stopped
