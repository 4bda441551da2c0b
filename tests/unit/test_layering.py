"""The architecture rules (tests/layering.py) hold over hil/ and services/.

One test per rule, so a failure names the rule; each message lists every violation as
``file:line: [rule] what``. The self-tests build small synthetic trees and check that each rule
does fire: a checker that finds nothing because it looks at nothing would pass the real tests.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.layering import (
    LAYERS,
    MAX_FUNCTION_LINES,
    Module,
    Violation,
    check_all,
    check_cycles,
    check_function_length,
    check_layers,
    check_pure,
    check_services_imports,
    layer_of,
    load_modules,
)

Check = Callable[[dict[str, Module]], list[Violation]]


@pytest.fixture(scope="module")
def repo_modules() -> dict[str, Module]:
    return load_modules(Path(__file__).resolve().parents[2])


def _assert_none(found: list[Violation], what: str) -> None:
    assert not found, f"{len(found)} {what}:\n" + "\n".join(str(v) for v in found)


def test_scans_the_real_tree(repo_modules: dict[str, Module]) -> None:
    # guards against a vacuous pass (wrong root, empty glob)
    assert {"hil.cli", "hil.nav.types", "hil.estimators.base", "services.fusion"} <= set(repo_modules)
    assert len(repo_modules) > 50


def test_no_import_cycles(repo_modules: dict[str, Module]) -> None:
    _assert_none(check_cycles(repo_modules), "import cycle(s)")


def test_only_the_cli_imports_services(repo_modules: dict[str, Module]) -> None:
    _assert_none(check_services_imports(repo_modules), "import(s) of services from hil/")


def test_pure_packages_stay_pure(repo_modules: dict[str, Module]) -> None:
    _assert_none(check_pure(repo_modules), "impure import(s) in a pure package")


def test_imports_follow_the_layers(repo_modules: dict[str, Module]) -> None:
    _assert_none(check_layers(repo_modules), "import(s) against the layer order")


def test_functions_are_short(repo_modules: dict[str, Module]) -> None:
    _assert_none(check_function_length(repo_modules), f"function(s) over {MAX_FUNCTION_LINES} lines")


# ---------------------------------------------------------------------------------------------
# self-tests on synthetic trees


def _tree(root: Path, files: dict[str, str]) -> dict[str, Module]:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    for pkg in ("hil", "services"):
        (root / pkg).mkdir(exist_ok=True)
        (root / pkg / "__init__.py").touch()
    return load_modules(root)


def _rules(found: list[Violation]) -> set[tuple[str, str, int]]:
    return {(v.rule, v.path, v.line) for v in found}


def test_layer_table_lookup() -> None:
    assert layer_of("hil.nav.types") == 0  # longest prefix wins over hil.nav
    assert layer_of("hil.nav.scenario") == 1
    assert layer_of("hil.estimators.base") == 2
    assert layer_of("hil") == 5 and layer_of("hil.cli") == 8
    assert layer_of("services.fusion") == 7
    assert layer_of("hil.nowhere") is None  # "hil" is the package __init__ only
    assert sorted(LAYERS) == list(range(9))


def test_catches_a_cycle_through_a_function_level_relative_import(tmp_path: Path) -> None:
    mods = _tree(
        tmp_path,
        {
            "hil/nav/__init__.py": "",
            "hil/nav/a.py": "import hil.nav.b\n",
            "hil/nav/b.py": "def f() -> None:\n    from .c import x\n",
            "hil/nav/c.py": "from hil.nav import a\nx = 1\n",
            "hil/nav/d.py": "from hil.nav import a  # imports a, not part of a cycle\n",
        },
    )
    found = check_cycles(mods)
    assert len(found) == 1, found
    assert "hil.nav.a -> hil.nav.b -> hil.nav.c -> hil.nav.a" in found[0].message
    assert "hil/nav/b.py:2 imports hil.nav.c" in found[0].message


def test_catches_a_long_function(tmp_path: Path) -> None:
    def body(indent: str, n: int) -> str:
        return "".join(f"{indent}x{i} = {i}\n" for i in range(n))

    at_limit = f"def ok() -> None:\n{body('    ', MAX_FUNCTION_LINES - 1)}\n"
    over = f"class C:\n    if True:\n        def m(self) -> None:\n{body(' ' * 12, MAX_FUNCTION_LINES)}"
    mods = _tree(tmp_path, {"hil/report/__init__.py": "", "hil/report/long.py": at_limit + over})
    found = check_function_length(mods)
    line = MAX_FUNCTION_LINES + 4  # the def of C.m
    assert _rules(found) == {("length", "hil/report/long.py", line)}, found
    assert f"hil.report.long.C.m is {MAX_FUNCTION_LINES + 1} lines" in found[0].message


def test_catches_impure_imports(tmp_path: Path) -> None:
    mods = _tree(
        tmp_path,
        {
            "hil/fusion/__init__.py": "",
            "hil/fusion/core.py": "import numpy\n\ndef f() -> None:\n    import zenoh\n",
            "hil/sensors/__init__.py": "",
            "hil/sensors/imu.py": "from time import monotonic\nimport can\n",
            "hil/nodes/__init__.py": "",
            "hil/nodes/n.py": "import can\nimport hil.can.codec\nimport threading\n",
            "hil/can/__init__.py": "",
            "hil/can/codec.py": "import time\n",  # hil.can is not a pure package
        },
    )
    assert _rules(check_pure(mods)) == {
        ("pure", "hil/fusion/core.py", 4),
        ("pure", "hil/sensors/imu.py", 1),
        ("pure", "hil/sensors/imu.py", 2),
        ("pure", "hil/nodes/n.py", 3),  # can.Message is allowed in hil.nodes, threading is not
    }


def test_catches_services_imports_and_upward_imports(tmp_path: Path) -> None:
    mods = _tree(
        tmp_path,
        {
            "hil/cli.py": "import services.fusion\n",
            "hil/bench/__init__.py": "",
            "hil/bench/x.py": "def f() -> None:\n    from services import fusion\n",
            "hil/nav/__init__.py": "",
            "hil/nav/types.py": "",
            "hil/nav/t.py": "from hil.nav.types import *\nfrom hil import faults\n",
            "hil/faults.py": "from hil.nav import t\n",
            "hil/oddity.py": "",
            "services/fusion.py": "from hil import cli\n",
        },
    )
    assert _rules(check_services_imports(mods)) == {("no-services", "hil/bench/x.py", 2)}
    assert _rules(check_layers(mods)) == {
        ("layer", "hil/bench/x.py", 2),  # 6 -> 7
        ("layer", "hil/nav/t.py", 2),  # 1 -> 2
        ("layer", "hil/oddity.py", 1),  # in no layer
        ("layer", "services/fusion.py", 1),  # 7 -> 8
    }


@pytest.mark.parametrize(
    "check", [check_cycles, check_services_imports, check_pure, check_layers, check_function_length]
)
def test_a_clean_tree_passes(tmp_path: Path, check: Check) -> None:
    mods = _tree(
        tmp_path,
        {
            "hil/nav/__init__.py": "",
            "hil/nav/types.py": "import numpy\n",
            "hil/nav/earth.py": "from .types import *\nimport math\n",
            "hil/cli.py": "import services.world\nimport hil.nav.earth\n",
            "services/world.py": "import time\nfrom hil.nav import earth\n",
        },
    )
    assert check(mods) == []


def test_check_all_runs_every_rule(tmp_path: Path) -> None:
    _tree(tmp_path, {"hil/nav/__init__.py": "", "hil/nav/a.py": "import hil.nav.a\nimport zenoh\n"})
    assert [v.rule for v in check_all(tmp_path)] == ["pure"]  # a self-import is no cycle
