"""``hil rerun --core timesync --verify`` of a session whose time sync was restarted mid-run
(``hil up --restart``, ``hil fault kill_service --target timesync``).

The restarted time sync is a fresh core on what it received after its subscription opened. Its
``first_input`` events name the first input of each sensor it took, so the rerun feeds a fresh
core from there and compares its re-stamps (``rerun_timesync._LaterLife``); a recording without
the events does not say which time tags those were (``rerun_timesync._Lives``), so its re-stamps
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

from hil.messages import Event, RunInfo, TimeTag, decode, encode
from hil.nodes.timesync import TimeSyncNode, first_input_detail, first_input_named
from hil.record.matching import verdict
from hil.record.mcapio import Record, read_session
from hil.record.rerun_timesync import _RAW, TimesyncRerun, rerun_timesync_records, restart_note
from hil.runners.sim import SimOptions, run_sim
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


@pytest.fixture(scope="module")
def sim_records(tmp_path_factory: pytest.TempPathFactory) -> tuple[Record, ...]:
    """12 s of straight_level (the golden's 4 s end inside a fresh time sync's start-up hold)."""
    path = tmp_path_factory.mktemp("relived") / "s.mcap"
    run_sim(
        SimOptions(duration_s=12.0, record=path, rig="relived", estimators=["comp1"], fusion_worker=False)
    )
    return tuple(read_session(path).records)


def _relived(
    sources: tuple[Record, ...],
    event_first: bool = False,
    name_next: str | None = None,
    shift_ns: int = 0,
    cuts: tuple[int, ...] = (2000,),
) -> tuple[list[Record], int, int]:
    """``sources`` (a sim recording) as a live session whose time sync was restarted at IMU seq
    2000 (``cuts``: at each of these): its inputs from their publishers, the first life's
    re-stamps up to there, then a fresh core's (TimeSyncNode, as the restarted process runs) of
    every input from there on (to the next cut, where that process died), with its
    ``first_input`` event per sensor just after (``event_first``: just before) the input it names.
    ``name_next``: that sensor's event names the input after the one the core began with (a tag
    more or less). ``shift_ns``: the later lives' recorded re-stamps moved (another core's)."""
    records = list(sources)
    at = [
        next(i for i, r in enumerate(records) if r.topic.endswith("/sensor/imu") and r.sequence == c)
        for c in cuts
    ]
    rig = records[at[0]].topic.rsplit("/", 2)[0]
    run = decode(RunInfo, next(r for r in records if r.topic.endswith("/run")).payload)
    node = TimeSyncNode(run)
    out: list[Record] = []
    named: set[str] = set()
    n_first = n_later = 0
    life = 1
    for i, r in enumerate(records):
        if i in at:  # the process died here; the supervisor started a new one
            life += 1
            node, named = TimeSyncNode(run), set()
        _, _, kind, sensor = r.topic.split("/") if r.topic.count("/") == 3 else ("", "", "", "")
        if kind == "synced":
            if i < at[0]:  # the first life's; it died at the cut
                out.append(dataclasses.replace(r, publisher="old:16"))
                n_first += 1
            continue
        if kind not in ("timetag", "sensor") or (kind == "sensor" and r.schema not in _RAW):
            out.append(r)
            continue
        r = dataclasses.replace(r, publisher=f"{sensor}-publisher:3")
        if i < at[0]:
            out.append(r)
            continue
        key = f"{kind}/{sensor}"
        msg = decode(TimeTag, r.payload) if kind == "timetag" else decode(_RAW[r.schema], r.payload)
        event: list[Record] = []
        if sensor not in named:
            named.add(sensor)
            seq = msg.seq + (1 if name_next == sensor else 0)
            ev = Event(
                seq=len(named),
                stamp_ns=0,
                kind="first_input",
                source="timesync",
                detail=first_input_detail(sensor, key, seq, r.publisher),
            )
            event = [
                Record(
                    f"{rig}/event/timesync", "hil.Event", encode(ev), r.log_time_ns, 0, ev.seq, f"new{life}:9"
                )
            ]
        out.extend([*event, r] if event_first else [r, *event])
        for _k, m in node.on_message(key, msg, 0):
            if shift_ns:
                m = msgspec.structs.replace(m, stamp_ns=m.stamp_ns + shift_ns)
            out.append(
                Record(
                    f"{rig}/synced/{sensor}", r.schema, encode(m), r.log_time_ns, 0, m.seq, f"new{life}:16"
                )
            )
            n_later += 1
    return out, n_first, n_later


@pytest.mark.parametrize(("worker", "event_first"), [(False, False), (True, False), (False, True)])
def test_a_restarted_time_sync_is_rebuilt_from_the_first_inputs_it_named(
    sim_records: tuple[Record, ...], worker: bool, event_first: bool
) -> None:
    records, n_first, n_later = _relived(sim_records, event_first)
    res = rerun_timesync_records(records, worker=worker)
    assert res.difference is None, res.difference
    assert (res.restarted, res.restarted_compared, res.excused) == (0, n_later, 0)
    assert n_first > 1500 and n_later > 1500 and res.n_recorded == n_first + n_later
    rc, lines = verdict(res, False, restart_note(res), True, "re-stamps")
    assert rc == 0, lines
    assert "rebuilt here from the first input of each sensor" in lines[0], lines
    assert f"its {n_later} re-stamps after that compared" in lines[0], lines
    assert lines[-1] == f"VERIFY OK: all {n_first + n_later} recorded re-stamps are bit-identical"


def test_a_restarted_time_syncs_differing_re_stamps_fail_verify(sim_records: tuple[Record, ...]) -> None:
    records, _n_first, _n_later = _relived(sim_records, shift_ns=1000)
    res = rerun_timesync_records(records, worker=False)
    assert res.difference is not None and " (life 2) seq " in res.difference, res.difference
    assert "field 'stamp_ns' differs" in res.difference, res.difference


def test_a_core_fed_from_another_input_than_the_one_named_differs(sim_records: tuple[Record, ...]) -> None:
    # the fresh core began with GNSS's first input after the cut; an event naming the next one
    # feeds the rebuilt core one input less, and its re-stamps are not the live ones
    records, _n_first, _n_later = _relived(sim_records, name_next="gnss")
    res = rerun_timesync_records(records, worker=False)
    assert res.difference is not None and res.difference.startswith("synced/gnss (life 2) seq"), (
        res.difference
    )


def test_a_restarted_time_sync_names_the_first_input_of_each_sensor_once(
    sim_records: tuple[Record, ...],
) -> None:
    run = decode(RunInfo, next(r for r in sim_records if r.topic.endswith("/run")).payload)
    # 2000 of the run's inputs from its middle, as (key, message)
    inputs = [
        (
            r.topic.split("/", 2)[2],
            decode(TimeTag, r.payload) if r.schema == "hil.TimeTag" else decode(_RAW[r.schema], r.payload),
        )
        for r in sim_records
        if r.topic.split("/")[2] in ("timetag", "sensor") and (r.schema in _RAW or r.schema == "hil.TimeTag")
    ][2000:4000]

    def events(node: TimeSyncNode) -> list[Event]:
        out = [
            m
            for key, msg in inputs
            for k, m in node.on_message_from(key, msg, 0, "pub:7")
            if k == "event/timesync"
        ]
        return out  # type: ignore[return-value]

    assert events(TimeSyncNode(run)) == []  # the first life began with the run: nothing to name
    later = events(TimeSyncNode(run, TimeSyncNode.Options(resume=1)))
    expected: dict[str, tuple[str, str, int, str]] = {}
    for key, msg in inputs:
        expected.setdefault(key.split("/")[1], (key.split("/")[1], key, msg.seq, "pub:7"))
    assert {"imu", "gnss"} <= set(expected), expected
    assert [e.kind for e in later] == ["first_input"] * len(expected)
    assert {
        e.detail.split(" re-stamps ")[1].split()[0]: first_input_named(e.detail) for e in later
    } == expected


@pytest.mark.parametrize(("worker", "event_first"), [(False, False), (True, False), (False, True)])
def test_each_life_is_fed_only_until_the_next_one_takes_over(
    sim_records: tuple[Record, ...], worker: bool, event_first: bool
) -> None:
    # restarted twice: each life's core here re-stamps from the first input its event named to
    # the first input the next life's names (that process had died), not to the end of the file
    records, n_first, n_later = _relived(sim_records, event_first, cuts=(1500, 3000))
    res = rerun_timesync_records(records, worker=worker)
    assert res.difference is None, res.difference
    assert (res.restarted, res.restarted_compared, res.restarts_s.__len__()) == (0, n_later, 2)
    assert res.n_recorded == n_first + n_later and n_first > 1000 and n_later > 2500
    # the recorded ones, and where the event comes after the input it names, the dead life's
    # re-stamp of that input (it was fed before the event was read): one per sensor and restart
    extra = 0 if event_first else 2 * 2
    assert res.n_recomputed == n_first + n_later + extra, (res.n_recomputed, n_first, n_later)
