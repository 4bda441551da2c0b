"""The input batching window (``input_batch_ms``): taken by time sync and the fusion only,
bounded, and refused by name when out of range -- from the service options, hil up and the bench.
The CAN bridge's read window (``can_batch_ms``) likewise, and how a window's outputs are grouped
into batches (``batch_sends``)."""

from __future__ import annotations

import pytest

from hil.bench.rig import main as bench_rig
from hil.nodes.base import BatchedInputOptions, OptionsError, decode_options
from hil.runners.live import batch_sends
from hil.runtime.options import fill_options, options_class
from hil.runtime.supervisor import UpOptions


def test_time_sync_and_fusion_take_the_window_and_hil_up_fills_it() -> None:
    assert issubclass(options_class("fusion"), BatchedInputOptions)
    assert issubclass(options_class("timesync"), BatchedInputOptions)
    up = UpOptions(input_batch_ms=10.0)
    assert fill_options("fusion", up)["input_batch_ms"] == 10.0
    assert fill_options("timesync", up)["input_batch_ms"] == 10.0
    assert "input_batch_ms" not in fill_options("can_bridge", up)  # it reads CAN, not an inbox


@pytest.mark.parametrize("bad", [-1.0, 100.5, "ten"])
def test_an_impossible_window_is_refused_naming_the_field(bad: object) -> None:
    with pytest.raises(OptionsError, match="input_batch_ms"):
        decode_options(options_class("fusion"), {"input_batch_ms": bad}, "fusion")


@pytest.mark.parametrize(
    "args",
    [["--input-batch-ms", "x"], ["--input-batch-ms", "0,200"], ["--input-batch-ms", "10", "--rigs", "2"]],
)
def test_bench_rig_refuses_bad_windows_in_one_line(
    args: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as e:
        bench_rig([*args, "--no-write"])
    assert e.value.code == 2
    assert "--input-batch-ms" in capsys.readouterr().err


def test_bench_rig_refuses_an_impossible_read_window(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        bench_rig(["--can-batch-ms", "-1", "--no-write"])
    assert e.value.code == 2
    assert "--can-batch-ms" in capsys.readouterr().err


def test_the_can_bridge_takes_its_read_window_and_hil_up_fills_it() -> None:
    # one default (None: by the IMU's rate), wherever it is written
    from hil.cli import build_parser

    up_args = build_parser().parse_args(["up"])
    assert UpOptions().can_batch_ms is options_class("can_bridge")().can_batch_ms is None  # type: ignore[attr-defined]
    assert up_args.can_batch_ms == UpOptions().can_batch_ms
    assert "can_batch_ms" not in fill_options("can_bridge", UpOptions())  # the service's default
    assert fill_options("can_bridge", UpOptions(can_batch_ms=0.0))["can_batch_ms"] == 0.0
    assert build_parser().parse_args(["up", "--can-batch-ms", "5"]).can_batch_ms == 5.0
    assert "can_batch_ms" not in fill_options("fusion", UpOptions())
    with pytest.raises(OptionsError, match="can_batch_ms"):
        decode_options(options_class("can_bridge"), {"can_batch_ms": 250.0}, "can_bridge")


@pytest.mark.parametrize(
    ("rate_hz", "asked", "window_ms"),
    [
        (400, None, 20.0),
        (500, None, 20.0),
        (1000, None, 10.0),
        (2000, None, 10.0),
        (400, 5.0, 5.0),
        (2000, 0.0, 0.0),
    ],
)
def test_the_read_window_follows_the_imu_rate_unless_one_is_asked_for(
    rate_hz: int, asked: float | None, window_ms: float
) -> None:
    """20 ms up to 500 Hz, where it saves the rig's CPU; 10 ms above, where 20 saved nothing and
    tripled the fused output's tail (docs/benchmarks.md, session 40)."""
    from hil.nodes.can_bridge import CanBridgeNode, CanBridgeOptions
    from hil.runners.sim import SimOptions, sim_run_info

    run = sim_run_info(SimOptions(scenario="straight_level", duration_s=5.0, imu_rate_hz=rate_hz))
    node = CanBridgeNode(run, CanBridgeOptions(can_batch_ms=asked))
    assert node.read_window_ms == window_ms


def test_hil_up_refuses_an_impossible_read_window(capsys: pytest.CaptureFixture[str]) -> None:
    from hil.cli import main as hil_main

    with pytest.raises(SystemExit) as e:
        hil_main(["up", "--can-batch-ms", "-5", "--duration", "1"])
    assert e.value.code == 2
    assert "--can-batch-ms" in capsys.readouterr().err


def test_batched_kinds_go_as_one_list_per_key_without_passing_other_outputs() -> None:
    outs = [
        ("can/vcan0", "f1"),
        ("can/vcan0", "f2"),
        ("sensor/imu", "s1"),
        ("can/vcan0", "f3"),
        ("sensor/imu", "s2"),
        ("timetag/imu", "t"),  # not batched: what follows it goes after it
        ("sensor/imu", "s3"),
        ("capture/imu", "c1"),
        ("capture/imu", "c2"),
        ("nav/ekf15", "n1"),  # solutions go one by one
        ("nav/ekf15", "n2"),
        ("synced/gnss", "g1"),  # and GNSS fixes
        ("synced/gnss", "g2"),
        ("synced/imu", "y1"),
    ]
    assert batch_sends(outs) == [
        ("can/vcan0", ["f1", "f2", "f3"]),
        ("sensor/imu", ["s1", "s2"]),
        ("timetag/imu", "t"),
        ("sensor/imu", ["s3"]),
        ("capture/imu", ["c1", "c2"]),
        ("nav/ekf15", "n1"),
        ("nav/ekf15", "n2"),
        ("synced/gnss", "g1"),
        ("synced/gnss", "g2"),
        ("synced/imu", ["y1"]),
    ]
    assert batch_sends([]) == []
