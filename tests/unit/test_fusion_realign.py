"""A fusion restarted mid-run (``hil up --restart``, option ``resume``) re-aligns from truth.

GIVEN the rig's default scenario (50 m/s due north) and a fusion node that starts 10 s into the
run, as ``hil up`` restarts one after ``hil fault kill_service --target fusion``
WHEN it takes the run's inputs from there on
THEN every estimator's solutions from the first one on are at the re-aligned state, ~500 m from
the origin: before the fix the compensation filters and kfvel published the origin (their
solution before their first IMU step) carried by the output predictor over the 0.5 s horizon.
"""

from __future__ import annotations

import dataclasses
from functools import cache
from typing import Any

import msgspec
import numpy as np

from hil.fusion.ideal import ideal_streams
from hil.messages import Event, GnssFix, ImuSample, NavSolution
from hil.nav.trajectory import TruthGenerator
from hil.nodes.fusion import (
    MAX_FIRST_RECEIVED,
    FusionNode,
    FusionOptions,
    realigned_first_received,
    realigned_imu_seq,
)
from hil.runners.sim import SimOptions, sim_run_info

RESTART_NS = 10_000_000_000
RUN_S = 12.0


@cache
def _rig() -> tuple[Any, list[ImuSample | GnssFix], TruthGenerator]:
    """The run, its inputs in arrival order from the restart on, and its truth."""
    run = sim_run_info(SimOptions(scenario="straight_level", duration_s=RUN_S))
    scenario = FusionNode(run).scenario
    imus, fixes = ideal_streams(scenario)
    # as the restarted process meets them: a fix arrives 0.1 s after its time of validity
    arrivals = [(m.stamp_ns, 0, m) for m in imus if m.stamp_ns > RESTART_NS]
    arrivals += [(f.stamp_ns + 100_000_000, 1, f) for f in fixes if f.stamp_ns + 100_000_000 > RESTART_NS]
    arrivals.sort(key=lambda a: (a[0], a[1], a[2].seq))
    return run, [m for *_k, m in arrivals], TruthGenerator(scenario)


@cache
def _restarted_outputs() -> tuple[list[Event], list[NavSolution]]:
    run, inputs, _truth = _rig()
    node = FusionNode(run, FusionOptions(resume=1))
    events: list[Event] = []
    sols: list[NavSolution] = []
    for m in inputs:
        for _key, out in node.on_message_from(f"synced/{m.sensor}", m, m.stamp_ns, ""):
            if isinstance(out, Event):
                events.append(out)
            elif isinstance(out, NavSolution):
                sols.append(out)
    return events, sols


def _first_horizon_errors() -> dict[str, float]:
    """Each stream's largest position error over the outputs the predictor carries over the
    first horizon, before it reaches the first fix (at the alignment at the earliest; 10 ms:
    more than an IMU interval): the alignment and the IMU alone."""
    events, sols = _restarted_outputs()
    assert [e.kind for e in events] == ["realigned"]
    _run, _inputs, truth = _rig()
    lag_ns = FusionOptions().config().lag_ns
    first_ns = min(s.stamp_ns for s in sols)
    early = [s for s in sols if s.stamp_ns < first_ns + lag_ns - 10_000_000]
    assert {s.estimator for s in early} == {"ins", *FusionOptions().config().estimators}
    stamps = np.array([s.stamp_ns for s in early], dtype=np.int64)
    true_pos = truth.sample(stamps).pos_ned_m
    assert float(true_pos[0][0]) > 400.0  # far from the origin: the origin would be ~500 m off
    worst: dict[str, float] = {}
    for s, p in zip(early, true_pos, strict=True):
        err = float(np.linalg.norm(np.asarray(s.pos_ned_m) - p))
        worst[s.estimator] = max(worst.get(s.estimator, 0.0), err)
    return worst


def test_every_estimator_publishes_the_realigned_position_from_its_first_output_on() -> None:
    worst = _first_horizon_errors()
    # an aligned INS over 0.5 s on a tactical IMU: millimetres (the origin: 500 m)
    assert max(worst.values()) < 0.5, worst


