"""Time sync: every raw measurement re-stamped to its rig time of validity; clock models.

The estimator is ``hil.timesync.core.TimeSyncCore``, configured per sensor from the scenario's
``[clock.<sensor>]`` tables (``hil.timesync.config``): time tags or arrival times only, the
calibrated tag latency and minimum delay. A re-stamped measurement on ``synced/<sensor>`` is the
raw one with ``stamp_ns`` replaced, so it keeps its ``seq`` and pairs with its raw original and
its capture truth. Each sensor's measurements and time tags come in through one subscription
(``*/<sensor>``), so they reach the core in publication order -- the order a recording keeps,
which ``hil rerun --core timesync`` relies on.

An interval measurement (the IMU's ``dt_ns``: increments integrated over one sample period of the
device's oscillator) is re-stamped too: ``dt_ns`` on ``synced/imu`` is that period on the rig
clock, the mapping's rate applied (``TimeSyncCore.rig_interval``), with the same mapping as the
stamp. The estimators integrate over it, so an IMU whose crystal runs 20 ppm fast is integrated
over the true interval, as a 20 µg accelerometer error would otherwise be. Here, not in the
fusion: the mapping lives here, and live, ``hil sim`` and ``hil rerun`` all read the recorded
``synced/imu``, so the correction is made once and replays bit for bit.

Live, a publisher that is not one of the rig's processes is refused before this node
(``Node.refuses_foreign``, ``rejected.foreign.<kind>`` in status): what the time sync publishes is
the rig's. A raw measurement whose seq this node has already re-stamped (among the last ``DEDUP_WINDOW`` of
its sensor) is refused (``rejected.duplicate_seq.<sensor>``): a second ``gnss:42`` -- a Zenoh
redelivery, or a stranger's copy -- would otherwise leave as a second ``synced/gnss`` seq 42 of
the same publisher, which no journal could tell from the first.

A measurement's arrival is ``arrival_ns()``: for a fix read off a serial line, when its epoch's
first byte came (``GnssFix.line_ns`` before the read that completed it), which is where the
receiver's latency -- the minimum delay -- ends; the bytes' time on the line (the message set at
the baud rate: ~27 ms of NMEA at 115200) would otherwise put every fix that much late.

The core may hold a few measurements while it decides whether the device clock stepped; held
ones are released by the verdict, at the end of input, or when their sensor falls silent: before
its next input stamped more than ``IDLE_RELEASE_NS`` after the last measurement's arrival (not
during the start-up hold, which has its own bound). That rule reads only the sensor's own inputs,
so ``hil rerun --core timesync`` releases where the service did. The service does not wait for
that input: every ``IDLE_TICK_NS`` of its clock it releases what a sensor silent for
``IDLE_RELEASE_NS`` plus ``IDLE_MARGIN_NS`` holds (the rule will hold for any input still on its
way, unless it was that long on it), so a held fix reaches the fusion within its horizon. Should
the next input prove the rule wrong (stamped within ``IDLE_RELEASE_NS`` after all: the process
or the bus stalled), that is counted (``idle_release_early.<sensor>``) and said on
``event/timesync``: a rerun's re-stamps of that sensor differ from there. Clock models go out once
a second.

A restarted time sync (``hil up --restart``: option ``resume``) is a fresh core on what its new
process received, which depends on when its subscription took effect. So on the first input of
each sensor it publishes a ``first_input`` event naming that input (``first_input_detail``):
per sensor, one process publishes the measurements and tags over one link, in order, so the new
core took exactly that input and every later one of the sensor, and ``hil rerun --core timesync``
rebuilds it from there (``first_input_named``).
"""

from __future__ import annotations

import re
from collections import deque
from typing import Any, ClassVar

import msgspec

from hil.messages import Measurement, TimeTag
from hil.nav.scenario import scenario_for_run
from hil.nodes.base import BatchedInputOptions, Input, Node, NodeOptions, Out
from hil.nodes.builders import clock_model_msg
from hil.sensor_table import SENSOR_NAMES, SENSORS
from hil.timesync.config import sync_configs_for
from hil.timesync.core import TimeSyncCore

