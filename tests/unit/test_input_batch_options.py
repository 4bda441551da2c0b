"""The input batching window (``input_batch_ms``): taken by time sync and the fusion only,
bounded, and refused by name when out of range -- from the service options, hil up and the bench."""

from __future__ import annotations

import pytest

from hil.bench.rig import main as bench_rig
from hil.nodes.base import BatchedInputOptions, OptionsError, decode_options
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
