"""The built-in campaigns: seed 004's Monte-Carlo and the UAV NEES study, through the rig."""

from __future__ import annotations

import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from hil.bench.seeds_uav import seed_gnss_scenario
from hil.campaign.cli import builtin_names
from hil.campaign.execute import OK, execute_run
from hil.campaign.runs import derive_runs
from hil.campaign.spec import spec_from_dict
from hil.estimators.ins7 import Ins7Params
from hil.nav.scenario import load_scenario
from hil.nav.sensor_specs import GM_PEAK_RATIO, IEEE_BI_FACTOR

ROOT = Path(str(resources.files("hil") / "campaigns"))


def _doc(name: str, **kw: Any) -> dict[str, Any]:
    doc = tomllib.loads((ROOT / f"{name}.campaign.toml").read_text())
    doc.update(kw)
    return doc


def test_builtins_listed_and_sized() -> None:
    assert builtin_names() == ["seed004", "uav_nees"]
    uav = derive_runs(spec_from_dict(_doc("uav_nees"), ROOT))
    assert len(uav) == 200 and len({r.seed for r in uav}) == 200  # the study at >= 200 runs
    assert {r.estimators for r in uav} == {("ekf15",)} and uav[0].settle_s == 60.0
    s4 = derive_runs(spec_from_dict(_doc("seed004"), ROOT))
    assert len(s4) == 1000 and s4[0].duration_s == 900.0  # the paper's 1000 runs x 900 s


def test_uav_scenario_is_the_benchs() -> None:
    """The shipped scenario is what hil bench seeds builds (hil.bench.seeds_uav), name aside."""
    mine = load_scenario(str(ROOT / "uav_survey_seed_gnss.toml"))
    bench = seed_gnss_scenario(None, mine.seed)
    for f in ("imu", "gnss", "segments", "events", "duration_s", "initial_euler_deg", "initial_vel_body_mps"):
        assert getattr(mine, f) == getattr(bench, f), f
    assert (mine.origin_lat_deg, mine.origin_lon_deg, mine.origin_alt_m) == (
        bench.origin_lat_deg,
        bench.origin_lon_deg,
        bench.origin_alt_m,
    )


def test_seed004_scenario_realises_the_papers_model() -> None:
    """Gauss-Markov sigmas and correlation times of hil.estimators.ins7 (to the 5 digits of B)."""
    p = Ins7Params()
    sc = load_scenario(str(ROOT / "seed004_static.toml"))
    imu = sc.imu.params
    gm = IEEE_BI_FACTOR / GM_PEAK_RATIO  # sigma_GM per unit of bias instability (hil.sensors.imu)
    assert math.isclose(gm * imu.gyro_bias_instability_radps[0], p.sigma_omega_radps, rel_tol=1e-4)
    assert math.isclose(gm * imu.accel_bias_instability_mps2[0], p.sigma_alpha_mps2, rel_tol=1e-4)
    assert imu.gyro_bias_corr_s == p.t_omega_s and imu.accel_bias_corr_s == p.t_alpha_s
    assert sc.gnss.pos_sigma_m == (p.sigma_s_m,) * 3 and sc.gnss.rate_hz == 1.0 / p.dt_s
    assert sc.duration_s == 900.0


def test_seed004_one_tiny_run() -> None:
    run = derive_runs(spec_from_dict(_doc("seed004", runs=1, duration_s=4.0), ROOT))[0]
    rows = execute_run(run)
    assert [(r["estimator"], r["status"]) for r in rows] == [("ekf15", OK)]
    assert rows[0]["nees_mean"] is not None
