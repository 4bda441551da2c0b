"""The rig's endpoint file and credential (hil/bus/endpoint.py), the routers' default listeners, and
the secure profile's per-role publish rules against what each service really publishes."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from hil.bus.endpoint import RigAccess, find_rig, read_endpoint, runtime_dir, viewer_bus
from hil.bus.session import BusConfigError

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def rt(tmp_path: Path) -> dict[str, str]:
    d = tmp_path / "rt"
    d.mkdir(mode=0o700)
    return {"HIL_RUNTIME_DIR": str(d)}


def _access(rig: str, env: dict[str, str], pid: int | None = None) -> RigAccess:
    a = RigAccess.new(rig, "tcp/127.0.0.1:1", authenticated=True)
    a.directory = Path(env["HIL_RUNTIME_DIR"])
    if pid is not None:
        a.pid = pid
    return a


def test_a_run_writes_private_files_a_viewer_finds_and_removes_them(rt: dict[str, str]) -> None:
    a = _access("bench", rt)
    a.write()
    for p in (a.name_path, a.config_path, a.users_path):
        assert stat.S_IMODE(p.stat().st_mode) == 0o600, p
    assert a.users_path.read_text() == f"hil:{a.password}\n" and len(a.password) >= 32
    found, why = find_rig("bench", rt)
    assert found is not None and found.endpoint == a.endpoint and found.pid == os.getpid(), why
    # the file is a zenoh configuration any zenoh program opens as it is
    conf = zenoh.Config.from_file(str(a.name_path))
    assert json.loads(conf.get_json("connect/endpoints")) == [a.endpoint]
    assert json.loads(conf.get_json("transport/auth/usrpwd/password")) == a.password
    cfg, how = viewer_bus("bench", rt)
    assert cfg.connect == (a.endpoint,) and cfg.listen == () and cfg.config_file == str(a.name_path), how
    a.remove()
    assert not any(p.exists() for p in (a.name_path, a.config_path, a.users_path))
    assert find_rig("bench", rt)[0] is None


def test_a_later_run_of_the_same_rig_keeps_its_name_file(rt: dict[str, str]) -> None:
    first = _access("bench", rt)
    first.write()
    second = _access("bench", rt, pid=os.getppid())  # another live process
    second.write()
    first.remove()  # the first run ends while the second goes on
    found = read_endpoint(second.name_path)
    assert found is not None and found.pid == second.pid
    assert second.users_path.exists() and not first.users_path.exists()


def test_a_file_left_by_a_killed_run_is_ignored(rt: dict[str, str]) -> None:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    dead = _access("bench", rt, pid=p.pid)
    dead.write()
    found, why = find_rig("bench", rt)
    assert found is None and "ended" in why
    cfg, how = viewer_bus("bench", rt)
    assert cfg.config_file is None and "ended" in how


def test_the_environment_wins_over_the_endpoint_file(rt: dict[str, str]) -> None:
    _access("bench", rt).write()
    env = dict(rt, HIL_ZENOH_CONNECT="tcp/10.0.0.1:7447", HIL_ZENOH_MODE="client")
    cfg, how = viewer_bus("bench", env)
    assert cfg.connect == ("tcp/10.0.0.1:7447",) and cfg.mode == "client" and "environment" in how


def test_a_runtime_directory_others_can_enter_is_refused(tmp_path: Path) -> None:
    d = tmp_path / "open"
    d.mkdir()
    d.chmod(0o755)
    with pytest.raises(BusConfigError, match="not a private directory"):
        runtime_dir({"HIL_RUNTIME_DIR": str(d)})
    with pytest.raises(BusConfigError):
        runtime_dir({"HIL_RUNTIME_DIR": str(d)}, create=True)
    assert find_rig("bench", {"HIL_RUNTIME_DIR": str(d)})[0] is None


def test_an_open_bus_writes_no_credential(rt: dict[str, str]) -> None:
    a = RigAccess.new("bench", "tcp/127.0.0.1:1", authenticated=False)
    a.directory = Path(rt["HIL_RUNTIME_DIR"])
    a.write()
    assert not a.users_path.exists() and a.hub_config().config_file is None
    assert "transport" not in json.loads(a.name_path.read_text().split("\n", 3)[3])


def test_routers_listen_on_loopback_unless_told_otherwise() -> None:
    conf = zenoh.Config.from_file(str(REPO / "deploy/zenoh/router.json5"))
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert listen and all(e.startswith("tcp/127.0.0.1:") for e in listen), listen
    from hil.cli import build_parser

    a = build_parser().parse_args(["router"])
    assert a.listen is None  # cmd_router then listens on ROUTER_LISTEN
    from hil.cli import ROUTER_LISTEN

    assert ROUTER_LISTEN.startswith("tcp/127.0.0.1:")


def _acl() -> dict[str, object]:
    conf = zenoh.Config.from_file(str(REPO / "deploy/zenoh/router-secure.json5"))
    return json.loads(conf.get_json("access_control"))  # type: ignore[no-any-return]


def _may_publish(acl: dict, role: str, key: str) -> bool:  # type: ignore[type-arg]
    subject = next(s["id"] for s in acl["subjects"] if s["cert_common_names"] == [f"hil-{role}"])
    rule_ids = {r for p in acl["policies"] if subject in p["subjects"] for r in p["rules"]}
    verdicts = {
        rule["permission"]
        for rule in acl["rules"]
        if rule["id"] in rule_ids
        and "ingress" in rule["flows"]
        and "put" in rule["messages"]
        and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in rule["key_exprs"])
    }
    return "allow" in verdicts and "deny" not in verdicts  # a matching deny wins (measured: test_security)


def test_the_secure_profile_lets_each_service_publish_what_it_publishes_and_no_more() -> None:
    from hil.nodes import NODES, node_class

    acl = _acl()
    # every key each service publishes at run time (its node's outputs, plus the dynamic ones)
    published = {name: list(node_class(name).outputs) for name in NODES if name != "fusion"}
    published["fusion"] = ["nav/ins", "nav/ekf15", "health/ekf15", "fusion/journal", "fusion/config"]
    published["timesync"] += ["clock/imu", "clock/gnss"]
    published["can_bridge"] += ["can/vcan0", "nav/dut_navbox"]
    published["gnss_bridge"] += ["serial/gnss0"]
    for name, keys in published.items():
        role = name.replace("_", "-")
        for key in [*keys, f"status/{name}", f"event/{name}"]:
            assert _may_publish(acl, role, f"hil/bench/{key}"), (role, key)
        others = {k for n, ks in published.items() if n != name for k in ks} - set(keys)
        if name in (
            "gnss_emulator",
            "gnss_bridge",
        ):  # both may put sensor/gnss: the receiver, read either way
            others -= {"sensor/gnss"}
        for key in sorted(others):
            assert not _may_publish(acl, role, f"hil/bench/{key}"), (role, "may also publish", key)
    for key in ("truth", "sensor/imu", "nav/ekf15", "control/fault", "status/world"):
        assert not _may_publish(acl, "monitor", f"hil/bench/{key}")
    assert _may_publish(acl, "operator", "hil/bench/control/fault")


def test_a_killed_runs_files_are_removed_and_nothing_else(tmp_path: Path) -> None:
    """``hil up`` sweeps its runtime directory: the ``.users`` and ``.json5`` of a run whose
    supervisor is gone go (its secret does not linger); a live run's stay, and so does every
    name file, even of a rig whose name ends in a dead pid."""
    from hil.bus.endpoint import remove_stale_run_files

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = RigAccess("bench", "tcp/127.0.0.1:7447", gone.pid, password="s", directory=tmp_path)
    live = RigAccess("bench", "tcp/127.0.0.1:7448", os.getpid(), password="t", directory=tmp_path)
    # a rig named "<x>-<dead pid>" run by this (live) process: its name file looks like a run file
    odd = RigAccess(f"old-{gone.pid}", "tcp/127.0.0.1:7449", os.getpid(), password="u", directory=tmp_path)
    for a in (dead, odd, live):  # live last: bench.json5 names the live run
        a.write()
    stray = tmp_path / f"notes-{gone.pid}.json5"  # not an endpoint file: left alone
    stray.write_text("{}\n")
    removed = remove_stale_run_files(tmp_path)
    assert sorted(removed) == sorted([dead.users_path, dead.config_path])
    assert not dead.users_path.exists() and not dead.config_path.exists()
    for p in (live.users_path, live.config_path, live.name_path, odd.name_path, odd.config_path, stray):
        assert p.exists(), p
