"""docs/faults.md: every example works as written, and every fault kind is documented.

The TOML examples go through the scenario loader (appended to a built-in scenario, as a user
would paste them), the `hil fault` lines through the real CLI parser and the same check the CLI
runs before sending; the table of kinds matches hil/faults.py and the event detail shown is
what the services write."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

from hil.cli import build_parser
from hil.faults import FAULT_KINDS, SIM_NOT_APPLICABLE, check_fault, fault_detail
from hil.nav.scenario import load_scenario
from hil.runners.sim import not_applicable_faults
from hil.runtime.scenario_io import scenario_from_text
from tests.conftest import REPO

DOC = REPO / "docs" / "faults.md"
ALL_KINDS = {*FAULT_KINDS, "gnss_pulse"}  # the pulse is scenario-only


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", DOC.read_text(), flags=re.S)


def test_every_toml_example_loads_through_the_scenario_loader() -> None:
    base = load_scenario("straight_level").source_text
    seen: set[str] = set()
    blocks = _blocks("toml")
    assert len(blocks) >= 11
    for block in blocks:
        s = scenario_from_text(base + "\n" + block, "doc_example")  # raises ScenarioError if wrong
        kinds = [ev.kind for ev in s.events]
        assert kinds == re.findall(r'^kind = "(\w+)"', block, flags=re.M), block
        seen.update(kinds)
    assert seen == ALL_KINDS


def test_every_hil_fault_example_parses_and_passes_the_cli_check() -> None:
    lines = [
        ln for b in _blocks("sh") for ln in b.splitlines() if ln.startswith("hil fault ") and "KIND" not in ln
    ]
    assert {shlex.split(ln)[2] for ln in lines} == set(FAULT_KINDS)
    parser = build_parser()
    for line in lines:
        a = parser.parse_args(shlex.split(line)[1:])
        params = {k: float(v) for k, _eq, v in (p.partition("=") for p in a.param)}
        check_fault(a.kind, a.target, params)  # what cmd_fault runs before it sends


def test_the_table_names_every_kind_with_its_service_and_whether_hil_sim_applies_it() -> None:
    rows = {}
    for ln in DOC.read_text().splitlines():
        m = re.match(r"\| `(\w+)` \| (.*?) \| (.*?) \| (.*?) \| (.*?) \|$", ln)
        if m:
            rows[m.group(1)] = m.groups()[1:]
    assert set(rows) >= ALL_KINDS
    for kind in ALL_KINDS:
        service, _scenario, _cmd, sim = rows[kind]
        owner = FAULT_KINDS.get(kind, ("gnss_emulator",))[0]
        if owner.startswith("<"):
            assert "emulator" in service
        elif owner == "supervisor":
            assert "supervisor" in service
        else:
            assert owner in service, (kind, service)
        assert sim.startswith("**no**") == (kind in SIM_NOT_APPLICABLE), (kind, sim)
        assert f"### `{kind}`" in DOC.read_text() or f"and `{kind}`" in DOC.read_text(), kind


def test_the_event_detail_and_the_sim_warning_shown_are_what_the_code_writes() -> None:
    text = DOC.read_text()
    shown = json.loads(_blocks("json")[0])
    assert (
        json.loads(
            fault_detail("imu_frame_loss", 3_000_000_000, 4_000_000_000, {"percent": 25.0}, "scenario")
        )
        == shown
    )
    base = load_scenario("straight_level").source_text
    s = scenario_from_text(
        base + '\n[[event]]\nkind = "kill_service"\nt_start_s = 5.0\nservice = "fusion"\n', "x"
    )
    lines, _ = not_applicable_faults(s.events, 10.0)
    assert f"`hil sim: warning: {lines[0][:48]}" in text


def test_the_page_is_linked_from_the_docs_index_and_the_readme() -> None:
    assert "(faults.md)" in (REPO / "docs" / "index.md").read_text()
    assert "(docs/faults.md)" in Path(REPO / "README.md").read_text()
