"""``hil rerun FILE --core timesync [--verify]``: re-stamp the recorded raw measurements again.

The time-sync core is per sensor, and per sensor its inputs -- ``timetag/<sensor>`` edges and raw
``sensor/<sensor>`` measurements -- come from one publishing process (the bridge for the IMU, the
receiver for GNSS), so the recorder sees them in the order the timesync service saw them (one
Zenoh link per peer pair is FIFO). Feeding them in file order through a fresh
``TimeSyncCore`` configured from the run's scenario therefore reproduces every re-stamp; each
recomputed ``synced/<sensor>`` message (the raw one with its ``stamp_ns`` replaced) is compared
byte for byte with the recorded one, by (sensor, seq).

Live sessions: the timesync service consumes each sensor's measurements and time tags through
one subscription (``hil/<rig>/*/<sensor>``, one callback thread), so it sees them in publication
order, as the recorder does. (With separate subscribers, zenoh-python's one thread per callback
let a PPS edge and a fix published back to back reach the core in the other order: verify then
named e.g. ``synced/gnss seq 19: field 'stamp_ns' differs``.)

Also not covered: a measurement the live service released by its *idle* flush (a sensor silent for
``IDLE_FLUSH_S`` while the core held samples around a suspected clock step) was stamped with the
mapping of that wall-clock moment, which a recording cannot tell; verify then names it.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgspec

from hil.messages import GnssFix, ImuSample, TimeTag, decode, encode
from hil.record.mcapio import Session
from hil.record.rerun import run_info_from

_RAW = {"hil.ImuSample": ImuSample, "hil.GnssFix": GnssFix}


@dataclass
class TimesyncRerun:
    recomputed: dict[tuple[str, int], bytes]
    recorded: dict[tuple[str, int], bytes]
    order: list[tuple[str, int]]  # recorded outputs in file order (the first difference is the first here)
    measurements: int
    timetags: int

    def first_difference(self) -> str | None:
        if not self.recorded:
            return "the recording holds no synced/<sensor> outputs to compare"
        for key in self.order:
            sensor, seq = key
            mine = self.recomputed.get(key)
            theirs = self.recorded[key]
            if mine is None:
                n = sum(1 for k in self.recorded if k not in self.recomputed)
                return f"synced/{sensor} seq {seq}: recorded but not recomputed ({n} such outputs)"
            if mine != theirs:
                a, b = msgspec.json.decode(theirs), msgspec.json.decode(mine)
                for f in b:
                    if a.get(f) != b.get(f):
                        return (
                            f"synced/{sensor} seq {seq}: field {f!r} differs: "
                            f"recorded {a.get(f)!r}, recomputed {b.get(f)!r}"
                        )
                return f"synced/{sensor} seq {seq}: payload bytes differ"
        return None


def rerun_timesync(session: Session) -> TimesyncRerun:
    from hil.runtime.scenario_io import scenario_for_run
    from hil.timesync.config import sync_configs_for
    from hil.timesync.core import TimeSyncCore

    run = run_info_from(session)
    core: TimeSyncCore[ImuSample | GnssFix] = TimeSyncCore(sync_configs_for(scenario_for_run(run)))
    recomputed: dict[tuple[str, int], bytes] = {}
    recorded: dict[tuple[str, int], bytes] = {}
    order: list[tuple[str, int]] = []
    n_meas = n_tags = 0

    def keep(released: list[tuple[ImuSample | GnssFix, int]]) -> None:
        for m, t in released:
            recomputed[(m.sensor, m.seq)] = encode(msgspec.structs.replace(m, stamp_ns=t))

    for r in session.records:
        parts = r.topic.split("/")
        if len(parts) != 4:
            continue
        kind, sensor = parts[2], parts[3]
        if kind == "timetag":
            tag = decode(TimeTag, r.payload)
            core.on_timetag(tag.sensor, tag.device_stamp_ns, tag.stamp_ns)
            n_tags += 1
        elif kind == "sensor" and r.schema in _RAW:
            raw = decode(_RAW[r.schema], r.payload)
            keep(core.on_measurement(raw.sensor, raw.device_stamp_ns, raw.rx_stamp_ns, raw))
            n_meas += 1
        elif kind == "synced" and r.schema in _RAW:
            key = (sensor, r.sequence)
            if key not in recorded:
                order.append(key)
            recorded[key] = r.payload
    keep(core.flush())
    return TimesyncRerun(recomputed, recorded, order, n_meas, n_tags)


def rerun_timesync_report(session: Session, verify: bool) -> tuple[int, list[str]]:
    res = rerun_timesync(session)
    lines = [
        f"rerun timesync: {res.measurements} raw measurements, {res.timetags} time tags, "
        f"{len(res.recomputed)} re-stamps recomputed, {len(res.recorded)} recorded"
    ]
    if session.truncated:
        lines.append("note: the file is truncated; rerun covers it up to its last complete chunk")
    if not verify:
        return 0, lines
    diff = res.first_difference()
    if diff:
        return 1, [*lines, f"VERIFY FAILED: {diff}"]
    return 0, [*lines, f"VERIFY OK: all {len(res.recorded)} recorded re-stamps are bit-identical"]
