"""docs/can-protocol.md is generated from the DBC and must be current."""

from __future__ import annotations

from hil.can.protocol_doc import DOC_PATH, render


def test_protocol_doc_is_current() -> None:
    assert DOC_PATH.exists(), "run: python -m hil.can.protocol_doc --write"
    assert DOC_PATH.read_text() == render(), (
        "docs/can-protocol.md is stale: python -m hil.can.protocol_doc --write"
    )


def test_protocol_doc_lists_every_dbc_frame() -> None:
    text = render()
    for name in ("IMU_Sync", "IMU_AxisX", "IMU_AxisY", "IMU_AxisZ", "IMU_Time", "IMU_SampleFD", "IMU_Status"):
        assert f"| {name} |" in text
