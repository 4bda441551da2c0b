"""A campaign spec is refused whole, in one line naming the key, before any task is sent."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from hil.campaign import driver
from hil.campaign.driver import DriverOptions, run_campaign
from hil.campaign.runs import derive_runs
from hil.campaign.spec import SpecError, load_spec, parse_spec, spec_from_dict
from hil.cli import main as hil_main


def _doc(**kw: Any) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "seed": 1,
        "runs": 2,
        "duration_s": 5.0,
        "configs": {"a": {"estimators": ["compvs", "ekf15"]}},
        "sim": {"scenarios": ["straight_level"]},
    }
    doc.update(kw)
    return doc


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"runz": 3}, "runz: unknown key"),
        ({"runs": 0}, "runs: must be an integer in [1, "),
        ({"runs": 2.5}, "runs: must be an integer"),
        ({"seed": -1}, "seed: must be an integer"),
        ({"duration_s": -5.0}, "duration_s: must be > 0"),
        ({"settle_s": 5.0}, "settle_s: 5 s leaves nothing"),
        ({"configs": {"a": {"estimators": ["ekf16"]}}}, "configs.a.estimators: unknown estimator 'ekf16'"),
        ({"configs": {"a": {"estimatorz": ["ekf15"]}}}, "configs.a.estimatorz: unknown key"),
        ({"configs": {"a": {"lag_s": 100.0}}}, "configs.a.lag_s: must be >= 0 and <= 60"),
        ({"configs": {"a": {"output_every": 0}}}, "configs.a.output_every: must be an integer"),
        ({"configs": {"recorded": {}}}, "configs.recorded: 'recorded' is reserved"),
        ({"configs": {}}, "configs: must define at least one"),
        ({"sim": {"scenarios": []}}, "sim.scenarios: must not be empty"),
        ({"sim": {"scenarios": ["straight_level"], "configs": ["b"]}}, "sim.configs: 'b' is not defined"),
        ({"sim": {"scenario": ["straight_level"]}}, "sim.scenario: unknown key"),
        ({"faults": {"x": {"events": [], "extra": 1}}}, "faults.x.extra: unknown key"),
        ({"rerun": {"recordings": ["a.mcap"], "verify": "yes"}}, "rerun.verify: must be true or false"),
        ({"sim": None}, "sim: must be a table"),
    ],
)
def test_refused_naming_the_key(change: dict[str, Any], key: str) -> None:
    doc = _doc(**change)
    if doc.get("sim") is None:
        doc["sim"] = "x"  # not a table
    with pytest.raises(SpecError) as err:
        spec_from_dict(doc, Path("."))
    assert str(err.value).startswith(key.split(":")[0]), str(err.value)
    assert key in str(err.value)
    assert "\n" not in str(err.value)


def test_nothing_to_run() -> None:
    with pytest.raises(SpecError, match="nothing to run"):
        spec_from_dict({"runs": 1}, Path("."))


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (
            {"sim": {"scenarios": ["straight_level", "no_such_scenario"]}},
            "sim.scenarios[1]: no built-in scenario",
        ),
        (
            {"faults": {"bad": {"events": [{"kind": "gnss_outage", "t_start_s": 5.0}]}}},
            "faults.bad.events with scenario 'straight_level': event[0] (gnss_outage) needs t_end_s",
        ),
        ({"rerun": {"recordings": ["nowhere/x.mcap"]}}, "rerun.recordings[0]: no such file or directory"),
    ],
)
def test_refused_before_any_task(
    change: dict[str, Any], key: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What needs the scenarios or the files is checked on the client, before connecting."""

    def no_cluster(*_a: Any, **_k: Any) -> Any:
        raise AssertionError("a cluster was contacted for a spec that cannot run")

    monkeypatch.setattr(driver, "connect", no_cluster)
    spec = spec_from_dict(_doc(**change), tmp_path)
    with pytest.raises(SpecError) as err:
        run_campaign(spec, DriverOptions(out_dir=tmp_path / "out", progress=False))
    assert key in str(err.value)
    assert not (tmp_path / "out").exists()


def test_spec_file_round_trips(tmp_path: Path) -> None:
    """DIR/campaign.toml (what a campaign writes) parses back to the same runs."""
    (tmp_path / "s.toml").write_text(
        'name = "c"\nseed = 7\nruns = 3\nduration_s = 5.0\n'
        '[configs.a]\nestimators = ["compvs"]\n'
        '[faults.none]\n[faults.out]\nevents = [{kind = "gnss_outage", t_start_s = 1.0, t_end_s = 2.0}]\n'
        '[sim]\nscenarios = ["straight_level"]\n'
    )
    spec = load_spec(tmp_path / "s.toml")
    again = parse_spec(spec.to_toml(), tmp_path)
    assert [r.key for r in derive_runs(again)] == [r.key for r in derive_runs(spec)]
    assert len(derive_runs(spec)) == 6


def test_cli_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "bad.toml").write_text(
        'runs = 2\n[configs.a]\nestimators = ["nope"]\n[sim]\nscenarios = ["static"]\n'
    )
    assert hil_main(["campaign", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hil: configs.a.estimators: unknown estimator 'nope'")
    assert len(err.splitlines()) == 1
    assert hil_main(["campaign", str(tmp_path / "missing.toml")]) == 2
    assert "spec: cannot read" in capsys.readouterr().err
