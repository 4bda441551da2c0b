"""``hil rerun --verify`` of a recording that lacks inputs the live fusion took (a recorder that died
and whose restarted successor could not recover them, an overloaded recorder that dropped them).

The fusion's state after a lost input is not the live one, so every output after it differs; before
this, verify failed at the first of them, and a session with one short loss could not be checked
at all. The fusion's journal counts the inputs it consumed up to its watermark: the first journal
counting more than the file holds up to there bounds the loss, and the outputs from the journal
before it on are not verifiable (counted, named in a note); those before are compared as ever.

GIVEN the golden recording (4 s, journals every 0.5 s from 3 s on: the sim's fusion releases its
first inputs there) with 40 synced IMU samples removed at 3.25 s
WHEN it is rerun
THEN the outputs before 3.0 s are verified, those after are excused and counted, and a tampered
output before the loss still fails the verify; removing outputs (not inputs) excuses nothing.
"""

from __future__ import annotations

from functools import cache

import msgspec

from hil.record.mcapio import Record, read_session
from hil.record.rerun import RerunResult, rerun_fusion_records
from tests.replay.helpers import GOLDEN

LOST_SEQS = range(1300, 1340)  # synced/imu samples at 3.25-3.35 s


@cache
def _records() -> tuple[Record, ...]:
    return tuple(read_session(GOLDEN).records)


def _seq(r: Record) -> int:
    return int(msgspec.json.decode(r.payload)["seq"])


def _without_imu(records: tuple[Record, ...]) -> list[Record]:
    return [r for r in records if not (r.topic.endswith("/synced/imu") and _seq(r) in LOST_SEQS)]


def _rerun(records: list[Record]) -> RerunResult:
    return rerun_fusion_records(records, window_ns=None, worker=False)


def test_outputs_before_the_lost_inputs_are_verified_and_those_after_are_counted() -> None:
    whole = _rerun(list(_records()))
    assert whole.difference is None and whole.lost_spans == [] and whole.after_loss == 0
    res = _rerun(_without_imu(_records()))
    # the watermark of the journal before the loss (2.995 s), the samples lost at 3.25 s, to the end
    ((lost_from, lost_to),) = res.lost_spans
    assert 2_900_000_000 <= lost_from < 3_250_000_000 and lost_to == 2**62, res.lost_spans
    assert res.difference is None, res.difference
    assert res.after_loss > 100  # every estimator's outputs after the loss differ
    assert res.n_recorded - res.after_loss > 1000  # and those before were compared, bit for bit
    assert res.inputs_used == whole.inputs_used - len(LOST_SEQS) < res.live_consumed


def test_a_difference_before_the_loss_still_fails() -> None:
    records = _without_imu(_records())
    i, r = next((i, r) for i, r in enumerate(records) if r.topic.endswith("/nav/ekf15") and _seq(r) == 40)
    d = msgspec.json.decode(r.payload)
    assert d["stamp_ns"] < 2_900_000_000  # before the loss
    d["pos_ned_m"] = [d["pos_ned_m"][0] + 1.0, *d["pos_ned_m"][1:]]
    tampered = Record(r.topic, r.schema, msgspec.json.encode(d), r.log_time_ns, r.publish_time_ns, r.sequence)
    records[i] = tampered
    res = _rerun(records)
    assert res.lost_spans
    assert res.difference is not None and res.difference.startswith("nav/ekf15 seq 40: field 'pos_ned_m'")


def test_outputs_missing_from_the_file_are_no_loss_of_inputs() -> None:
    records = [r for r in _records() if not (r.topic.endswith("/nav/ekf15") and _seq(r) >= 100)]
    res = _rerun(records)
    assert res.lost_spans == [] and res.after_loss == 0 and res.difference is None


def test_a_loss_before_the_first_journal_with_a_watermark_spans_from_the_first_input() -> None:
    # the sim's first journals come before its fusion released anything (no watermark: -2**62)
    records = [r for r in _records() if not (r.topic.endswith("/synced/imu") and 100 <= _seq(r) < 140)]
    res = _rerun(records)
    ((lost_from, _to),) = res.lost_spans
    assert 0 <= lost_from < 250_000_000, lost_from  # the first input's stamp, not the sentinel
    assert res.difference is None


def test_a_loss_in_one_life_of_the_fusion_excuses_nothing_of_the_next() -> None:
    # GIVEN a fusion restarted (session "b") at 10 s whose first life ("a") lost inputs at ~2 s
    # by its journals, and whose second lost none
    from array import array

    from hil.record.rerun import _FusionRerun

    st = _FusionRerun(None, False, worker=False)
    st.realigned_sessions = ["b"]
    st.life_starts_ns = {1: 10_000_000_000}
    st.fed_stamps = {
        0: array("q", range(0, 9_000_000_000, 100_000_000)),
        1: array("q", range(10_000_000_000, 20_000_000_000, 100_000_000)),
    }
    st.journal_marks = [
        ("a", -(2**62), 0),  # before its first release: no watermark
        ("a", 1_000_000_000, 11),
        ("a", 2_500_000_000, 30),  # 26 fed up to 2.5 s: 4 lost between 1 s and 2.5 s
        ("b", 15_000_000_000, 51),
    ]
    # THEN the outputs from 1 s to the restart are not verifiable, the second life's all are
    assert st._lost_spans() == [(1_000_000_000, 10_000_000_000)]
