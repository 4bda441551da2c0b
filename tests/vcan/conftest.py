"""The vcan tier: run against a real SocketCAN ``vcan0`` -- here, or inside user-mode-linux.

- ``vcan0`` exists on this kernel (a bench, a CI runner with vcan, or we *are* inside UML):
  the tests run directly.
- no ``vcan0`` but UML is installed (``tools/uml/install.sh``): the selected vcan tests run once,
  together, inside UML (one boot), and each host-side test reports its UML outcome (pass, the
  failure text, or the skip reason) plus the figures it recorded with ``record_property``.
- neither: every vcan test is skipped with one reason; ``HIL_REQUIRE_VCAN=1`` (CI) makes that a
  failure instead, so a runner that lost its CAN support cannot go green silently.
"""

from __future__ import annotations

import importlib.util
import os
import shlex
import shutil
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
VCAN = "vcan0"
UML_TIMEOUT_S = 240.0


def _uml_module() -> Any:
    spec = importlib.util.spec_from_file_location("hil_uml", REPO / "tools" / "uml" / "uml.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules["hil_uml"] = mod
    spec.loader.exec_module(mod)
    return mod


def vcan_mode() -> str:
    """``direct`` | ``uml`` | ``none``."""
    if Path("/sys/class/net", VCAN).exists():
        return "direct"
    if os.environ.get("HIL_IN_UML") != "1" and _uml_module().uml_available():
        return "uml"
    return "none"


MODE = vcan_mode()
NONE_REASON = (
    f"no {VCAN} on this kernel (needs SocketCAN: `ip link add dev {VCAN} type vcan`) and "
    "user-mode-linux is not installed (tools/uml/install.sh)"
)
_OUTCOMES: dict[str, dict[str, Any]] | None = None


def _is_vcan(item: pytest.Item) -> bool:
    return item.get_closest_marker("vcan") is not None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if MODE != "none" or os.environ.get("HIL_REQUIRE_VCAN") == "1":
        return  # HIL_REQUIRE_VCAN=1: pytest_runtest_setup fails them instead
    for item in items:
        if _is_vcan(item):
            item.add_marker(pytest.mark.skip(reason=NONE_REASON))


def pytest_runtest_setup(item: pytest.Item) -> None:
    if MODE == "none" and _is_vcan(item) and os.environ.get("HIL_REQUIRE_VCAN") == "1":
        pytest.fail(f"HIL_REQUIRE_VCAN=1 but {NONE_REASON}", pytrace=False)


def _testcase_key(classname: str, name: str) -> str:
    module = classname.replace(".", "/") + ".py"
    return f"{module}::{name}"


def _run_in_uml(session: pytest.Session) -> dict[str, dict[str, Any]]:
    uml = _uml_module()
    nodeids = [it.nodeid for it in session.items if _is_vcan(it)]
    res = Path(os.environ.get("HIL_UML_RES") or tempfile.mkdtemp(prefix="hil-vcan-uml-"))
    res.mkdir(parents=True, exist_ok=True)
    junit = res / "junit.xml"
    junit.unlink(missing_ok=True)
    args = " ".join(shlex.quote(n) for n in nodeids)
    script = (
        f"cd {shlex.quote(str(REPO))}\n"
        f"export HIL_IN_UML=1 HIL_LOG=WARNING PYTHONDONTWRITEBYTECODE=1\n"
        f"{shlex.quote(sys.executable)} -m pytest -p no:cacheprovider -q -rs -o junit_family=xunit1 "
        f"--junitxml={shlex.quote(str(junit))} {args}\n"
    )
    result = uml.run_in_uml(script, timeout_s=UML_TIMEOUT_S, res_dir=res)
    outcomes: dict[str, dict[str, Any]] = {}
    if junit.exists():
        for case in ET.parse(junit).getroot().iter("testcase"):
            key = _testcase_key(case.get("classname", ""), case.get("name", ""))
            props = [(p.get("name", ""), p.get("value", "")) for p in case.iter("property")]
            failure = case.find("failure") if case.find("failure") is not None else case.find("error")
            skipped = case.find("skipped")
            if failure is not None:
                text = (failure.get("message") or "") + "\n" + (failure.text or "")
                outcomes[key] = {"outcome": "failed", "text": text, "props": props}
            elif skipped is not None:
                outcomes[key] = {"outcome": "skipped", "text": skipped.get("message") or "", "props": props}
            else:
                outcomes[key] = {"outcome": "passed", "text": "", "props": props, "time": case.get("time")}
    outcomes["__run__"] = {
        "rc": result.rc,
        "wall_s": result.wall_s,
        "tail": f"(results in {res})\n" + (result.output[-4000:] or result.console[-3000:]),
    }
    everything_passed = result.rc == 0 and all(
        outcomes.get(n, {}).get("outcome") in ("passed", "skipped") for n in nodeids
    )
    if everything_passed and not os.environ.get("HIL_UML_RES"):  # kept only to read a failure
        shutil.rmtree(res, ignore_errors=True)
    return outcomes


def _uml_outcome(item: pytest.Item) -> dict[str, Any]:
    global _OUTCOMES
    if _OUTCOMES is None:
        _OUTCOMES = _run_in_uml(item.session)
    rel = item.nodeid
    hit = _OUTCOMES.get(rel)
    if hit is None:
        run = _OUTCOMES["__run__"]
        return {
            "outcome": "failed",
            "text": f"no result from UML for {rel} (rc={run['rc']}, {run['wall_s']:.0f}s):\n{run['tail']}",
            "props": [],
        }
    return hit


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    """In ``uml`` mode the body already ran inside UML: report that outcome instead of running it."""
    if MODE != "uml" or not _is_vcan(pyfuncitem):
        return None
    res = _uml_outcome(pyfuncitem)
    pyfuncitem.user_properties.extend(res["props"])
    pyfuncitem.user_properties.append(("ran_in", "user-mode-linux"))
    if res["outcome"] == "failed":
        pytest.fail(f"inside user-mode-linux:\n{res['text']}", pytrace=False)
    if res["outcome"] == "skipped":
        pytest.skip(f"inside user-mode-linux: {res['text']}")
    return True
