"""``hil rerun --core timesync`` of a live session whose time sync's inbox dropped inputs.

The live service's bounded inbox drops the oldest of a lane once it is that far behind (50 s of
IMU samples, 500 GNSS fixes): counted in its status (``inbox.dropped.<kind>``), not journaled, so
the rerun feeds them and its re-stamps of that sensor can differ from there. Verify then names
the first difference; the note says why, from the status the recording holds.

GIVEN the golden recording with a status of the time sync that counts drops (two lives of it)
WHEN it is rerun
THEN the note names the drops summed over the lives; without such a status, no note.
"""

from __future__ import annotations

import dataclasses

from hil.messages import Count, ServiceStatus, encode
from hil.record.mcapio import Record, read_session
from hil.record.rerun_timesync import rerun_timesync_records, unjournaled_notes
from tests.replay.helpers import GOLDEN


def _status(like: Record, publisher: str, counters: dict[str, int]) -> Record:
    st = ServiceStatus(
        seq=1,
        stamp_ns=0,
        service="timesync",
        state="running",
        pid=1,
        uptime_s=1.0,
        counters=[Count(k, v) for k, v in counters.items()],
    )
    rig = like.topic.rsplit("/", 2)[0]
    return dataclasses.replace(
        like,
        topic=f"{rig}/status/timesync",
        schema="hil.ServiceStatus",
        payload=encode(st),
        publisher=publisher,
    )


def test_the_inbox_drops_of_each_life_are_noted() -> None:
    records = list(read_session(GOLDEN).records)
    i = next(i for i, r in enumerate(records) if r.topic.endswith("/synced/imu") and r.sequence == 500)
    records[i:i] = [
        _status(records[i], "old:3", {"inbox.dropped.sensor.imu": 4, "inbox.dropped.control.fault": 9}),
        _status(records[i], "old:3", {"inbox.dropped.sensor.imu": 7}),  # cumulative: 7, not 11
        _status(records[i], "new:3", {"inbox.dropped.timetag.gnss": 2}),
    ]
    res = rerun_timesync_records(records, worker=False)
    assert res.difference is None, res.difference  # nothing actually dropped here: the note only
    assert res.inbox_dropped == 9
    assert unjournaled_notes(res) == [
        "note: the time sync dropped 9 of its inputs from its inbox (its status: inbox.dropped.*; it "
        "fell that far behind; which ones is not journaled): re-stamps of that sensor after it can differ"
    ]
    assert unjournaled_notes(rerun_timesync_records(read_session(GOLDEN).records, worker=False)) == []
