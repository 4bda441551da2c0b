"""Per-publisher seq accounting: gaps counted, late fills un-counted, duplicates named."""

from __future__ import annotations

from hil.messages import generation_seq
from hil.record.completeness import MAX_GAP_RANGES, Completeness, SeqTracker
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


def test_a_restarted_publisher_is_a_new_generation_not_loss_duplicates_or_disorder() -> None:
    from hil.messages import generation_seq

    t = SeqTracker()
    for n in range(50):  # first process: 0..49; it dies after 49 (whatever it sent last arrived)
        t.see(generation_seq(0, n))
    for n in range(3, 40):  # restarted: its first three were published before we were routed
        t.see(generation_seq(1, n))
    assert (t.restarts, t.missing, t.duplicates, t.out_of_order, t.gaps) == (1, 0, 0, 0, 0)
    assert t.generation == 1 and t.last == generation_seq(1, 39)
    # loss inside the new generation is loss, counted and named in that generation's numbers
    t.see(generation_seq(1, 45))
    s = t.summary()
    assert (t.missing, t.gap_ranges) == (5, [(generation_seq(1, 40), generation_seq(1, 44))])
    assert s["generations"] == [
        {"generation": 0, "first": 0, "last": 49, "count": 50, "missing": 0},
        {"generation": 1, "first": 3, "last": 45, "count": 38, "missing": 5},
    ]
    # a straggler of the dead process arriving late is out of order, not a new restart
    t.see(generation_seq(0, 20))
    assert (t.restarts, t.out_of_order, t.duplicates) == (1, 1, 0)


def test_derived_seqs_keep_showing_the_downtime_as_a_gap() -> None:
    # IMU samples are numbered by the device's sample index: a restart is a gap, data lost
    t = SeqTracker()
    for k in [*range(0, 1000), *range(1400, 1500)]:
        t.see(k)
    assert (t.restarts, t.missing, t.gap_ranges) == (0, 400, [(1000, 1399)])
    c = Completeness()
    for n in (0, 1, 2):
        c.see("hil/r/status/fusion", n)
    c.see("hil/r/status/fusion", 1 << 32)
    assert c.restarts() == {"hil/r/status/fusion": 1} and c.total_missing() == 0


def test_the_report_counts_a_restart_as_the_recorder_does() -> None:
    import numpy as np

    from hil.messages import generation_seq
    from hil.report.data import seq_accounting

    seqs = [*range(0, 50), *range(52, 60), *(generation_seq(1, n) for n in range(0, 30)), 55]
    t = SeqTracker()
    for s in seqs:
        t.see(s)
    assert seq_accounting(np.array(seqs, np.int64)) == (t.missing, 1, t.restarts) == (2, 1, 1)


def test_forged_seqs_are_outliers_not_a_billion_missing_and_no_count_goes_negative() -> None:
    """GIVEN a stream of the rig's hundreds WHEN seq 10⁹, a made-up far 'generation' and late
    fills repeated come in THEN nothing is missing, the forgeries are outliers, and a gap
    filled twice un-counts once."""
    from hil.messages import generation_seq

    t = SeqTracker()
    for s in [*range(100), 10**9, 100, 101, generation_seq(7, 123_456_789), 102]:
        t.see(s)
    assert (t.missing, t.gaps, t.outliers, t.restarts) == (0, 0, 2, 0)
    assert t.last == 102 and t.summary()["outliers"] == 2
    for s in [103, 106, 104, 104, 104, 105, 105]:  # a gap of 2, each late one sent three times
        t.see(s)
    assert t.missing == 0 and t.duplicates == 0 and t.out_of_order == 5
    assert all(v >= 0 for v in (t.missing, t.gaps, t.count, t.outliers))


def test_a_real_restart_still_counts_as_one() -> None:
    from hil.messages import generation_seq

    t = SeqTracker()
    for s in [*range(5), *(generation_seq(1, n) for n in range(3))]:
        t.see(s)
    assert (t.restarts, t.missing, t.outliers) == (1, 0, 0)


def test_foreign_traffic_is_accounted_apart_and_bounded() -> None:
    from hil.record.completeness import ForeignTraffic

    f = ForeignTraffic(max_publishers=2)
    for p in ("a:1", "b:1", "c:1"):
        for s in (0, 10**9, 5):
            f.see("hil/r/synced/gnss", p, s)
    rep = f.report()
    assert rep["messages"] == 9 and rep["publishers"] == ["a:1", "b:1"] and rep["untracked"] == 3
    assert rep["topics"] == {"hil/r/synced/gnss": 6}


def test_holds_is_what_was_seen_and_never_an_open_gap() -> None:
    # what a restarted recorder asks of its earlier lives' files: "already recorded?"
    c = Completeness()
    for s in [*range(5, 10), *range(13, 20), generation_seq(1, 0), generation_seq(1, 1)]:
        c.see("k", s)
    held = [s for s in range(25) if c.holds("k", s)]
    assert held == [*range(5, 10), *range(13, 20)]  # not before the first seen, not in 10..12
    assert c.holds("k", generation_seq(1, 1)) and not c.holds("k", generation_seq(1, 2))
    assert not c.holds("other", 5)
    c.see("k", 11)  # a late fill: held from now on, its neighbours still not
    assert [s for s in range(9, 14) if c.holds("k", s)] == [9, 11, 13]


def test_holds_says_no_where_gaps_were_too_many_to_track() -> None:
    # better a message twice than one lost: past MAX_GAP_RANGES, where the gaps are is unknown
    t = SeqTracker()
    for s in range(0, 2 * (MAX_GAP_RANGES + 2), 2):
        t.see(s)
    assert t.gaps == MAX_GAP_RANGES + 1 and not t.holds(0) and not t.holds(2)
