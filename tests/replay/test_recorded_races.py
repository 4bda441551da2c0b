"""Recordings of live races that once failed ``hil rerun --verify``, kept as they were recorded
(cut to the fusion's inputs, outputs, journals and events with ``hil filter``).

``restarted_fusion_unreceived_fix.mcap``: ``test_supervision``'s restarted fusion (SIGKILLed 3 s in,
restarted by ``hil up --restart 1``) re-aligned at 3.755 s on IMU sample 1502; GNSS fix 37, valid
at 3.700 s, was published just after that sample, but the new process's subscription to the fixes
took effect later than its subscription to the IMU (the suite was building the Docker image beside
it) and it never received the fix: its solutions say ``gnss_seq`` -1 until fix 38. Rerun infers
what a new life received from the publish order, took fix 37, and recomputed ``gnss_seq`` 37 for
nav/ins seq 210. A restarted life now takes nothing valid before its re-alignment, live
(``FusionCore`` refuses it: ``prealign``) and in rerun alike.
"""

from __future__ import annotations

from pathlib import Path

from hil.record.rerun import rerun

RECORDED = Path(__file__).parent / "recorded"


def test_a_restarted_fusion_that_never_received_a_fix_valid_before_its_alignment_reruns_bit_identical() -> (
    None
):
    path = RECORDED / "restarted_fusion_unreceived_fix.mcap"
    assert path.stat().st_size < 300_000
    code, lines = rerun(str(path), core="fusion", verify=True, worker=False)
    text = "\n".join(lines)
    assert code == 0, text
    assert "restarted 1 time" in text and "VERIFY OK: all 122 recorded outputs are bit-identical" in text, (
        text
    )
