"""docs/topics.md is generated from schemas/ and the key layout, and must be current."""

from __future__ import annotations

from hil.messages import CONTRACT_TYPES, schema_name
from hil.report.topics_doc import DOC_PATH, render


def test_topics_doc_is_current() -> None:
    assert DOC_PATH.exists(), "run: python -m hil.report.topics_doc --write"
    assert DOC_PATH.read_text() == render(), (
        "docs/topics.md is stale: python -m hil.report.topics_doc --write"
    )


def test_topics_doc_lists_every_type_and_key() -> None:
    text = render()
    for cls in CONTRACT_TYPES:
        assert f"## {schema_name(cls)}\n" in text
    assert "hil/<rig>/nav/<estimator>" in text and "| `pos_ned_m` | number[3] | yes |" in text
