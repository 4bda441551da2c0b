"""How ``make test`` (``pytest -n 2``) hands the suite to its two workers (tests/conftest.py's
scheduler): every live test in one unit, so that no two rigs run at once; the vcan tier in a unit
of its own; the pure tests, and modules that start no rig, pooled."""

from __future__ import annotations

import re
from pathlib import Path

from tests.conftest import IMAGE_SCOPE, POOLED_MODULES, SERIAL_SCOPE, VCAN_SCOPE, last_live_last, xdist_scope

REPO = Path(__file__).resolve().parents[2]


def test_live_tests_share_one_unit_and_the_vcan_tier_has_its_own() -> None:
    live = [
        "tests/integration/test_up.py::test_up_exits_zero_and_prints_a_summary",
        "tests/integration/test_bad_input.py::test_garbage_on_every_subscribed_key_is_counted_and_survived",
        "tests/multihost/test_router_restart.py::test_rig_across_hosts_survives_a_router_restart",
        "tests/docker/test_compose_up.py::test_compose_up_records_the_whole_rig",
        "tests/test_something_at_the_top.py::test_x",
    ]
    assert {xdist_scope(n) for n in live} == {SERIAL_SCOPE}
    vcan = [
        "tests/vcan/test_socketcan.py::test_sustained_run_loses_no_sample[fd]",
        "tests/vcan/test_replay_vcan.py::test_replayed_frames_decode_to_the_recorded_samples_with_their_spacing",
    ]
    assert {xdist_scope(n) for n in vcan} == {VCAN_SCOPE} != {SERIAL_SCOPE}


def test_the_image_is_built_beside_the_live_tests_and_composed_after_them() -> None:
    """The image's build is a unit of its own (the free worker makes it while the live tests
    run); the compose test that runs it goes last in the live unit, and only it moves."""
    image = [
        "tests/docker/test_image.py::test_the_image_holds_this_checkout_s_package",
        "tests/docker/test_image.py::test_the_cli_answers_in_the_image",
    ]
    assert {xdist_scope(n) for n in image} == {IMAGE_SCOPE}
    assert IMAGE_SCOPE not in (SERIAL_SCOPE, VCAN_SCOPE)
    compose = "tests/docker/test_compose_up.py::test_compose_up_records_the_whole_rig"
    nodeids = [
        "tests/docker/test_compose_static.py::test_a",
        compose,
        "tests/docker/test_image.py::test_b",
        "tests/integration/test_up.py::test_c",
        "tests/multihost/test_security.py::test_d",
        "tests/unit/test_e.py::test_f",
    ]
    ordered = [nodeids[i] for i in last_live_last(nodeids)]
    assert ordered == [*nodeids[:1], *nodeids[2:], compose]
    without = nodeids[2:] + nodeids[:1]
    assert [without[i] for i in last_live_last(without)] == without  # nothing else moves


def test_pure_tests_are_pooled_one_by_one_and_offline_modules_whole() -> None:
    a = "tests/unit/test_jit.py::test_a"
    b = "tests/replay/test_golden.py::test_b[x-y]"
    assert xdist_scope(a) == a and xdist_scope(b) == b
    tools = "tests/integration/test_record_tools.py"
    scopes = {xdist_scope(f"{tools}::test_filter"), xdist_scope(f"{tools}::test_merge[split]")}
    assert scopes == {tools}


def test_a_pooled_module_starts_no_rig_and_opens_no_bus() -> None:
    """The pooled modules run beside a live test: one that started a rig, a service, or a Zenoh
    session would measure it and be measured (or meet its traffic)."""
    live_markers = re.compile(
        r"hil_cmd\(\s*\"(up|service|replay|monitor|foxglove)\"|open_session|zenoh_hub|import zenoh|"
        r"Rig\(|\"up\",|docker|netns"
    )
    for module in POOLED_MODULES:
        source = (REPO / module).read_text()
        assert module.startswith("tests/") and (REPO / module).is_file(), module
        found = live_markers.search(source)
        assert found is None, (module, found and found.group(0))
