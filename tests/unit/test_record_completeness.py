"""Per-publisher seq accounting: gaps counted, late fills un-counted, duplicates named."""

from __future__ import annotations

from hil.record.completeness import Completeness, SeqTracker
from hil.record.lockstep import decode_ack, encode_ack


def test_contiguous_stream_has_nothing_missing() -> None:
    t = SeqTracker()
    for s in range(100):
        t.see(s)
    assert (t.count, t.gaps, t.missing, t.duplicates, t.out_of_order) == (100, 0, 0, 0, 0)


def test_a_gap_is_counted_and_a_late_fill_uncounts_it() -> None:
    t = SeqTracker()
    for s in [0, 1, 2, 6, 7]:
        t.see(s)
    assert (t.gaps, t.missing) == (1, 3) and t.gap_ranges == [(3, 5)]
    t.see(4)  # arrived late
    assert (t.missing, t.out_of_order) == (2, 1)


def test_duplicates_are_named_not_counted_as_data() -> None:
    t = SeqTracker()
    for s in [0, 1, 1, 2]:
        t.see(s)
    assert (t.duplicates, t.missing) == (1, 0)


def test_a_stream_that_starts_late_is_not_a_gap() -> None:
    # a recorder started after the publisher: the first seq seen is the baseline
    t = SeqTracker()
    for s in range(500, 510):
        t.see(s)
    assert t.missing == 0 and t.first == 500


def test_session_total_sums_publishers() -> None:
    c = Completeness()
    for s in [0, 2]:
        c.see("hil/r/sensor/imu", s)
    for s in [0, 1, 5]:
        c.see("hil/r/truth", s)
    assert c.total_missing() == 1 + 3
    assert set(c.report()) == {"hil/r/sensor/imu", "hil/r/truth"}


def test_lockstep_ack_round_trips_and_rejects_garbage() -> None:
    assert decode_ack(encode_ack(12345)) == 12345
    for bad in (b"", b"-1", b"1e3", b"x", b"9" * 30, b"\xff"):
        assert decode_ack(bad) is None
