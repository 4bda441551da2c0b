"""docs/foxglove-layout.json is the layout hil.record.foxglove_layout builds with the SDK's layout
types, and every topic and field it shows is one a recording has."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from hil.record.foxglove_layout import DOC_PATH, layout_json
from hil.record.mcapio import read_session
from tests.wellknown_reader import decode_wellknown


def test_the_shipped_layout_is_current() -> None:
    assert DOC_PATH.read_text() == layout_json("bench"), "python -m hil.record.foxglove_layout --write"


def _walk(node: Any) -> list[tuple[str, str]]:
    """(what, value) of every topic and message path in a layout."""
    out: list[tuple[str, str]] = []
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("followTopic", "value") and isinstance(v, str):
                out.append((k, v))
            elif k == "topicConfig" and isinstance(v, dict):
                out += [("topic", t) for t in v]
            else:
                out += _walk(v)
    elif isinstance(node, list):
        for v in node:
            out += _walk(v)
    return out


def test_every_topic_and_field_the_layout_shows_is_in_a_recording(sim_recording: Path) -> None:
    doc = json.loads(layout_json("simrec"))
    panels = {n["panelType"] for n in _panels(doc)}
    assert panels == {"Map", "ThreeDee", "Plot", "Log"}, panels
    s = read_session(sim_recording)
    hil_topics = {r.topic: r for r in reversed(s.records)}  # the first message of each
    foxglove_topics = set(decode_wellknown(sim_recording))
    refs = _walk(doc)
    assert len(refs) > 20
    for what, ref in refs:
        if what in ("followTopic", "topic"):
            assert ref in foxglove_topics, ref
            continue
        m = re.match(r"^([^.]+)\.([a-z_]+)(.*)$", ref)  # topic.field[...]...
        assert m, ref
        topic, fieldname, rest = m.groups()
        assert topic in hil_topics, ref
        body = json.loads(hil_topics[topic].payload)
        assert fieldname in body, ref
        keyed = re.match(r'^\[:\]\{key=="([^"]+)"\}\.value$', rest)
        if keyed and keyed.group(1) == "consumed":
            assert keyed.group(1) in {c["key"] for c in body[fieldname]}, ref


def _panels(node: Any) -> list[dict[str, Any]]:
    if isinstance(node, dict):
        found = [node] if node.get("type") == "panel" else []
        return found + [p for v in node.values() for p in _panels(v)]
    if isinstance(node, list):
        return [p for v in node for p in _panels(v)]
    return []
