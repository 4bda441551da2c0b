"""A split ``hil rerun`` runs the GNSS gate's reference in one core only: the other core takes its
verdicts (``FusionCore.gate_relay``) and recomputes its estimators exactly as one core does.

GIVEN 10 Hz fixes with a 15 m pulse of the seed paper's shape (the gate rejects fixes; by their own
verdicts the estimators would take others than by the reference's) and four estimators
WHEN one core runs all four, a second ekf15 (the reference) and compvs keeping the gate's
verdicts, and a third comp1 and kfvel taking them after every input
THEN the third's solutions are the first's, bit for bit, and without the relayed verdicts (each
estimator deciding on its own) they are not.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

from hil.fusion.core import FusionConfig, FusionCore
from hil.fusion.ideal import ideal_inputs
from hil.messages import encode
from hil.nav.scenario import parse_scenario
from hil.nav.trajectory import TruthGenerator
from tests.unit.test_fusion_horizon import SCENARIO as HORIZON_FLIGHT
from tests.unit.test_gnss_gate_reacquire import saturated_inputs

# the horizon tests' flight (hold, turn, hold; 10 Hz fixes) with a 15 m pulse at 25 s
SCENARIO = (
    HORIZON_FLIGHT
    + """
[[event]]
kind = "gnss_pulse"
t_start_s = 25.0
amplitude_m = 15.0
tau_s = 1.0
direction_ned = [1.0, 0.0, 0.0]
"""
)
SHARE_A = ("ekf15", "compvs")
SHARE_B = ("comp1", "kfvel")


@cache
def _run(saturated_s: float = 0.0) -> dict[str, object]:
    s = parse_scenario(SCENARIO)
    cfg = FusionConfig(estimators=("comp1", "compvs", "kfvel", "ekf15"))
    full, a, b, b_own = (
        FusionCore.for_scenario(s, replace(cfg, estimators=est))
        for est in (cfg.estimators, SHARE_A, SHARE_B, SHARE_B)
    )
    a.gate_verdicts, b.gate_relay = {}, {}
    relayed: list[bool | None] = []
    out: dict[str, list[bytes]] = {"full": [], "b": [], "b_own": []}
    inputs = ideal_inputs(s, TruthGenerator(s))
    if saturated_s:
        inputs = saturated_inputs(inputs, 5.0, saturated_s)
    for m in inputs:
        out["full"] += [encode(x) for x in full.replay(m) if x.estimator in SHARE_B]
        a.replay(m)
        relayed += a.gate_verdicts.values()
        b.gate_relay.update(a.gate_verdicts)
        a.gate_verdicts.clear()
        out["b"] += [encode(x) for x in b.replay(m) if x.estimator in SHARE_B]
        out["b_own"] += [encode(x) for x in b_own.replay(m) if x.estimator in SHARE_B]
    return {"out": out, "relayed": relayed, "left": dict(b.gate_relay)}


def test_the_core_without_the_reference_recomputes_with_its_verdicts() -> None:
    r = _run()
    out = r["out"]
    assert len(out["full"]) >= 1000  # type: ignore[index]
    assert out["b"] == out["full"]  # type: ignore[index]
    relayed = r["relayed"]
    assert relayed.count(False) >= 5 and relayed.count(True) > 300  # type: ignore[attr-defined]  # the pulse
    assert r["left"] == {}  # every verdict taken by the fix it was for


def test_without_the_verdicts_the_share_decides_otherwise() -> None:
    out = _run()["out"]
    assert out["b_own"] != out["full"]  # type: ignore[index]


def test_the_core_without_the_reference_is_re_initialised_where_the_reference_was() -> None:
    """After a flagged IMU fault the reference re-initialises every estimator on one fix (and
    the free INS, the open-loop filters starting again): the core without it was told the
    verdict, not the reset, and its comp1 and kfvel went on from the INS the fault left."""
    r = _run(0.05)
    out = r["out"]
    assert len(out["full"]) >= 1000  # type: ignore[index]
    assert out["b"] == out["full"]  # type: ignore[index]
    assert r["left"] == {}
