"""A DUT mapping is checked whole where it is loaded (``hil.can.dut_emulator.load_dut``): a bad
TOML, a missing or unparsable DBC, a field not in the DBC, a bad estimator name or scale is one
``ValueError`` naming the file -- which ``hil up --dut`` refuses up front, the bridge counts as
``errors.dut_config`` and the DUT emulator says as an option error, none of them a traceback."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hil.can.dut_emulator import load_dut
from hil.nodes.base import OptionsError
from hil.nodes.can_bridge import CanBridgeNode, CanBridgeOptions
from hil.nodes.dut_emulator import DutEmulatorNode, DutEmulatorOptions
from hil.runners.sim import SimOptions, sim_run_info
from tests.conftest import REPO

NAVBOX = REPO / "examples" / "dut" / "navbox.toml"

# name -> (how the mapping is spoiled, what the error says)
BAD: dict[str, tuple[str, str]] = {
    "missing_dbc": ("dbc=missing.dbc", "missing.dbc not found"),
    "field_not_in_dbc": ("field=NAV_Position.Nope", "signal 'Nope' is not in message 'NAV_Position'"),
    "not_toml": ("text=not [toml", "not a TOML DUT mapping"),
    "bad_estimator": ("estimator=bad name", "estimator 'bad name' is not a valid name"),
    "scale_not_a_number": ("scale=abc", "scale 'lat_deg' = 'abc' is not a finite number"),
    "garbage_dbc": ("dbc=bad.dbc", "does not parse as a DBC"),
}


def spoiled_mapping(tmp: Path, how: str) -> Path:
    """A copy of examples/dut/navbox.toml (and its DBC) with one thing wrong."""
    shutil.copy(NAVBOX.with_name("navbox.dbc"), tmp / "navbox.dbc")
    (tmp / "bad.dbc").write_text("garbage dbc\n")
    what, _, value = how.partition("=")
    text = NAVBOX.read_text()
    if what == "dbc":
        text = text.replace('dbc = "navbox.dbc"', f'dbc = "{value}"')
    elif what == "field":
        text = text.replace("NAV_Position.Latitude", value)
    elif what == "estimator":
        text = text.replace('estimator = "dut_navbox"', f'estimator = "{value}"')
    elif what == "scale":
        text += f'lat_deg = "{value}"\n'
    else:
        text = value
    out = tmp / "unit.toml"
    out.write_text(text)
    return out


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_mapping_is_one_value_error_naming_the_file(tmp_path: Path, name: str) -> None:
    how, why = BAD[name]
    path = spoiled_mapping(tmp_path, how)
    with pytest.raises(ValueError, match="^" + str(path).replace(".", r"\.")) as err:
        load_dut(path)
    assert why in str(err.value) and "\n" not in str(err.value)
    db, mapping = load_dut(NAVBOX)  # the good one loads
    assert mapping.estimator == "dut_navbox" and db.get_message_by_name("NAV_Attitude")


def test_the_bridge_counts_an_unparsable_dbc_and_goes_on_without_the_unit(tmp_path: Path) -> None:
    path = spoiled_mapping(tmp_path, "dbc=bad.dbc")
    run = sim_run_info(SimOptions(scenario="straight_level", duration_s=2.0))
    node = CanBridgeNode(run, CanBridgeOptions(dut_mapping=str(path)))
    assert node.dut is None
    assert node.counters().get("errors.dut_config") == 1
    assert "does not parse as a DBC" in node.last_error


def test_the_dut_emulator_says_a_bad_mapping_as_an_option_error(tmp_path: Path) -> None:
    path = spoiled_mapping(tmp_path, "field=NAV_Position.Nope")
    run = sim_run_info(SimOptions(scenario="straight_level", duration_s=2.0))
    with pytest.raises(OptionsError, match=r"dut_emulator: option dut_mapping: .*'Nope' is not in message"):
        DutEmulatorNode(run, DutEmulatorOptions(dut_mapping=str(path)))