IDLE_TICK_NS = 50_000_000  # how often the service looks for a silent sensor's held measurements
IDLE_MARGIN_NS = 50_000_000  # how long an input may be on its way and still keep the rule true
DEDUP_WINDOW = 8192  # recent seqs per sensor remembered to refuse a repeat
CLOCK_PERIOD_NS = 1_000_000_000

_FIRST_INPUT = re.compile(r"the first input it received of (\w+): ((?:timetag|sensor)/\w+):(-?\d+)@(\S*)")


def first_input_detail(sensor: str, key: str, seq: int, source: str) -> str:
    """A restarted time sync's ``first_input`` event: the input of ``sensor`` its fresh core began
    with (``key`` ``timetag/<sensor>`` or ``sensor/<sensor>``, its seq and publisher)."""
    return (
        f"time sync restarted: a fresh core re-stamps {sensor} from the first input it received "
        f"of {sensor}: {key}:{seq}@{source}"
    )


def first_input_named(detail: str) -> tuple[str, str, int, str] | None:
    """(sensor, key, seq, publisher) from a ``first_input`` event's detail; None if it names none."""
    m = _FIRST_INPUT.search(detail)
    return (m[1], m[2], int(m[3]), m[4]) if m else None


class TimeSyncNode(Node):
    inputs_move_timers = False  # its timers are its own: periodic, or none
    refuses_foreign = True  # a stranger's raw measurement must not come out as the rig's synced one
    name = "timesync"
    Options: ClassVar[type[NodeOptions]] = BatchedInputOptions
    inputs = tuple(Input(f"*/{s}", {"sensor": SENSORS[s].message, "timetag": TimeTag}) for s in SENSOR_NAMES)
    outputs = tuple(f"synced/{s}" for s in SENSOR_NAMES)

    def __init__(self, run: Any, options: Any = None) -> None:
        super().__init__(run, options)
        configs = sync_configs_for(scenario_for_run(run), imu_can_fd=run.imu_can_fd)
        self.core: TimeSyncCore[Measurement] = TimeSyncCore(configs)
        self.end_ns = int(run.duration_s * 1e9)
        self._next_idle = IDLE_TICK_NS
        self._next_clock = CLOCK_PERIOD_NS
        # sensors released on the clock (``tick``) whose next input is still to prove it right
        self._released_on_clock: set[str] = set()
        self._recent: dict[str, tuple[set[int], deque[int]]] = {}
        # a restarted time sync: the sensors whose first input it has not named yet (bounded by
        # the sensor table: inputs come only on its sensors' keys)
        self._unnamed: set[str] = set(SENSOR_NAMES) if self.generation > 0 else set()

    def on_message_from(self, key: str, msg: Any, now_ns: int, source: str) -> list[Out]:
        if self._unnamed:
            sensor = key.rpartition("/")[2]
            if sensor in self._unnamed:
                self._unnamed.discard(sensor)
                detail = first_input_detail(sensor, key, msg.seq, source)
                return [self.event("first_input", detail, now_ns), *self.on_message(key, msg, now_ns)]
        return self.on_message(key, msg, now_ns)

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        if self._released_on_clock:
            early = self._released_early(msg, now_ns)
            if early:
                return early + self._take(msg)
        return self._take(msg)

    def _take(self, msg: Any) -> list[Out]:
        if isinstance(msg, TimeTag):
            return self._synced(self.core.on_timetag(msg.sensor, msg.device_stamp_ns, msg.stamp_ns))
        if msg.sensor not in SENSORS:
            self.error("rejected.sensor.unknown", f"no synced channel for sensor {msg.sensor!r}")
            return []
        if self._repeat(msg.sensor, msg.seq):
            self.error(
                f"rejected.duplicate_seq.{msg.sensor}",
                f"sensor/{msg.sensor} seq {msg.seq} came again; the first one was re-stamped",
            )
            return []
        return self._synced(self.core.on_measurement(msg.sensor, msg.device_stamp_ns, msg.arrival_ns(), msg))

    def _repeat(self, sensor: str, seq: int) -> bool:
        recent = self._recent.get(sensor)
        if recent is None:  # not setdefault: that built a set and a deque for every measurement
            recent = self._recent[sensor] = (set(), deque())
        seen, order = recent
        if seq in seen:
            return True
        seen.add(seq)
        order.append(seq)
        if len(order) > DEDUP_WINDOW:
            seen.discard(order.popleft())
        return False

    def _synced(self, released: list[tuple[Any, int]]) -> list[Out]:
        """Re-stamped measurements; an interval (``dt_ns``) is taken to the rig clock by the
        mapping that stamped it (the one in force now: the core released them under it)."""
        out: list[Out] = []
        for m, t in released:
            dt = getattr(m, "dt_ns", None)
            if dt is None:
                out.append((f"synced/{m.sensor}", msgspec.structs.replace(m, stamp_ns=t)))
                continue
            dt_rig = self.core.rig_interval(m.sensor, m.device_stamp_ns, dt)
            if not 0 < dt_rig <= 10**9:  # beyond the message's range (no sane mapping): kept, counted
                self.inc(f"rig_interval_kept.{m.sensor}")
                dt_rig = dt
            out.append((f"synced/{m.sensor}", msgspec.structs.replace(m, stamp_ns=t, dt_ns=dt_rig)))
        return out

    def _released_early(self, msg: Any, now_ns: int) -> list[Out]:
        """The first input of a sensor this node released on its clock: did the rule the inputs
        apply (``SensorSync.ends_silence``, against the last arrival: a tag does not move it)
        hold for it?"""
        sensor = msg.sensor
        s = self.core.sensors.get(sensor)
        if sensor not in self._released_on_clock or s is None or s.last_rx_ns is None:
            return []
        if isinstance(msg, TimeTag):
            if s.cfg.source != "timetag":
                return []  # a tag the core does not use moves nothing (``SensorSync.on_timetag``)
            stamp = msg.stamp_ns
        else:
            stamp = msg.arrival_ns()
        self._released_on_clock.discard(sensor)
        if s.ends_silence(stamp):
            return []
        self.inc(f"idle_release_early.{sensor}")
        last = s.last_rx_ns
        detail = (
            f"{sensor}: held measurements released on the clock, the sensor silent since its last "
            f"arrival, but {sensor} seq {msg.seq} (stamped {(stamp - last) / 1e6:.1f} ms after that "
            f"arrival, taken {(now_ns - last) / 1e6:.0f} ms after it) was still on its way: a rerun "
            f"releases them after it, so its re-stamps of {sensor} differ from here"
        )
        return [self.event("idle_release_early", detail, now_ns)]

    def next_tick_ns(self) -> int | None:
        t = min(self._next_idle, self._next_clock)
        return t if t <= self.end_ns else None

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = []
        if now_ns >= self._next_idle:
            self._next_idle = (now_ns // IDLE_TICK_NS + 1) * IDLE_TICK_NS
            for name, s in self.core.sensors.items():
                # the rule the inputs apply (``SensorSync.idle_release_due``), sure to hold for an
                # input on its way for less than the margin; never the start-up hold (its bound is
                # device time: a stalled process is not a silent sensor)
                if s.idle_release_due(now_ns - IDLE_MARGIN_NS):
                    self._released_on_clock.add(name)
                    outs.extend(self._synced(s.release_held()))
        if now_ns >= self._next_clock:
            self._next_clock = (now_ns // CLOCK_PERIOD_NS + 1) * CLOCK_PERIOD_NS
            for m in list(self.core.mappings.values()):
                key = f"clock/{m.sensor}"
                outs.append((key, clock_model_msg(self.next_seq(key), now_ns, m)))
        return outs

    def finish(self, now_ns: int) -> list[Out]:
        return self._synced(self.core.flush())  # measurements still held at the end of input

    def counters(self) -> dict[str, int]:
        out = {f"steps_detected.{k}": m.steps_detected for k, m in self.core.mappings.items()}
        out.update(self.counts)
        return out