def test_the_realignment_does_not_step_the_first_sample_twice() -> None:
    """The truth at the first sample's stamp already holds the motion that sample measured: an
    alignment there, stepped by it, put every stream one interval (12.5 cm) ahead."""
    worst = _first_horizon_errors()
    assert max(worst.values()) < 0.02, worst


def _run_restarted(inputs: list[ImuSample | GnssFix]) -> tuple[FusionNode, list[bytes]]:
    run = _rig()[0]
    node = FusionNode(run, FusionOptions(resume=1))
    sols: list[bytes] = []
    for m in inputs:
        for _key, out in node.on_message_from(f"synced/{m.sensor}", m, m.stamp_ns, ""):
            if isinstance(out, NavSolution):
                sols.append(msgspec.json.encode(out))
    return node, sols


def test_a_fix_valid_before_the_alignment_changes_nothing_whether_it_arrives_or_not() -> None:
    """GIVEN a restarted fusion whose subscription to the fixes took effect later than the one to
    the IMU (under load, one key's declaration reaches the hub after the other's), so that a fix
    valid just before its alignment arrives after its first IMU sample -- or, a moment later,
    would not have arrived at all; WHEN it runs on either; THEN it publishes the same solutions
    (what ``hil rerun`` relies on: it cannot tell the two apart), the fix refused, counted and
    journaled. Before, it fused the fix when it arrived: gnss_seq and the states differed from a
    run without it, and rerun, taking it, failed the supervision test once in a full suite."""
    _run, inputs, _truth = _rig()
    first_imu = next(i for i, m in enumerate(inputs) if isinstance(m, ImuSample))
    scenario = FusionNode(_rig()[0]).scenario
    _imus, fixes = ideal_streams(scenario)
    align_ns = inputs[first_imu].stamp_ns - 2_500_000  # the start of the first sample's interval
    before = max((f for f in fixes if f.stamp_ns < align_ns), key=lambda f: f.stamp_ns)
    assert align_ns - before.stamp_ns < 150_000_000  # recent: within the horizon it would be fused in
    late = [*inputs[: first_imu + 40], before, *inputs[first_imu + 40 :]]
    with_fix, sols_with = _run_restarted(late)
    without, sols_without = _run_restarted(list(inputs))
    assert len(sols_with) == len(sols_without) > 100
    assert sols_with == sols_without
    assert with_fix.core is not None and without.core is not None
    assert with_fix.core.counters.get("dropped_before_alignment.gnss") == 1
    assert f"prealign:gnss:{before.seq}" in with_fix.core.take_dropped()
    assert "dropped_before_alignment.gnss" not in without.core.counters


def test_the_fusion_subscribes_to_its_aiding_streams_before_the_imu() -> None:
    """A restarted fusion takes what was published after the IMU sample before its first (rerun
    infers that from the publish order): declared before the IMU's on the one session, the fixes'
    subscription has taken effect at the hub by the time the IMU's has."""
    from hil.sensor_table import SENSORS

    paces = [SENSORS[i.key.split("/")[1]].paces_fusion for i in FusionNode.inputs]
    assert paces == sorted(paces) and paces[-1] and not paces[0], [i.key for i in FusionNode.inputs]


