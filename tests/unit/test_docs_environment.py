"""Every environment variable the code reads is documented in docs/environment.md."""

from __future__ import annotations

import re

from tests.conftest import REPO

READS = re.compile(r"""(?:os\.environ(?:\.get|\.pop)?\s*[\[(]\s*|os\.getenv\(\s*)["']([A-Z][A-Z0-9_]+)["']""")
NAMED = re.compile(r"""\b[A-Z_]*ENV\s*=\s*["']([A-Z][A-Z0-9_]+)["']""")  # MISS_DETECTION_ENV = "HIL_..."


def read_variables() -> dict[str, str]:
    found: dict[str, str] = {}
    for top in ("hil", "services", "tools", "deploy", "tests"):
        for path in (REPO / top).rglob("*.py"):
            text = path.read_text()
            for m in [*READS.finditer(text), *NAMED.finditer(text)]:
                found.setdefault(m.group(1), str(path.relative_to(REPO)))
    return found


def test_every_variable_read_is_documented() -> None:
    doc = (REPO / "docs" / "environment.md").read_text()
    found = read_variables()
    assert "HIL_ZENOH_CONNECT" in found and "HIL_HEAP_TRIM_S" in found  # the grep finds them
    missing = {v: where for v, where in found.items() if f"`{v}`" not in doc}
    assert not missing, f"document these in docs/environment.md: {missing}"
