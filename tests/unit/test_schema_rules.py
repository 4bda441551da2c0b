"""Every schema decodes in Foxglove: the rules of Foxglove's and Lichtblick's ``parseJsonSchema``
(ported in ``hil.schemas_io.parse_json_schema``) on every schema in ``schemas/`` and on every
schema a fresh recording embeds; and the recordings made before the change still decode."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from hil.messages import (
    CONTRACT_TYPES,
    FaultCommand,
    NavSolution,
    ServiceStatus,
    current_form,
    decode,
    encode,
    json_schema,
    schema_name,
)
from hil.schemas_io import (
    DIALECTS,
    SCHEMAS_DIR,
    SchemaRejected,
    foxglove_schema_problems,
    parse_json_schema,
)
from hil.wellknown import SCHEMAS


def _obj(**props: Any) -> dict[str, Any]:
    return {"type": "object", "properties": props}


# (case, schema, accepted by foxglove, accepted by lichtblick): one case per branch of the source
CASES: list[tuple[str, dict[str, Any], bool, bool]] = [
    (
        "scalars",
        _obj(a={"type": "boolean"}, b={"type": "string"}, c={"type": "number"}, d={"type": "integer"}),
        True,
        True,
    ),
    ("base64 string", _obj(a={"type": "string", "contentEncoding": "base64"}), True, True),
    ("other encoding", _obj(a={"type": "string", "contentEncoding": "gzip"}), False, False),
    ("nested object", _obj(a=_obj(x={"type": "number"})), True, True),
    (
        "arrays of scalars",
        _obj(
            a={"type": "array", "items": {"type": "number"}},
            b={"type": "array", "items": {"type": "integer"}},
        ),
        True,
        True,
    ),
    (
        "array of objects",
        _obj(a={"type": "array", "items": _obj(key={"type": "string"}, value={"type": "integer"})}),
        True,
        True,
    ),
    (
        "array of encoded strings",
        _obj(a={"type": "array", "items": {"type": "string", "contentEncoding": "base64"}}),
        False,
        False,
    ),
    ("array without items", _obj(a={"type": "array"}), False, False),
    (
        "array of arrays",
        _obj(a={"type": "array", "items": {"type": "array", "items": {"type": "number"}}}),
        False,
        False,
    ),
    ("null", _obj(a={"type": "null"}), False, False),
    ("optional (anyOf with null)", _obj(a={"anyOf": [{"type": "number"}, {"type": "null"}]}), False, False),
    ("type list", _obj(a={"type": ["number", "null"]}), False, False),
    ("$ref", {**_obj(a={"$ref": "#/$defs/X"}), "$defs": {"X": _obj()}}, False, False),
    (
        "map (object without properties)",
        _obj(a={"type": "object", "additionalProperties": {"type": "integer"}}),
        False,
        False,
    ),
    ("root not an object", {"type": "array", "items": {"type": "number"}}, False, False),
    (
        "enum as oneOf consts",
        _obj(a={"oneOf": [{"title": "A", "const": 0}, {"title": "B", "const": 1}]}),
        True,
        False,
    ),
    ("enum with a type", _obj(a={"type": "integer", "oneOf": [{"title": "A", "const": 0}]}), True, True),
    ("oneOf of types", _obj(a={"oneOf": [{"type": "number"}, {"type": "string"}]}), False, False),
]


@pytest.mark.parametrize("case, schema, foxglove, lichtblick", CASES, ids=[c[0] for c in CASES])
def test_the_port_accepts_and_refuses_as_the_typescript_does(
    case: str, schema: dict[str, Any], foxglove: bool, lichtblick: bool
) -> None:
    for dialect, accepted in (("foxglove", foxglove), ("lichtblick", lichtblick)):
        if accepted:
            parse_json_schema(schema, "t", dialect)
        else:
            with pytest.raises(SchemaRejected):
                parse_json_schema(schema, "t", dialect)


def test_the_port_builds_the_datatypes_the_viewer_builds() -> None:
    types = parse_json_schema(json_schema(ServiceStatus), "hil.ServiceStatus", "foxglove")
    counters = next(f for f in types["hil.ServiceStatus"] if f["name"] == "counters")
    assert counters == {
        "name": "counters",
        "type": "hil.ServiceStatus.counters",
        "isComplex": True,
        "isArray": True,
    }
    assert types["hil.ServiceStatus.counters"] == [
        {"name": "key", "type": "string"},
        {"name": "value", "type": "uint32"},
    ]
    assert (
        parse_json_schema(json_schema(ServiceStatus), "s", "lichtblick")["s.counters"][1]["type"] == "float64"
    )


@pytest.mark.parametrize("cls", CONTRACT_TYPES, ids=lambda c: c.__name__)
def test_every_checked_in_schema_decodes_in_foxglove_and_lichtblick(cls: type) -> None:
    schema = json.loads((SCHEMAS_DIR / f"{schema_name(cls)}.json").read_text())
    assert foxglove_schema_problems(schema, schema_name(cls)) == []
    assert "$defs" not in json.dumps(schema) and "anyOf" not in schema


def _embedded_schemas(path: Path) -> dict[str, tuple[str, str, bytes]]:
    """topic -> (message encoding, schema encoding, schema data) of every channel in a file."""
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    return {
        c.topic: (
            c.message_encoding,
            summary.schemas[c.schema_id].encoding,
            summary.schemas[c.schema_id].data,
        )
        for c in summary.channels.values()
    }


def test_every_json_schema_a_fresh_recording_embeds_decodes_in_foxglove(sim_recording: Path) -> None:
    channels = _embedded_schemas(sim_recording)
    json_channels = {t: v for t, v in channels.items() if v[0] == "json"}
    assert len(json_channels) >= 20  # the rig's topics: nav/*, status/*, sensor/*, ...
    for topic, (_enc, schema_enc, data) in json_channels.items():
        assert schema_enc == "jsonschema", topic
        schema = json.loads(data)
        assert foxglove_schema_problems(schema, schema["title"]) == [], topic
    assert any("/nav/" in t for t in json_channels) and any("/status/" in t for t in json_channels)
    # and every other channel is one of Foxglove's well-known types with the SDK's own schema
    # (each decodes with it: tests/unit/test_wellknown.py)
    others = {t: v for t, v in channels.items() if v[0] != "json"}
    assert others and all(
        enc == "protobuf" and schema_enc == "protobuf" for enc, schema_enc, _d in others.values()
    )
    assert {data for _e, _s, data in others.values()} <= {s.data for s in SCHEMAS.values()}


def test_the_schemas_of_a_recording_made_before_were_refused_and_its_messages_still_decode() -> None:
    from tests.replay.helpers import LEGACY_GOLDEN

    channels = _embedded_schemas(LEGACY_GOLDEN)
    refused = {
        json.loads(data)["title"]
        for enc, _s, data in channels.values()
        if enc == "json" and foxglove_schema_problems(json.loads(data), "x")
    }
    assert refused == {"hil.NavSolution", "hil.ServiceStatus"}  # the issue's two
    from hil.record.mcapio import read_session

    s = read_session(LEGACY_GOLDEN)
    navs = [r for r in s.records if r.schema == "hil.NavSolution"]
    statuses = [r for r in s.records if r.schema == "hil.ServiceStatus"]
    assert any(b'"pos_sigma_m":null' in r.payload for r in navs)
    for r in navs + statuses:
        m = r.decode()
        # the current form of a previous payload decodes to the same message (fields appended
        # since, such as NavSolution.att_sigma_rad, take their defaults)
        assert decode(type(m), current_form(type(m), r.payload)) == m
        assert decode(type(m), encode(m)) == m
    ins = [r.decode() for r in navs if r.topic.endswith("/nav/ins")]
    assert ins and all(m.pos_sigma_m == [] for m in ins)  # type: ignore[attr-defined]
    last = statuses[-1].decode()
    assert isinstance(last, ServiceStatus) and last.counter_map()


def test_previous_forms_decode_into_the_current_types_and_bad_input_still_fails() -> None:
    nav = (
        b'{"seq":1,"stamp_ns":5,"estimator":"ins","pos_ned_m":[0,0,0],"vel_ned_mps":[0,0,0],'
        b'"q_nb":[1,0,0,0],"lat_deg":1,"lon_deg":2,"alt_m":3,"pos_sigma_m":null,"vel_sigma_mps":[1,2,3]}'
    )
    sol = decode(NavSolution, nav)
    assert sol.pos_sigma_m == [] and sol.vel_sigma_mps == [1.0, 2.0, 3.0]
    assert b'"pos_sigma_m":[]' in current_form(NavSolution, nav)
    status = (
        b'{"seq":1,"stamp_ns":0,"service":"x","state":"running","pid":1,"uptime_s":1.0,'
        b'"rates_hz":{"in.a":2.5},"counters":{"rejected.b":3}}'
    )
    st = decode(ServiceStatus, status)
    assert st.rate_map() == {"in.a": 2.5} and st.counter_map() == {"rejected.b": 3}
    fault = b'{"seq":1,"stamp_ns":0,"kind":"gnss_jump","params":{"n_m":5.0}}'
    assert decode(FaultCommand, fault).param_map() == {"n_m": 5.0}
    current = encode(st)
    assert current_form(ServiceStatus, current) is current  # the current form is left as it is
    import msgspec

    with pytest.raises(msgspec.ValidationError, match="pos_sigma_m"):
        decode(NavSolution, nav.replace(b'"pos_sigma_m":null', b'"pos_sigma_m":[1,2]'))
    with pytest.raises(msgspec.ValidationError):
        decode(ServiceStatus, status.replace(b'{"rejected.b":3}', b'{"rejected.b":"x"}'))


def test_dialects_are_the_two_viewers() -> None:
    assert DIALECTS == ("foxglove", "lichtblick")
