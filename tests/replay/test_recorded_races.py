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

import dataclasses
from pathlib import Path

import msgspec

from hil.messages import encode
from hil.nodes.fusion import realigned_first_received
from hil.record.mcapio import Record, read_session
from hil.record.rerun import rerun, rerun_fusion_records

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


def _with_fix_published_before_the_first_sample(detail: str | None) -> list[Record]:
    """The recording as it would be had fix 37 been valid just after the alignment (3.7560 s) and
    published between IMU samples 1501 and 1502 -- before the restarted fusion's first sample --
    and not received: its subscription to the fixes took effect a moment after it was published.
    ``detail``: the realigned event's detail instead of the recorded one (None: as recorded, the
    form before the event named the first input received per stream)."""
    records = list(read_session(RECORDED / "restarted_fusion_unreceived_fix.mcap").records)
    (fix,) = [r for r in records if r.topic.endswith("/synced/gnss") and r.decode().seq == 37]  # type: ignore[attr-defined]
    rest = [r for r in records if r is not fix]
    at = next(
        i
        for i, r in enumerate(rest)
        if r.topic.endswith("/synced/imu") and r.decode().seq == 1502  # type: ignore[attr-defined]
    )
    m = fix.decode()
    moved = dataclasses.replace(
        fix,
        payload=encode(msgspec.structs.replace(m, stamp_ns=3_756_000_000)),  # type: ignore[type-var]
        log_time_ns=rest[at - 1].log_time_ns,
    )
    out = [*rest[:at], moved, *rest[at:]]
    if detail is not None:
        (i,) = [i for i, r in enumerate(out) if r.topic.endswith("/event/fusion")]
        ev = out[i].decode()
        out[i] = dataclasses.replace(out[i], payload=encode(msgspec.structs.replace(ev, detail=detail)))  # type: ignore[type-var]
    return out


def test_a_restarted_fusion_is_rerun_on_exactly_the_inputs_its_event_says_it_received_first() -> None:
    """GIVEN the restarted fusion's recording with a fix valid after its alignment published just
    before its first IMU sample, which it did not receive (its subscription took effect just
    after); WHEN rerun with the event as the fusion now writes it (the first input of each stream
    received before that sample: only the IMU sample), THEN it verifies; with the event saying
    the fix was received, rerun fuses it and finds the difference; and with the event in the form
    before it (no first inputs named), rerun infers from the publish order, takes the fix and
    fails: the race this journal closes."""
    imu_pub = "ec0b1d2898e44262d3d883595a486ff8:16"
    gnss_pub = "ec0b1d2898e44262d3d883595a486ff8:19"
    head = "fusion restarted: estimators re-aligned from truth at t=3.7550 s (the start of imu seq 1502); outputs numbered from 188"
    exact = _with_fix_published_before_the_first_sample(f"{head}; first received: imu:1502@{imu_pub}")
    assert realigned_first_received(f"{head}; first received: imu:1502@{imu_pub}") == {("imu", imu_pub): 1502}
    res = rerun_fusion_records(exact, window_ns=None, worker=False)
    assert (res.difference, res.restarts) == (None, 1)
    assert res.n_recorded == 122
    said = _with_fix_published_before_the_first_sample(
        f"{head}; first received: gnss:37@{gnss_pub}, imu:1502@{imu_pub}"
    )
    res = rerun_fusion_records(said, window_ns=None, worker=False)
    assert res.difference is not None and "gnss_seq" in res.difference, res.difference
    inferred = _with_fix_published_before_the_first_sample(None)
    res = rerun_fusion_records(inferred, window_ns=None, worker=False)
    assert res.difference is not None and "gnss_seq" in res.difference, res.difference
