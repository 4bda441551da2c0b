"""timesync: re-stamps every raw measurement to rig time of validity and publishes clock models.

A re-stamped measurement on ``synced/<sensor>`` keeps the ``seq`` of its raw original, so the
recording pairs every synced message with its raw one and its true capture time. The estimator
is ``hil.timesync.core.TimeSyncCore``, configured per sensor from the scenario's
``[clock.<sensor>]`` tables (``hil.timesync.config``): time tags or arrival times only, the
calibrated tag latency and minimum delay. The core may hold a few measurements while it decides
whether the device clock stepped; held ones are released by the next measurement, or here when
a sensor has gone quiet (so the end of a run loses nothing).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import queue
import threading
from typing import Any

import msgspec

from hil.bus.keys import SENSOR_TYPES
from hil.bus.pubsub import DispatchSubscriber
from hil.messages import ClockModel, GnssFix, ImuSample, RunInfo, TimeTag
from hil.runtime.builders import clock_model_msg
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service
from hil.timesync.config import sync_configs_for
from hil.timesync.core import TimeSyncCore

IDLE_FLUSH_S = 0.2  # release held measurements of a sensor silent this long


class TimeSync(Service):
    name = "timesync"

    def setup(self) -> None:
        self.core: TimeSyncCore[ImuSample | GnssFix] = TimeSyncCore()
        self.lock = threading.Lock()
        self.inbox: queue.SimpleQueue[ImuSample | GnssFix | TimeTag | None] = queue.SimpleQueue()
        self._worker = threading.Thread(target=self._work, name="timesync", daemon=True)
        self._worker.start()
        self.synced_pubs = {s: self.publisher(self.keys.synced(s), cls) for s, cls in SENSOR_TYPES.items()}
        self.clock_pubs: dict[str, Any] = {}
        # One subscription per sensor for its measurements *and* its time tags, so the core sees
        # them in publication order (the recorder's order): `hil rerun --core timesync` relies on it.
        for sensor, cls in SENSOR_TYPES.items():
            self._subs.append(
                DispatchSubscriber(
                    self.ctx.session,
                    f"{self.keys.root}/*/{sensor}",
                    {"sensor": (cls, self._enqueue), "timetag": (TimeTag, self._enqueue)},
                    self.stats,
                )
            )

    def _enqueue(self, msg: ImuSample | GnssFix | TimeTag, _key: str) -> None:
        # Zenoh's callback thread only enqueues: this subscription also matches our own
        # synced/<sensor> and clock/<sensor> outputs, and publishing from inside the callback
        # could wait on the very queue that callback drains.
        self.inbox.put(msg)

    def _work(self) -> None:
        """One thread consumes the inbox in arrival order (= publication order per sensor)."""
        while True:
            msg = self.inbox.get()
            if msg is None:
                return
            try:
                if isinstance(msg, TimeTag):
                    self._on_timetag(msg, "")
                else:
                    self._on_measurement(msg, "")
            except Exception as err:  # a bad measurement must not stop re-stamping
                self.stats.error("errors.timesync", f"{type(err).__name__}: {err}")

    def _on_timetag(self, tag: TimeTag, _key: str) -> None:
        with self.lock:
            self.core.on_timetag(tag.sensor, tag.device_stamp_ns, tag.stamp_ns)

    def _on_measurement(self, msg: ImuSample | GnssFix, _key: str) -> None:
        if msg.sensor not in self.synced_pubs:
            self.stats.error("rejected.sensor.unknown", f"no synced channel for sensor {msg.sensor!r}")
            return
        with self.lock:
            released = self.core.on_measurement(msg.sensor, msg.device_stamp_ns, msg.rx_stamp_ns, msg)
            self._publish(released)

    def _publish(self, released: list[tuple[ImuSample | GnssFix, int]]) -> None:
        # under self.lock: held measurements go out in their arrival order
        for m, t in released:
            self.synced_pubs[m.sensor].put(msgspec.structs.replace(m, stamp_ns=t))

    def extra_status(self) -> dict[str, int]:
        core = getattr(self, "core", None)
        if core is None:
            return {}
        with self.lock:
            return {f"steps_detected.{k}": m.steps_detected for k, m in core.mappings.items()}

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        configs = sync_configs_for(scenario_for_run(run))
        with self.lock:
            fresh: TimeSyncCore[ImuSample | GnssFix] = TimeSyncCore(configs)
            self._publish(self.core.flush())  # anything seen before the run was announced
            self.core = fresh
        seen: dict[str, int] = {}
        tick = 0
        while not self.ctx.stop.wait(IDLE_FLUSH_S):
            tick += 1
            with self.lock:
                for name, s in self.core.sensors.items():
                    if s.held and seen.get(name) == s.n_arrivals:
                        self._publish(s.flush())
                    seen[name] = s.n_arrivals
                maps = [dataclasses.replace(m) for m in self.core.mappings.values()]
            if tick % round(1.0 / IDLE_FLUSH_S):
                continue
            for m in maps:
                pub = self.clock_pubs.get(m.sensor)
                if pub is None:
                    pub = self.clock_pubs[m.sensor] = self.publisher(self.keys.clock(m.sensor), ClockModel)
                # the publisher's counter: in this process's restart generation (service.py)
                pub.put(clock_model_msg(pub.next_seq(), clock.now_ns(), m))

    def teardown(self) -> None:
        self.inbox.put(None)  # what arrived before the stop is still re-stamped
        self._worker.join(timeout=5.0)
        # the session may already be closing: nothing more to say then
        with self.lock, contextlib.suppress(Exception):
            self._publish(self.core.flush())


SERVICE = TimeSync


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service timesync")
    ap.add_argument("--rig", default="default")
    a = ap.parse_args(argv)
    return run_service(TimeSync, a.rig, {})
