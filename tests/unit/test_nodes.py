"""The node model: typed options, the sensor table, estimator handlers, the nodes' own contract
and the virtual-clock runner's determinism."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.bus.keys import SENSOR_TYPES, type_for_key
from hil.estimators.base import Estimator, GnssInput, ImuInput
from hil.fusion.core import FusionConfig, FusionCore, input_key
from hil.messages import EstimatorHealth, FaultCommand, FusionSettings, GnssFix, ImuSample
from hil.messages import params as fault_params
from hil.nav.scenario import load_scenario
from hil.nav.types import NavState
from hil.nodes import NODES, node_class
from hil.nodes.base import CAN_TX, OptionsError, decode_options
from hil.nodes.fusion import FusionNode, FusionOptions
from hil.nodes.imu_emulator import ImuEmulatorNode
from hil.runners.sim import SimOptions, run_sim, sim_run_info
from hil.runtime.options import RecorderOptions, fill_options, options_class
from hil.sensor_table import SENSORS
from tests.conftest import run_hil


def _run(duration_s: float = 5.0, scenario: str = "straight_level") -> object:
    return sim_run_info(SimOptions(scenario=scenario, duration_s=duration_s))


# -- typed options ------------------------------------------------------------------------------
def test_an_unknown_or_bad_option_is_one_line_naming_the_field() -> None:
    with pytest.raises(OptionsError, match=r"fusion: unknown option 'lagg'; known options: .*lag_s"):
        decode_options(FusionOptions, {"lagg": 0.1}, "fusion")
    with pytest.raises(OptionsError, match=r"fusion: option lag_s: Expected `float`, got `str`"):
        decode_options(FusionOptions, {"lag_s": "soon"}, "fusion")
    with pytest.raises(OptionsError, match=r"unknown estimator\(s\) \['nosuch'\]"):
        decode_options(FusionOptions, {"estimators": ["ekf15", "nosuch"]}, "fusion")
    with pytest.raises(OptionsError, match="recorder: option split_mb"):
        decode_options(RecorderOptions, {"split_mb": [1]}, "recorder")


def test_each_option_has_one_default_the_fusion_lag_is_the_cores() -> None:
    assert FusionOptions().lag_s == FusionConfig().lag_ns / 1e9
    assert FusionOptions().config() == FusionConfig(estimators=FusionOptions().config().estimators)
    assert SimOptions().lag_s == FusionOptions().lag_s


def test_hil_up_fills_options_by_name_and_refuses_before_starting() -> None:
    class Up:
        channel = "can7"
        fd = True
        estimators = ("ekf15",)
        interface = None

    assert fill_options("imu_emulator", Up()) == {"channel": "can7", "fd": True}
    assert fill_options("fusion", Up()) == {"estimators": ("ekf15",)}
    assert options_class("recorder") is RecorderOptions
    proc = run_hil("up", "--estimators", "ekf15,nosuch", "--duration", "1", timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "hil: --estimators: unknown estimator(s) ['nosuch']; known: cf2, cf3, comp1, comp2, comp3, comp3f, "
        "compvs, ekf15, kfvel (and ins, the free inertial solution, which always runs: name it alone "
        "for it alone)"
    ]
    assert "hil up: rig" not in proc.stdout  # nothing was started


# -- the sensor table ---------------------------------------------------------------------------
def test_keys_ranks_and_routes_come_from_the_sensor_table() -> None:
    assert {n: k.message for n, k in SENSORS.items()} == SENSOR_TYPES
    for name, kind in SENSORS.items():
        assert type_for_key(f"hil/r/synced/{name}") is kind.message
        assert f"synced/{name}" in [i.key for i in FusionNode.inputs]
        assert kind.emulator in NODES
    assert type_for_key("hil/r/fusion/config") is FusionSettings
    assert type_for_key("hil/r/health/ekf15") is EstimatorHealth
    imu = ImuSample(
        seq=1,
        stamp_ns=5,
        device_stamp_ns=5,
        rx_stamp_ns=5,
        dt_ns=1,
        dtheta_b_rad=[0.0] * 3,
        dvel_b_mps=[0.0] * 3,
    )
    fix = GnssFix(
        seq=0, stamp_ns=5, device_stamp_ns=5, rx_stamp_ns=5, lat_deg=0, lon_deg=0, alt_m=0,
        pos_ned_m=[0.0] * 3, vel_ned_mps=[0.0] * 3, pos_sigma_m=[1.0] * 3, vel_sigma_mps=[1.0] * 3,
        fix_type=3, num_sats=9, hdop=1.0,
    )  # fmt: skip
    assert sorted([fix, imu], key=input_key) == [imu, fix]  # at equal stamps the table's rank decides


# -- estimators: one handler per measurement kind, a no-op by default ----------------------------
class _ImuOnly(Estimator):
    name = "imu_only"

    def __init__(self) -> None:
        self.imu = 0

    def on_imu(self, imu: ImuInput, ins: NavState) -> None:
        self.imu += 1

    def solution(self) -> NavState:
        raise AssertionError("not asked in this test")


class _WithGnss(_ImuOnly):
    name = "with_gnss"

    def __init__(self) -> None:
        super().__init__()
        self.fixes: list[GnssInput] = []

    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        self.fixes.append(gnss)


def test_an_estimator_gets_only_the_measurements_it_has_a_handler_for() -> None:
    assert _ImuOnly().handler("gnss") is None  # the base class's no-op is not called at all
    assert _ImuOnly().handler("magnetometer") is None  # a kind no estimator knows: nothing to edit
    assert _WithGnss().handler("gnss") is not None
    s = load_scenario("straight_level")
    ests = {"imu_only": _ImuOnly(), "with_gnss": _WithGnss()}
    init = FusionCore.for_scenario(s, FusionConfig()).init
    core2 = FusionCore(
        init, FusionConfig(estimators=tuple(ests)), make_estimator=lambda name, _init: ests[name]
    )
    fix = GnssFix(
        seq=0, stamp_ns=0, device_stamp_ns=0, rx_stamp_ns=0, lat_deg=0, lon_deg=0, alt_m=0,
        pos_ned_m=[1.0, 2.0, 3.0], vel_ned_mps=[0.0] * 3, pos_sigma_m=[1.0] * 3, vel_sigma_mps=[1.0] * 3,
        fix_type=3, num_sats=9, hdop=1.0,
    )  # fmt: skip
    core2.process(fix)
    assert [list(f.pos_ned_m) for f in ests["with_gnss"].fixes] == [[1.0, 2.0, 3.0]]
    assert core2._handlers["gnss"] == [("with_gnss", ests["with_gnss"].on_gnss)]


# -- nodes --------------------------------------------------------------------------------------
def test_imu_node_paces_on_the_time_it_is_given_and_resumes_after_a_restart() -> None:
    run = _run()
    node = ImuEmulatorNode(run)
    assert node.start(0) == []
    assert node.next_tick_ns() == 2_500_000  # sample 0 ends at 1/400 s
    outs = node.tick(10_000_000)  # four samples are due: all four, in order
    caps = [m for k, m in outs if k == "capture/imu"]
    assert [c.seq for c in caps] == [0, 1, 2, 3]
    assert [c.true_stamp_ns for c in caps] == [2_500_000, 5_000_000, 7_500_000, 10_000_000]
    # classic CAN: 4 frames a sample, and the first carries a status frame (its SampleCount)
    assert sum(len(b.frames) for k, b in outs if k == CAN_TX) == 4 * 4 + 1
    # a restarted device (option resume) resumes at the current sample index, SampleCount with it
    again = ImuEmulatorNode(run, ImuEmulatorNode.Options(resume=1))
    ((ev_key, ev),) = again.start(3_000_000_000)
    assert ev_key == "event/imu_emulator" and ev.kind == "resumed" and again.k == 1200
    assert again.codec.samples_encoded == 1200 and ev.seq == 1 << 32  # restart generation 1


def test_imu_node_counts_a_bad_fault_command_and_applies_a_good_one_at_the_next_sample() -> None:
    node = ImuEmulatorNode(_run())
    bad = FaultCommand(seq=0, stamp_ns=0, kind="imu_frame_loss", params=fault_params({"percent": 140.0}))
    node.on_message("control/fault", bad, 0)
    assert node.counters()["rejected.control.fault"] == 1 and "percent" in node.last_error
    good = FaultCommand(seq=1, stamp_ns=0, kind="can_bus_off", duration_s=0.01)
    node.on_message("control/fault", good, 0)
    outs = node.tick(20_000_000)
    kinds = [m.kind for k, m in outs if k == "event/imu_emulator"]
    assert kinds == ["fault_start", "fault_end"]
    assert node.counters()["fault.imu_samples_not_sent.bus_off"] == 4  # 2.5 .. 10 ms: [2.5, 12.5) ms


def test_a_gnss_outage_commanded_before_time_zero_starts_at_time_zero() -> None:
    """GIVEN a 2 s outage commanded 0.7 s before the run starts (services run before time zero)
    THEN it is announced from 0 to 2 s and the receiver's first fix is valid at 2 s or later."""
    import json

    from hil.nodes.gnss_emulator import GnssEmulatorNode, GnssEmulatorOptions

    node = GnssEmulatorNode(_run(5.0), GnssEmulatorOptions())
    node.start(0)
    cmd = FaultCommand(seq=0, stamp_ns=0, kind="gnss_outage", duration_s=2.0)
    assert node.on_message("control/fault", cmd, -700_000_000) == []
    outs = []
    while (t := node.next_tick_ns()) is not None:
        outs += node.tick(t)
    edges = [(m.kind, json.loads(m.detail)) for k, m in outs if k == "event/gnss_emulator"]
    assert [(k, d["t_start_s"], d["t_end_s"]) for k, d in edges] == [
        ("fault_start", 0.0, 2.0),
        ("fault_end", 0.0, 2.0),
    ]
    valid = [m.stamp_ns for k, m in outs if k == "capture/gnss"]
    assert valid and min(valid) >= 2_000_000_000 and max(valid) > 4_000_000_000


