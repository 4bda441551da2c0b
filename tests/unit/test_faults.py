"""The fault core both executors call (live emulators and `hil sim`): decisions depend only on the
scenario seed, the sample index and time, so a run and its replay lose the same samples."""

from __future__ import annotations

import re

import can
import numpy as np
import pytest

from hil.can.codec import ImuCanCodec, ImuFrameAssembler
from hil.faults import (
    FaultError,
    FrameCorruptor,
    ImuFaults,
    check_fault,
    device_timeline,
    edge_time_ns,
)
from hil.messages import FaultCommand
from hil.messages import params as fault_params
from hil.nav.scenario import ScenarioError, ScenarioEvent, load_scenario
from hil.nodes.gnss_emulator import GnssEmulatorNode
from hil.runners.sim import SimOptions, sim_run_info
from hil.runtime.scenario_io import scenario_from_text

DT_NS = 2_500_000


def _ev(kind: str, t0: float, t1: float | None = None, **params: object) -> ScenarioEvent:
    return ScenarioEvent(kind, t0, t1, params)


def _lost(seed: int, events: list[ScenarioEvent], n: int = 2000) -> list[int]:
    f = ImuFaults(seed, events)
    z = np.zeros(3)
    return [k for k in range(n) if not f.apply(k, (k + 1) * DT_NS, z, z).send]


def test_frame_loss_is_a_function_of_seed_and_sample_index() -> None:
    ev = [_ev("imu_frame_loss", 0.0, 10.0, percent=20.0)]
    a, b, c = _lost(3, ev), _lost(3, ev), _lost(4, ev)
    assert a == b and a != c
    assert abs(len(a) / 2000 - 0.20) < 0.03 and abs(len(c) / 2000 - 0.20) < 0.03


def test_burst_error_fires_once_and_leaves_its_params_alone() -> None:
    f = ImuFaults(1, [_ev("can_burst_error", 0.01, frames=8)])
    z = np.zeros(3)
    acts = [f.apply(k, (k + 1) * DT_NS, z, z).corrupt_frames for k in range(20)]
    assert acts.count(8) == 1 and sum(acts) == 8 and acts.index(8) == 3  # sample 3 ends at 10 ms
    assert dict(f.timeline.faults[0].params) == {"frames": 8}  # so fault_end/reports read it clean


def test_corruptor_flips_exactly_n_frames_and_the_assembler_rejects_them_on_crc() -> None:
    codec = ImuCanCodec.from_dbc()
    asm = ImuFrameAssembler(ImuCanCodec.from_dbc())
    bad = FrameCorruptor()
    bad.arm(5)
    hit = []
    for k in range(4):
        for fr in codec.encode_sample(
            device_stamp_ns=k * DT_NS, dtheta_b_rad=[0.0] * 3, dvel_b_mps=[0.0] * 3
        ):
            hit.append(bad(fr))
            asm.feed(fr)
    assert sum(hit) == 5 and hit[:5] == [True] * 5 and bad.corrupted == 5 and bad.pending == 0
    assert asm.counters["bad_crc"] == 5
    assert not bad(can.Message(arbitration_id=1, data=b"\x00" * 8))  # the burst is over


def test_each_device_announces_its_own_clock_step_and_gnss_the_pulse() -> None:
    events = [
        _ev("clock_step", 2.0, sensor="imu", step_s=0.1),
        _ev("clock_step", 1.0, sensor="gnss", step_s=0.2),
        _ev("gnss_pulse", 3.0, 4.0, amplitude_m=50.0, tau_s=1.0),
        _ev("imu_stuck", 0.5, 0.7),
        _ev("kill_service", 1.0, service="fusion"),
    ]
    imu = device_timeline(events, "imu")
    gnss = device_timeline(events, "gnss")
    assert [(f.kind, f.params.get("sensor")) for f in imu.faults] == [
        ("clock_step", "imu"),
        ("imu_stuck", None),
    ]
    assert [f.kind for f in gnss.faults] == ["clock_step", "gnss_pulse"]
    # edges come out in time order whatever the file order, each once
    edges = imu.edges(10_000_000_000)
    assert [(e, f.kind, edge_time_ns(e, f)) for e, f in edges] == [
        ("fault_start", "imu_stuck", 500_000_000),
        ("fault_end", "imu_stuck", 700_000_000),
        ("fault_start", "clock_step", 2_000_000_000),
    ]
    assert imu.edges(20_000_000_000) == []


