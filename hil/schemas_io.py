"""``schemas/`` is generated from the message types; this keeps the two from drifting apart."""

from __future__ import annotations

import json
from pathlib import Path

from hil.messages import CONTRACT_TYPES, json_schema, schema_name

SCHEMAS_DIR = Path(__file__).resolve().parents[1] / "schemas"


def _text(cls: type) -> str:
    return json.dumps(json_schema(cls), indent=2, sort_keys=True) + "\n"


def write_schemas(directory: Path = SCHEMAS_DIR) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    out = []
    for cls in CONTRACT_TYPES:
        p = directory / f"{schema_name(cls)}.json"
        p.write_text(_text(cls))
        out.append(p)
    return out


def check_schemas(directory: Path = SCHEMAS_DIR) -> list[str]:
    """Differences between the checked-in schemas and the message types, one line each."""
    problems = []
    expected = {f"{schema_name(c)}.json": _text(c) for c in CONTRACT_TYPES}
    for name, text in expected.items():
        p = directory / name
        if not p.is_file():
            problems.append(f"{p}: missing (run `hil schemas --write`)")
        elif p.read_text() != text:
            problems.append(f"{p}: differs from hil.messages (run `hil schemas --write` and review the diff)")
    for p in directory.glob("hil.*.json"):
        if p.name not in expected:
            problems.append(f"{p}: no message type has this schema")
    return problems
