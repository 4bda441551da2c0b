"""``schemas/`` is generated from the message types; this keeps the two from drifting apart, and
checks that every schema is one Foxglove and Lichtblick can decode (``parse_json_schema``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

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
    """Differences between the checked-in schemas and the message types, and what a viewer would
    refuse in them (``foxglove_schema_problems``), one line each."""
    problems = []
    for cls in CONTRACT_TYPES:
        problems += foxglove_schema_problems(json_schema(cls), schema_name(cls))
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


# -- Foxglove's JSON Schema rules ----------------------------------------------------------------


class SchemaRejected(ValueError):
    """A viewer would refuse this JSON Schema (and drop every message of its channel)."""


DIALECTS = ("foxglove", "lichtblick")


def parse_json_schema(
    root: dict[str, Any], root_type_name: str, dialect: str = "foxglove"
) -> dict[str, list[dict[str, Any]]]:
    """A port of ``packages/mcap-support/src/parseJsonSchema.ts``: the datatypes a viewer builds
    from a channel's JSON Schema, or ``SchemaRejected`` where the TypeScript throws.

    The two dialects differ only where the sources do: Foxglove's takes a field whose ``oneOf``
    alternatives all have numeric ``const`` (an enum) and types ``integer`` as ``uint32``;
    Lichtblick's ignores ``oneOf`` (such a field needs a ``type`` there) and types ``integer`` as
    ``float64``. Anything else -- ``null``, a union (``anyOf``, a list of types), a ``$ref``, an
    object without ``properties``, an array without ``items`` -- is refused by both. (Where the
    TypeScript fails with a TypeError, e.g. ``Object.entries(undefined)``, so does this, as
    ``SchemaRejected``.)
    """
    if dialect not in DIALECTS:
        raise ValueError(f"dialect {dialect!r}: one of {DIALECTS}")
    integer = "uint32" if dialect == "foxglove" else "float64"
    datatypes: dict[str, list[dict[str, Any]]] = {}

    def add(schema: Any, type_name: str, key_path: list[str]) -> None:
        if not isinstance(schema, dict) or schema.get("type") != "object":
            got = schema.get("type") if isinstance(schema, dict) else schema
            raise SchemaRejected(f'Expected "type": "object" for schema {type_name}, got {json.dumps(got)}')
        props = schema.get("properties")
        if not isinstance(props, dict):
            raise SchemaRejected(
                f"TypeError: {'.'.join([*key_path]) or type_name} is an object without properties "
                "(Object.entries(undefined))"
            )
        fields: list[dict[str, Any]] = []
        for name, field in props.items():
            path = ".".join([*key_path, name])
            fs = field if isinstance(field, dict) else {}
            one_of = fs.get("oneOf")
            if dialect == "foxglove" and isinstance(one_of, list):
                if all(isinstance(a, dict) and _is_number(a.get("const")) for a in one_of):
                    for a in one_of:
                        fields.append({"name": a.get("title"), "type": "uint32", "isConstant": True})
                    fields.append({"name": name, "type": "uint32"})
                    continue
                raise SchemaRejected(
                    f"Unsupported type for {path}: oneOf alternatives must have number values"
                )
            kind = fs.get("type")
            if kind == "boolean":
                fields.append({"name": name, "type": "bool"})
            elif kind == "string":
                enc = fs.get("contentEncoding")
                if enc is None:
                    fields.append({"name": name, "type": "string"})
                elif enc == "base64":
                    fields.append({"name": name, "type": "uint8", "isArray": True})
                else:
                    raise SchemaRejected(f"Unsupported contentEncoding {json.dumps(enc)} in {path}")
            elif kind == "number":
                fields.append({"name": name, "type": "float64"})
            elif kind == "integer":
                fields.append({"name": name, "type": integer})
            elif kind == "object":
                add(fs, f"{type_name}.{name}", [*key_path, name])
                fields.append({"name": name, "type": f"{type_name}.{name}", "isComplex": True})
            elif kind == "array":
                fields.append(array_field(fs, name, type_name, key_path))
            else:
                raise SchemaRejected(f"Unsupported type {_js(kind)} for {path}")
        datatypes[type_name] = fields

    def array_field(fs: dict[str, Any], name: str, type_name: str, key_path: list[str]) -> dict[str, Any]:
        path = ".".join([*key_path, name])
        items = fs.get("items")
        if not isinstance(items, dict):
            raise SchemaRejected(
                f"TypeError: array {path} has no items schema (itemSchema.type of undefined)"
            )
        kind = items.get("type")
        if kind == "boolean":
            return {"name": name, "type": "bool", "isArray": True}
        if kind == "string":
            if items.get("contentEncoding") is not None:
                enc = json.dumps(items["contentEncoding"])
                raise SchemaRejected(f"Unsupported contentEncoding {enc} for array item {path}")
            return {"name": name, "type": "string", "isArray": True}
        if kind == "number":
            return {"name": name, "type": "float64", "isArray": True}
        if kind == "integer":
            return {"name": name, "type": integer, "isArray": True}
        if kind == "object":
            add(items, f"{type_name}.{name}", [*key_path, name])
            return {"name": name, "type": f"{type_name}.{name}", "isComplex": True, "isArray": True}
        raise SchemaRejected(f"Unsupported type {_js(kind)} for array item {path}")

    add(root, root_type_name, [])
    return datatypes


def _js(v: Any) -> str:
    """``JSON.stringify`` as the TypeScript prints it (a missing value is ``undefined``)."""
    return "undefined" if v is None else json.dumps(v)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def foxglove_schema_problems(schema: Any, name: str) -> list[str]:
    """Why Foxglove or Lichtblick would refuse this JSON Schema, one line per dialect ([] if none)."""
    out = []
    for dialect in DIALECTS:
        try:
            parse_json_schema(schema, name, dialect)
        except SchemaRejected as err:
            out.append(f"{name}: {dialect} refuses it: {err}")
    return out
