"""``hil fault``'s checks match what the rig accepts, and a fault's event keeps its parameters.

A command every service would throw away (``rejected.control.fault.invalid``) must be refused
before it is sent; one bound for ``--duration`` (the message's); an offset recorded as applied."""

from __future__ import annotations

import json
import re
import typing

import pytest

from hil.cli import UserError, _checked_fault_command, build_parser
from hil.faults import MAX_DURATION_S, FaultError, check_fault
from hil.messages import FaultCommand, encode
from hil.messages import params as fault_params
from hil.nodes.gnss_emulator import GnssEmulatorNode
from hil.runners.sim import SimOptions, sim_run_info


@pytest.mark.parametrize("target", ["bad target!", "fusion;rm", "x" * 65, "a/b"])
def test_a_target_the_message_refuses_is_refused_naming_target(target: str) -> None:
    cmd = FaultCommand(seq=1, stamp_ns=0, kind="kill_service", target=target)
    with pytest.raises(UserError, match=re.escape(f"--target {target!r}: not a service or sensor name")):
        _checked_fault_command(cmd)


def test_a_valid_command_passes_the_message_check_unchanged() -> None:
    cmd = FaultCommand(seq=1, stamp_ns=0, kind="kill_service", target="fusion", duration_s=3.0)
    assert encode(_checked_fault_command(cmd)) == encode(cmd)


def test_duration_has_one_bound_the_messages() -> None:
    parser = build_parser()
    assert parser.parse_args(["fault", "gnss_outage", "--duration", "1e6"]).duration == MAX_DURATION_S
    with pytest.raises(SystemExit):
        parser.parse_args(["fault", "gnss_outage", "--duration", "1.5e6"])
    meta = typing.get_type_hints(FaultCommand, include_extras=True)["duration_s"].__metadata__[0]
    assert meta.le == MAX_DURATION_S


@pytest.mark.parametrize(
    ("kind", "params", "why"),
    [
        ("can_burst_error", {"frames": 1.5}, "frames counts, so it must be a whole number"),
        ("gnss_jump", {"n_m": 1e308}, "n_m must be in [-1e+07, 1e+07] m"),
        ("gnss_spoof", {"d_m": -2e7}, "d_m must be in [-1e+07, 1e+07] m"),
        ("gnss_velocity_glitch", {"e_mps": 1e5}, "e_mps must be in [-10000, 10000] m/s"),
    ],
)
def test_counts_must_be_whole_and_offsets_plausible(kind: str, params: dict[str, float], why: str) -> None:
    with pytest.raises(FaultError, match=re.escape(why)):
        check_fault(kind, "", params)
    check_fault(kind, "", {k: 1.0 for k in params})  # a plausible one passes


def test_a_commanded_gnss_jump_records_its_offset_in_its_event() -> None:
    node = GnssEmulatorNode(sim_run_info(SimOptions(scenario="straight_level", duration_s=5.0)))
    cmd = FaultCommand(
        seq=0, stamp_ns=0, kind="gnss_jump", params=fault_params({"n_m": 30.0, "e_m": -10.0}), duration_s=1.0
    )
    assert node.on_message("control/fault", cmd, 1_000_000_000) == []
    events = [m for _k, m in node.tick(1_500_000_000) if getattr(m, "kind", "") == "fault_start"]
    assert len(events) == 1
    assert json.loads(events[0].detail)["params"] == {"offset_ned_m": [30.0, -10.0, 0.0]}
