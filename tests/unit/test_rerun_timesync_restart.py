"""``hil rerun --core timesync --verify`` of a session whose time sync was restarted mid-run
(``hil up --restart``, ``hil fault kill_service --target timesync``).

The restarted time sync is a fresh core on what it received after its subscription opened; the
recording does not say which time tags those were (``rerun_timesync._Lives``), so its re-stamps
are counted as not verifiable, in a note naming the restart, and everything the first life
re-stamped is compared as ever. Found live: verify failed right after the restart
(``synced/gnss seq 55: field 'stamp_ns' differs``) with no word about it.

GIVEN the golden recording with its re-stamps from the middle on published by a new Zenoh
session and stamped otherwise (a fresh core), and the supervisor's ``service_restarted`` event
WHEN the time sync is rerun
THEN verify passes, leaves the later life's re-stamps out of its count and names the restart;
the same re-stamps from the first life's session, or a difference before the restart, fail it.
"""

from __future__ import annotations

import dataclasses
from functools import cache

import msgspec
import pytest

from hil.messages import Event, encode
from hil.record.matching import verdict
from hil.record.mcapio import Record, read_session
from hil.record.rerun_timesync import TimesyncRerun, rerun_timesync_records, restart_note
from tests.replay.helpers import GOLDEN

RESTART_NS = 2_000_000_000  # the supervisor's restart (rig time), just before the new life's first output


@cache
def _records() -> tuple[Record, ...]:
    return tuple(read_session(GOLDEN).records)


def _restamped(r: Record, by_ns: int) -> Record:
    """``r`` (a synced record) with its stamp moved: another core's re-stamp."""
    msg = msgspec.json.decode(r.payload)
    msg["stamp_ns"] += by_ns
    return dataclasses.replace(r, payload=msgspec.json.encode(msg))


def _restarted(new_session: bool = True, event: bool = True) -> tuple[list[Record], int, int]:
    """The golden records with the synced ones from IMU seq 800 on a later life's; the counts of
    the first life's and the later life's synced records."""
    records = list(_records())
    cut = next(i for i, r in enumerate(records) if r.topic.endswith("/synced/imu") and r.sequence == 800)
    rig = records[cut].topic.rsplit("/", 2)[0]
    out: list[Record] = []
    n_first = n_later = 0
    for i, r in enumerate(records):
        if i == cut and event:
            ev = Event(seq=1, stamp_ns=RESTART_NS, kind="service_restarted", source="timesync", detail="test")
            out.append(
                Record(f"{rig}/event/supervisor", "hil.Event", encode(ev), r.log_time_ns, 0, 1, "sup:1")
            )
        if "/synced/" in r.topic:
            if i < cut:
                r, n_first = dataclasses.replace(r, publisher="old:16"), n_first + 1
            else:
                r = dataclasses.replace(_restamped(r, 1000), publisher="new:16" if new_session else "old:16")
                n_later += 1
        out.append(r)
    return out, n_first, n_later


@pytest.mark.parametrize("worker", [False, True])
def test_a_restarted_time_syncs_re_stamps_are_counted_not_compared(worker: bool) -> None:
    records, n_first, n_later = _restarted()
    res = rerun_timesync_records(records, worker=worker)
    assert res.difference is None, res.difference
    assert (res.restarted, res.restarts_s, res.excused) == (n_later, (RESTART_NS / 1e9,), n_later)
    assert res.n_recorded == n_first + n_later and n_first > 500 and n_later > 500
    rc, lines = verdict(res, False, restart_note(res), True, "re-stamps")
    assert rc == 0, lines
    assert lines[0].startswith("note: the time sync restarted at t=2.0 s (a new process"), lines
    assert f"its {n_later} re-stamps after that are not verifiable" in lines[0], lines
    assert lines[-1] == f"VERIFY OK: all {n_first} recorded re-stamps are bit-identical"


def test_without_the_event_the_restart_is_named_by_its_first_output() -> None:
    records, _n_first, n_later = _restarted(event=False)
    res = rerun_timesync_records(records, worker=False)
    first_later = next(r for r in records if r.publisher == "new:16")
    assert res.difference is None and res.restarted == n_later
    assert res.restarts_s == ((first_later.log_time_ns - _start_ns(records)) / 1e9,)


def test_the_same_re_stamps_from_the_first_lifes_session_fail_verify() -> None:
    # (the test's re-stamps do differ: only the new session excuses them)
    records, _n_first, _n_later = _restarted(new_session=False)
    res = rerun_timesync_records(records, worker=False)
    assert res.difference is not None and "field 'stamp_ns' differs" in res.difference
    assert res.restarted == 0 and res.restarts_s == ()


def test_a_difference_before_the_restart_still_fails_verify() -> None:
    records, _n_first, _n_later = _restarted()
    i = next(i for i, r in enumerate(records) if r.topic.endswith("/synced/imu") and r.sequence == 500)
    records[i] = _restamped(records[i], 1)
    res = rerun_timesync_records(records, worker=False)
    assert res.difference is not None and res.difference.startswith("synced/imu seq 500: field 'stamp_ns'")
    assert verdict(res, False, [], True, "re-stamps")[0] == 1


def _start_ns(records: list[Record]) -> int:
    run = next(r for r in records if r.topic.endswith("/run")).decode()
    return int(run.start_epoch_ns)  # type: ignore[attr-defined]


def test_a_note_only_for_a_restart() -> None:
    assert restart_note(TimesyncRerun(1, 1, 1, 1, None)) == []