@pytest.mark.parametrize("restart_ns", [-400_000_000, 0, 2_300_000_000])
def test_a_restarted_gnss_receiver_s_pps_edges_carry_the_second_as_seq(restart_ns: int) -> None:
    """GIVEN the GNSS emulator restarted (resume) before time zero, at it or mid-run WHEN it runs
    to the end THEN each PPS time tag's seq is its edge's second less one, as in a run never
    restarted: none negative (a restart during the world's lead put an edge at 0 s with seq -1,
    refused by time sync and the recorder), none repeated."""
    from hil.messages import TimeTag
    from hil.nodes.gnss_emulator import GnssEmulatorNode, GnssEmulatorOptions

    node = GnssEmulatorNode(_run(5.0), GnssEmulatorOptions(resume=1))
    node.start(restart_ns)
    outs = []
    while (t := node.next_tick_ns()) is not None:
        outs += node.tick(max(t, restart_ns))
    seqs = [m.seq for k, m in outs if k == "timetag/gnss" and isinstance(m, TimeTag)]
    first = max(1, restart_ns // 1_000_000_000 + 1)
    assert seqs == list(range(first - 1, 5)), seqs


def test_fusion_node_publishes_its_config_journal_and_health_on_the_rig_clock() -> None:
    node = FusionNode(_run(), FusionOptions(estimators=["kfvel"]))
    ((key, cfg),) = node.start(0)
    assert key == "fusion/config" and cfg.estimators == ["kfvel"] and cfg.lag_ns == FusionConfig().lag_ns
    assert node.next_tick_ns() == 500_000_000
    assert [k for k, _ in node.tick(500_000_000)] == ["fusion/journal"]
    assert [k for k, _ in node.tick(1_000_000_000)] == ["fusion/journal", "health/kfvel"]
    assert node.next_tick_ns() == 1_500_000_000
    assert node_class("fusion") is FusionNode


# -- the virtual-clock runner -------------------------------------------------------------------
def test_hil_sim_is_a_pure_function_of_the_scenario(tmp_path: Path) -> None:
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    for p in (a, b):
        run_sim(SimOptions(scenario="car_drive", duration_s=3.0, record=p, estimators=["comp1", "ekf15"]))
    assert a.read_bytes() == b.read_bytes()
    assert np.frombuffer(a.read_bytes()[:8], dtype=np.uint8).tolist() == list(b"\x89MCAP0\r\n")


def test_gnss_node_asks_for_no_tick_past_the_run_when_the_truth_rounds_1_ns_longer() -> None:
    """GIVEN a run of 4.1 s (int(4.1e9) = 4_099_999_999 ns, the truth's 4_100_000_000 ns, so its
    last epoch lies 1 ns past the run) WHEN the GNSS node is ticked at every time it asks for
    THEN each asked time is later than the one before and it stops asking (hil sim hung here)."""
    from hil.nodes.gnss_emulator import GnssEmulatorNode, GnssEmulatorOptions

    run = _run(4.1)
    node = GnssEmulatorNode(run, GnssEmulatorOptions(pull_block_s=1.0))
    node.start(0)
    asked: list[int] = []
    while (t := node.next_tick_ns()) is not None and len(asked) < 10_000:
        assert not asked or t > asked[-1], f"asked for {t} again after {asked[-1]}"
        asked.append(t)
        node.tick(t)
    assert node.next_tick_ns() is None and asked[-1] <= int(4.1e9) + 1_000_000
