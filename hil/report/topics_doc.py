"""Generate ``docs/topics.md`` from ``schemas/hil.*.json`` and the key layout (a test keeps it current).

python -m hil.report.topics_doc            # print
python -m hil.report.topics_doc --write    # rewrite docs/topics.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hil.bus import keys as keys_mod
from hil.messages import MAX_BATCH
from hil.schemas_io import SCHEMAS_DIR

DOC_PATH = Path(__file__).resolve().parents[2] / "docs" / "topics.md"


def _type(spec: dict[str, Any], defs: dict[str, Any]) -> str:
    if "$ref" in spec:
        return spec["$ref"].rsplit("/", 1)[-1]
    if "anyOf" in spec:
        return " \\| ".join(_type(s, defs) for s in spec["anyOf"])
    t = spec.get("type", "any")
    if t == "array":
        n = spec.get("minItems")
        inner = _type(spec.get("items", {}), defs)
        return f"{inner}[{n}]" if n is not None and n == spec.get("maxItems") else f"list[{inner}]"
    if t == "object" and "additionalProperties" in spec:
        return f"map[str, {_type(spec['additionalProperties'], defs)}]"
    if t == "object" and "properties" in spec:  # a map as [{key, value}, ...], say
        return "{" + ", ".join(f"{k}: {_type(v, defs)}" for k, v in spec["properties"].items()) + "}"
    return str(t)


def _limits(spec: dict[str, Any]) -> str:
    out = []
    if "maxItems" in spec and spec.get("minItems") != spec["maxItems"]:
        out.append(f"items ≤ {spec['maxItems']}")
    for k, sym in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("maxLength", "len ≤")):
        if k in spec:
            out.append(f"{sym} {spec[k]}")
    if "pattern" in spec:
        out.append(f"`{spec['pattern']}`")
    return ", ".join(out)


# The plain zenoh-python client of "Discover a rig's topics": tests/integration/test_bus_live.py
# runs this very text against a live ``hil up``.
DISCOVERY_EXAMPLE = """\
import json, sys, time, zenoh  # pip install eclipse-zenoh; argv: the rig's endpoint and its name
conf = zenoh.Config()
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))  # e.g. tcp/127.0.0.1:7447
with zenoh.open(conf) as session:
    topics, answered = {}, None  # key -> type, from every service (each reply also has "schemas")
    for _ in range(30):  # a new session meets the rig's peers within moments: ask until it holds
        replies = [json.loads(r.ok.payload.to_string()) for r in
                   session.get(f"hil/{sys.argv[2]}/@topics/*", timeout=10) if r.ok]
        for reply in replies:
            topics.update(reply["topics"])
        services = sorted(r["service"] for r in replies)
        if replies and services == answered:
            break
        answered = services
        time.sleep(1)
    print("\\n".join(f"{key} {typ}" for key, typ in sorted(topics.items())))
    sample = session.declare_subscriber(f"hil/{sys.argv[2]}/nav/*").recv()  # the next solution
    print(sample.key_expr, sample.encoding, json.loads(sample.payload.to_bytes())["pos_ned_m"])
"""


def _batched_keys() -> str:
    """The keys that may carry a batch, as the bus says it (``hil.bus.keys``)."""
    names = [f"`{k}/<channel>`" if k == "can" else f"`{k}/*`" for k in sorted(keys_mod.BATCHED_KINDS)]
    names += [f"`{k}`" for k in sorted(keys_mod.BATCHED_KEYS)]
    return ", ".join(names[:-1]) + " and " + names[-1]


def _discovery() -> list[str]:
    return [
        "## Discover a rig's topics (no hil code needed)",
        "",
        "The bus describes itself (`hil/bus/describe.py`):",
        "",
        "- every sample's Zenoh encoding names its type: `application/json;hil.NavSolution` (the",
        "  schema below with that title; the CAN transport `hilcan/<rig>/<channel>` carries",
        "  `application/octet-stream;hilzenoh.frame`, `hil/can/zenoh_bus.py`);",
        "- a sample's payload is one message (a JSON object), or possibly a batch on",
        f"  {_batched_keys()}:",
        f"  a JSON array of up to {MAX_BATCH} messages of the key's type that were ready",
        "  together (a CAN read window's raw frames and IMU samples, `hil up --can-batch-ms`;",
        "  the world's truth rows of one block, ten at 100 Hz;",
        "  `hil.bus.keys.may_batch`, `hil.messages.split_batch`), each with its own `seq`. The",
        "  recording keeps them one MCAP message each; on any other key (a solution `nav/<name>`,",
        "  a GNSS fix) a sample is always one message;",
        "- every service holds the liveliness token `hil/<rig>/@alive/<service>` while it runs",
        '  (`session.liveliness().get("hil/*/@alive/*")` lists the running services of every rig);',
        "- every service answers a query on `hil/<rig>/@topics/<service>` with one JSON reply",
        "  (encoding `application/json;hil.Topics`): `rig`, `service`, `topics` (key -> type of every",
        "  key it publishes) and `schemas` (type -> JSON Schema).",
        "",
        "`@` chunks are verbatim in Zenoh: `hil/<rig>/**` never matches them, so subscribers and the",
        "recording are unaffected. A plain zenoh-python client, given the rig's endpoint and name:",
        "",
        "```python",
        *DISCOVERY_EXAMPLE.rstrip("\n").splitlines(),
        "```",
        "",
    ]


def render(schemas_dir: Path = SCHEMAS_DIR) -> str:
    lines = [
        "# Topics and message fields",
        "",
        "Generated by `python -m hil.report.topics_doc --write` from `schemas/hil.*.json` and",
        "`hil/bus/keys.py`; a test fails when this file is stale. Every message is JSON; every time is",
        "integer ns (`*_ns`); positions and velocities NED metres about the scenario origin.",
        "Every field has one concrete JSON type (Foxglove's and Lichtblick's schema parser take every",
        "type: `hil schemas` checks it): an absent vector is `[]`, a map is a list of `{key, value}`.",
        "",
        "Beside these keys, recordings and the live Foxglove server (`hil foxglove`) carry Foxglove's",
        "well-known types derived from them on `/foxglove/...` (`foxglove.LocationFix`,",
        "`foxglove.FrameTransform`, `foxglove.Log`; protobuf, the SDK's schemas): `docs/recording.md`,",
        "section *Foxglove*, lists the topics, the frame tree and the conversions.",
        "",
        "## Key expressions",
        "",
        "```",
        *[ln.strip() for ln in (keys_mod.__doc__ or "").split("::", 1)[-1].split("\n\n")[1].splitlines()],
        "```",
        "",
        *_discovery(),
    ]
    for path in sorted(schemas_dir.glob("hil.*.json")):
        schema = json.loads(path.read_text())
        defs = schema.get("$defs", {})
        req = set(schema.get("required", []))
        lines += [f"## {schema['title']}", ""]
        if schema.get("description"):
            lines += [" ".join(schema["description"].split()), ""]
        lines += ["| field | type | required | default | limits |", "| --- | --- | --- | --- | --- |"]
        for name, spec in schema.get("properties", {}).items():
            default = json.dumps(spec["default"]) if "default" in spec else ""
            must = "yes" if name in req else ""
            lines.append(f"| `{name}` | {_type(spec, defs)} | {must} | {default} | {_limits(spec)} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args(argv)
    text = render()
    if a.write:
        DOC_PATH.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
