"""Run derivation: every run deterministic from the spec, seeds from the campaign seed and the
replicate, shared by the configurations and fault sets of a replicate (paired comparisons)."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from hil.campaign.runs import derive_runs, replicate_seed
from hil.campaign.spec import spec_from_dict
from hil.nav.scenario import parse_scenario


def _spec(**kw: Any) -> Any:
    doc: dict[str, Any] = {
        "name": "c",
        "seed": 11,
        "runs": 3,
        "duration_s": 5.0,
        "configs": {"a": {"estimators": ["compvs"]}, "b": {"estimators": ["ekf15"], "output_every": 4}},
        "faults": {
            "none": {},
            "out": {"events": [{"kind": "gnss_outage", "t_start_s": 1.0, "t_end_s": 2.0}]},
        },
        "sim": {"scenarios": ["straight_level", "uav_survey"]},
    }
    doc.update(kw)
    return spec_from_dict(doc, Path("."))


def test_same_spec_same_runs() -> None:
    a, b = derive_runs(_spec()), derive_runs(_spec())
    assert a == b
    assert len(a) == 3 * 2 * 2 * 2
    assert [r.index for r in a] == list(range(len(a)))


def test_seeds_from_campaign_seed_and_replicate() -> None:
    runs = derive_runs(_spec())
    for r in runs:
        assert r.seed == replicate_seed(11, r.replicate)
    # one seed per replicate, shared by every scenario, fault set and configuration
    assert len({r.seed for r in runs}) == 3
    assert {r.seed for r in derive_runs(_spec(seed=12))}.isdisjoint({r.seed for r in runs})
    # the scenario each run runs carries that seed, and the fault set's events
    r = next(r for r in runs if r.faults == "out" and r.scenario == "uav_survey")
    sc = parse_scenario(r.scenario_toml)
    assert sc.seed == r.seed and sc.name == "uav_survey"
    assert [e.kind for e in sc.events] == ["gnss_pulse", "gnss_outage"]
    assert tomllib.loads(r.scenario_toml)["seed"] == r.seed


def test_more_runs_keep_the_first_ones() -> None:
    """Replicates are outermost: 3 -> 5 runs appends, so a resumed campaign skips the first 3."""
    few, more = derive_runs(_spec(runs=3)), derive_runs(_spec(runs=5))
    assert [r.key for r in more[: len(few)]] == [r.key for r in few]
    assert [r.index for r in more[: len(few)]] == [r.index for r in few]


def test_key_is_the_definition_not_the_name_or_index() -> None:
    a = derive_runs(_spec())
    b = derive_runs(_spec(name="other"))
    assert [r.key for r in a] == [r.key for r in b]
    assert len({r.key for r in a}) == len(a)
    c = derive_runs(_spec(settle_s=1.0))  # another statistics window: another result
    assert {r.key for r in c}.isdisjoint({r.key for r in a})