def test_bad_fault_commands_are_refused_with_a_reason_and_counted_not_raised() -> None:
    bad = [
        ("bogus", "", {}, "unknown fault kind"),
        ("imu_stuck", "", {"percent": 3.0}, "unknown param"),
        ("imu_frame_loss", "", {"percent": 140.0}, "percent must be in [0, 100]"),
        ("gnss_jump", "", {"n_m": float("nan")}, "finite"),
        ("gnss_latency", "", {"jitter_s": 0.1}, "needs latency_s"),
        ("gnss_latency", "", {"latency_s": -0.2}, "must be >= 0"),
        ("can_burst_error", "", {"frames": 0.0}, "frames must be in"),
        ("clock_step", "fusion", {"step_s": 0.1}, "--target imu or --target gnss"),
        ("clock_step", "imu", {"step_s": 1e9}, "|step_s| must be <= 86400 s"),
        ("clock_step", "gnss", {"step_s": -86_401.0}, "|step_s| must be <= 86400 s"),
        ("kill_service", "", {}, "needs --target"),
    ]
    for kind, target, params, why in bad:
        with pytest.raises(FaultError, match=re.escape(why)):
            check_fault(kind, target, params)
    for duration in (-1.0, float("inf"), 2e6):
        with pytest.raises(FaultError, match="duration must be in"):
            check_fault("imu_stuck", "", {}, duration)
    # the GNSS emulator node: a bad command is counted, never raised, never applied
    node = GnssEmulatorNode(sim_run_info(SimOptions(scenario="straight_level", duration_s=5.0)))
    events_before = len(node.timeline.faults)
    cmd = FaultCommand(seq=0, stamp_ns=0, kind="gnss_latency", params=fault_params({"latency_s": -1.0}))
    assert node.on_message("control/fault", cmd, 1_000_000_000) == []
    assert node.counters() == {"rejected.control.fault": 1} and "must be >= 0" in node.last_error
    # addressed to nobody: counted by every device that sees it; another device's command: not ours
    for kind, target in (("bogus", ""), ("clock_step", "fusion"), ("imu_stuck", ""), ("clock_step", "imu")):
        cmd = FaultCommand(seq=1, stamp_ns=0, kind=kind, target=target, params=fault_params({"step_s": 1.0}))
        assert node.on_message("control/fault", cmd, 1_000_000_000) == []
    assert (
        node.counters() == {"rejected.control.fault": 3}
        and "--target imu or --target gnss" in node.last_error
    )
    assert len(node.timeline.faults) == events_before
    base = load_scenario("straight_level").source_text
    for event, why in (
        ('kind = "gnss_latency"\nt_start_s = 1\nlatency_s = -0.1', "must be >= 0"),
        ('kind = "can_burst_error"\nt_start_s = 1\nframes = 1e9', "frames in [1, 100000]"),
    ):
        with pytest.raises(ScenarioError, match=re.escape(why)):
            scenario_from_text(base + "\n[[event]]\n" + event + "\n", "bad")


@pytest.mark.parametrize("n", [-5.0, 0.0, 2.5, 1e12])
def test_a_line_burst_of_no_whole_sensible_size_is_refused_as_command_and_as_event(n: float) -> None:
    """``bytes`` went unchecked: negative and fractional were taken, a huge one built its noise
    byte by byte (the emulator hung)."""
    with pytest.raises(FaultError, match=r"gnss_line_burst: bytes must be a whole number in \[1, 65536\]"):
        check_fault("gnss_line_burst", "", {"bytes": n})
    event = f'kind = "gnss_line_burst"\nt_start_s = 1\nbytes = {n!r}'
    base = load_scenario("straight_level").source_text
    with pytest.raises(ScenarioError, match=r"event\[\d+\]\.bytes must be a whole number in \[1, 65536\]"):
        scenario_from_text(base + "\n[[event]]\n" + event + "\n", "bad")


def test_a_line_burst_within_the_bound_is_taken() -> None:
    check_fault("gnss_line_burst", "", {"bytes": 300.0})
    check_fault("gnss_line_burst", "", {})  # the default, 64


def test_a_clock_step_commanded_mid_block_stamps_as_the_clock_model_does() -> None:
    """The IMU emulator stamps a second of samples ahead; a commanded step makes those stale:
    from its sample on, the stamps are the clock model's with the step, sample by sample."""
    import numpy as np

    from hil.can.codec import ImuCanCodec, ImuFrameAssembler
    from hil.messages import FaultCommand, Param
    from hil.nav.scenario import scenario_for_run
    from hil.nodes.base import CAN_TX
    from hil.nodes.imu_emulator import ImuEmulatorNode, ImuEmulatorOptions
    from hil.runners.sim import SimOptions, sim_run_info
    from hil.sensors.clock import device_clock_for

    run = sim_run_info(SimOptions(scenario="static", duration_s=3.0))
    node = ImuEmulatorNode(run, ImuEmulatorOptions())
    asm = ImuFrameAssembler(ImuCanCodec.from_dbc())
    stamps: list[int] = []
    t = node.next_tick_ns()
    while t is not None:
        if t == 1_502_500_000:  # mid-block: 1.5 s into the second block
            cmd = FaultCommand(
                seq=0, stamp_ns=t, kind="clock_step", target="imu", params=[Param(key="step_s", value=0.25)]
            )
            node.on_message("control/fault", cmd, t)
        for key, burst in node.tick(t):
            if key == CAN_TX:
                stamps += [
                    s.device_stamp_ns for f in burst.frames for s in asm.feed(f) if hasattr(s, "dtheta_b_rad")
                ]
        t = node.next_tick_ns()
    clock = device_clock_for(scenario_for_run(run), "imu")
    t_true = np.arange(1, len(stamps) + 1, dtype=np.int64) * node.dt_ns
    want = [clock.device_ns(int(x)) + (250_000_000 if x >= 1_502_500_000 else 0) for x in t_true]
    assert len(stamps) == 1200 and stamps == want
