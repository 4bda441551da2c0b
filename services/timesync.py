"""timesync: re-stamps every raw measurement to rig time of validity and publishes clock models.

A re-stamped measurement on ``synced/<sensor>`` keeps the ``seq`` of its raw original, so the
recording pairs every synced message with its raw one and its true capture time.
"""

from __future__ import annotations

import argparse
import threading
from typing import Any

import msgspec

from hil.bus.keys import SENSOR_TYPES
from hil.messages import ClockModel, GnssFix, ImuSample, RunInfo, TimeTag
from hil.runtime.clock import RigClock
from hil.runtime.service import Service, run_service
from hil.timesync.core import TimeSyncCore


class TimeSync(Service):
    name = "timesync"

    def setup(self) -> None:
        self.core = TimeSyncCore()
        self.lock = threading.Lock()
        self.synced_pubs = {s: self.publisher(self.keys.synced(s), cls) for s, cls in SENSOR_TYPES.items()}
        self.clock_pubs: dict[str, Any] = {}
        self.subscribe(self.keys.sensor("imu"), ImuSample, self._on_measurement)
        self.subscribe(self.keys.sensor("gnss"), GnssFix, self._on_measurement)
        self.subscribe(self.keys.timetag("*"), TimeTag, self._on_timetag)

    def _on_timetag(self, tag: TimeTag, _key: str) -> None:
        with self.lock:
            self.core.on_timetag(tag.sensor, tag.device_stamp_ns, tag.stamp_ns)

    def _on_measurement(self, msg: ImuSample | GnssFix, _key: str) -> None:
        with self.lock:
            self.core.on_arrival(msg.sensor, msg.device_stamp_ns, msg.rx_stamp_ns)
            t = self.core.restamp(msg.sensor, msg.device_stamp_ns)
        pub = self.synced_pubs.get(msg.sensor)
        if pub is None:
            self.stats.error("rejected.sensor.unknown", f"no synced channel for sensor {msg.sensor!r}")
            return
        pub.put(msgspec.structs.replace(msg, stamp_ns=t))

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        seq: dict[str, int] = {}
        while not self.ctx.stop.wait(1.0):
            with self.lock:
                maps = list(self.core.mappings.values())
            for m in maps:
                pub = self.clock_pubs.get(m.sensor)
                if pub is None:
                    pub = self.clock_pubs[m.sensor] = self.publisher(self.keys.clock(m.sensor), ClockModel)
                seq[m.sensor] = seq.get(m.sensor, -1) + 1
                pub.put(
                    ClockModel(
                        seq=seq[m.sensor],
                        stamp_ns=clock.now_ns(),
                        sensor=m.sensor,
                        source=m.source,
                        offset_ns=m.offset_ns,
                        drift_ppb=m.drift_ppb,
                        ref_device_ns=m.ref_device_ns,
                        residual_rms_ns=m.residual_rms_ns,
                        n_samples=m.n_samples,
                        state=m.state,
                        steps_detected=m.steps_detected,
                    )
                )


SERVICE = TimeSync


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service timesync")
    ap.add_argument("--rig", default="default")
    a = ap.parse_args(argv)
    return run_service(TimeSync, a.rig, {})
