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
    assert whole.difference is None and whole.lost_from_ns is None and whole.after_loss == 0
    res = _rerun(_without_imu(_records()))
    assert res.lost_from_ns is not None
    # the watermark of the journal before the loss (2.995 s), the samples lost at 3.25 s
    assert 2_900_000_000 <= res.lost_from_ns < 3_250_000_000, res.lost_from_ns
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
    assert res.lost_from_ns is not None
    assert res.difference is not None and res.difference.startswith("nav/ekf15 seq 40: field 'pos_ned_m'")


def test_outputs_missing_from_the_file_are_no_loss_of_inputs() -> None:
    records = [r for r in _records() if not (r.topic.endswith("/nav/ekf15") and _seq(r) >= 100)]
    res = _rerun(records)
    assert res.lost_from_ns is None and res.after_loss == 0 and res.difference is None