def test_the_realigned_event_names_the_first_input_of_each_stream_received_before_the_first_sample() -> None:
    """What ``hil rerun`` gives a restarted life: from its first input of each stream on. A fix
    received before the first IMU sample is named with its publisher; a stream not named before
    that sample had nothing received (rerun takes none of it from before)."""
    run, inputs, _truth = _rig()
    first_imu = next(m for m in inputs if isinstance(m, ImuSample))
    fix = next(m for m in inputs if isinstance(m, GnssFix))
    node = FusionNode(run, FusionOptions(resume=1))
    assert node.on_message_from("synced/gnss", fix, fix.stamp_ns, "zid:19") == []
    outs = node.on_message_from("synced/imu", first_imu, first_imu.stamp_ns, "zid:16")
    (event,) = [o for _k, o in outs if isinstance(o, Event)]
    assert event.kind == "realigned"
    assert realigned_imu_seq(event.detail) == first_imu.seq
    assert realigned_first_received(event.detail) == {
        ("gnss", "zid:19"): fix.seq,
        ("imu", "zid:16"): first_imu.seq,
    }
    alone = FusionNode(run, FusionOptions(resume=1))
    outs = alone.on_message_from("synced/imu", first_imu, first_imu.stamp_ns, "")
    (event,) = [o for _k, o in outs if isinstance(o, Event)]
    assert realigned_first_received(event.detail) == {("imu", ""): first_imu.seq}
    assert (
        realigned_first_received("fusion restarted: ... (the start of imu seq 7); outputs numbered from 1")
        is None
    )


def test_inputs_received_while_holding_but_not_held_are_journaled_at_the_realignment() -> None:
    """GIVEN a restarted fusion waiting for its first IMU sample (an IMU outage) whose held list
    is bounded, WHEN more fixes arrive than it holds, and its inbox drops one, THEN the oldest go
    (counted ``dropped_held``) and, where valid after the alignment, are journaled with the inbox's
    drop -- rerun takes every input of a stream from its first received on, so what the live
    core never saw must be in the journal."""
    run, inputs, _truth = _rig()
    first_imu = next(m for m in inputs if isinstance(m, ImuSample))
    node = FusionNode(run, FusionOptions(resume=1))
    node.config = dataclasses.replace(node.config, max_buffered_aiding=2)
    base = first_imu.stamp_ns  # stamped after the alignment (a lagging IMU stream): all valid
    fix = next(m for m in inputs if isinstance(m, GnssFix))
    fixes = [msgspec.structs.replace(fix, seq=100 + k, stamp_ns=base + k * 1000) for k in range(5)]
    stale = msgspec.structs.replace(fix, seq=99, stamp_ns=base - 1_000_000_000)
    node.on_dropped("synced/gnss", stale, "p")  # before the alignment: refused either way
    for f in fixes[:4]:
        node.on_message_from("synced/gnss", f, f.stamp_ns, "p")
    node.on_dropped("synced/gnss", fixes[4], "p")
    assert node.counters().get("dropped_held.gnss") == 2
    outs = node.on_message_from("synced/imu", first_imu, first_imu.stamp_ns, "p")
    event = next(o for _k, o in outs if isinstance(o, Event))
    assert realigned_first_received(event.detail) == {("gnss", "p"): 99, ("imu", "p"): first_imu.seq}
    assert node.core is not None
    dropped = node.core.take_dropped()
    assert dropped[:3] == ["held:gnss:100@p", "held:gnss:101@p", "inbox:gnss:104@p"], dropped
    assert not any(d.endswith("gnss:99@p") for d in dropped)


def test_a_flood_of_publishers_while_holding_names_a_bounded_number_of_streams() -> None:
    """On a bus without the rig's key a stranger can make up publishers: the event (and what the
    node keeps to write it) stays bounded."""
    run, inputs, _truth = _rig()
    first_imu = next(m for m in inputs if isinstance(m, ImuSample))
    fix = next(m for m in inputs if isinstance(m, GnssFix))
    node = FusionNode(run, FusionOptions(resume=1))
    for k in range(3 * MAX_FIRST_RECEIVED):
        node.on_message_from("synced/gnss", fix, fix.stamp_ns, f"made-up:{k}")
    outs = node.on_message_from("synced/imu", first_imu, first_imu.stamp_ns, "rig:16")
    (event,) = [o for _k, o in outs if isinstance(o, Event)]
    firsts = realigned_first_received(event.detail)
    assert firsts is not None and len(firsts) == MAX_FIRST_RECEIVED
    assert ("gnss", "made-up:0") in firsts
