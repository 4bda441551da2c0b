"""What a worker does with one run, in this process: statistics, failures as results, reruns."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.execute import FAILED, OK, execute_run, sim_recording
from hil.campaign.runs import RERUN, RunSpec, derive_runs
from hil.campaign.spec import spec_from_dict
from hil.record.info import estimator_errors
from hil.record.mcapio import read_session


@pytest.fixture(scope="module")
def sim_run() -> RunSpec:
    doc: dict[str, Any] = {
        "seed": 5,
        "runs": 1,
        "duration_s": 6.0,
        "configs": {"a": {"estimators": ["compvs", "ekf15"]}},
        "sim": {"scenarios": ["straight_level"]},
    }
    return derive_runs(spec_from_dict(doc, Path(".")))[0]


@pytest.fixture(scope="module")
def kept(sim_run: RunSpec, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict[str, Any]]]:
    path = tmp_path_factory.mktemp("sim") / "run.mcap"
    return path, execute_run(sim_run, keep=path)


def test_statistics_are_hil_infos(kept: tuple[Path, list[dict[str, Any]]]) -> None:
    """h_rms/95 %/max/final are the figures hil info prints for the same recording."""
    path, rows = kept
    ref = estimator_errors(read_session(path))
    assert [r["estimator"] for r in rows] == ["compvs", "ekf15"]
    for r in rows:
        e = ref[r["estimator"]]
        assert r["status"] == OK and r["n"] == e["n"]
        for col, k in (
            ("h_rms_m", "rms_m"),
            ("h_p95_m", "p95_m"),
            ("h_max_m", "max_m"),
            ("h_final_m", "final_m"),
        ):
            assert math.isclose(r[col], e[k], rel_tol=1e-5), (col, r[col], e[k])
        assert r["series_dt_s"] == 1.0 and len(r["series_h_err_m"]) == 5
    ekf = rows[1]
    assert ekf["nees_mean"] is not None and 0.0 <= ekf["nees_in_band"] <= 1.0
    assert len(ekf["series_nees"]) == len(ekf["series_h_sigma_m"]) == 5
    assert rows[0]["nees_mean"] is None and rows[0]["series_nees"] == []  # compvs has no covariance


def test_same_run_same_rows(sim_run: RunSpec, kept: tuple[Path, list[dict[str, Any]]]) -> None:
    """Deterministic from its spec: the temporary recording (only what the statistics read) is
    deleted, the figures are the kept complete recording's."""
    again = execute_run(sim_run)
    strip = ("wall_s", "cpu_s", "worker", "finished_utc", "recording")
    assert [{k: v for k, v in r.items() if k not in strip} for r in again] == [
        {k: v for k, v in r.items() if k not in strip} for r in kept[1]
    ]
    assert all(r["recording"] == "" for r in again)


def test_a_temporary_recording_holds_what_the_statistics_read_a_kept_one_everything(
    sim_run: RunSpec, kept: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    small = tmp_path / "small.mcap"
    sim_recording(sim_run, small, tmp_path, everything=False)
    topics = {r.topic for r in read_session(small).records}
    assert topics == {"hil/sim/run", "hil/sim/truth"} | {
        f"hil/sim/nav/{e}" for e in ("compvs", "ekf15", "ins")
    }
    full = {r.topic for r in read_session(kept[0]).records}
    assert topics < full and {"hil/sim/sensor/imu", "hil/sim/synced/gnss"} <= full


def test_a_failing_run_is_a_result(sim_run: RunSpec) -> None:
    broken = replace(sim_run, scenario_toml=sim_run.scenario_toml.replace("[imu]", "[imu]\nbogus_dph = 5"))
    rows = execute_run(broken)
    assert [r["status"] for r in rows] == [FAILED, FAILED]
    assert rows[0]["error"].startswith("ScenarioError: imu: unknown IMU key 'bogus_dph'")
    assert rows[0]["h_rms_m"] is None


def _rerun(sim_run: RunSpec, path: Path, **kw: Any) -> RunSpec:
    fields: dict[str, Any] = {
        "kind": RERUN,
        "recording": str(path),
        "scenario_toml": "",
        "estimators": (),
        "verify": True,
        "output_every": 0,
    }
    fields.update(kw)
    return replace(sim_run, **fields)


def test_rerun_verifies_and_reproduces_the_figures(
    sim_run: RunSpec, kept: tuple[Path, list[dict[str, Any]]]
) -> None:
    path, sim_rows = kept
    rows = execute_run(_rerun(sim_run, path))
    assert [(r["estimator"], r["status"], r["verify"]) for r in rows] == [
        ("compvs", OK, "ok"),
        ("ekf15", OK, "ok"),
    ]
    assert [r["h_rms_m"] for r in rows] == [r["h_rms_m"] for r in sim_rows]
    assert rows[0]["scenario"] == "straight_level" and rows[0]["seed"] == sim_run.seed


def test_rerun_with_another_configuration(sim_run: RunSpec, kept: tuple[Path, list[dict[str, Any]]]) -> None:
    rows = execute_run(_rerun(sim_run, kept[0], estimators=("cf3", "kfvel"), verify=False))
    assert [(r["estimator"], r["status"], r["verify"]) for r in rows] == [("cf3", OK, ""), ("kfvel", OK, "")]
    assert all(r["h_rms_m"] is not None and r["n"] > 0 for r in rows)


def test_rerun_of_a_corrupt_file_fails_with_its_error(sim_run: RunSpec, tmp_path: Path) -> None:
    bad = tmp_path / "garbage.mcap"
    bad.write_bytes(b"not an mcap file at all" * 10)
    rows = execute_run(_rerun(sim_run, bad))
    assert len(rows) == 1 and rows[0]["status"] == FAILED
    assert rows[0]["error"].startswith("RecordingError:")
