"""The CAN bridge: frames of the IMU (and of a device under test) -> contract messages.

Each frame read off the bus, with its receive stamp on the rig clock, becomes:

- ``can/<channel>``  the raw frame (``hil.CanFrame``, ``stamp_ns`` = receive stamp);
- ``sensor/imu``     each reassembled sample (``hil.can.codec.ImuFrameAssembler``: E2E CRC,
  rolling counter, reassembly): ``stamp_ns = rx_stamp_ns`` = receive stamp of the frame that
  completed it, ``device_stamp_ns`` from the frame, ``seq`` = the device's sample index (from the
  status frame's ``SampleCount``, so a lost sample is a seq gap and the emulator's capture truth
  pairs exactly), ``dt_ns`` from consecutive device stamps (``hil.timesync.sample_index``);
- ``timetag/imu``    a ``TimeTag(kind="sync_frame")`` per sync frame: the edge on the device
  clock paired with the frame's receive stamp, the time tag the synchronisation needs;
- ``nav/<name>``     a device under test's solution, decoded from its own frames with its DBC and
  mapping (option ``dut_mapping``, ``hil.can.dut``), scored beside the rig's estimators.

Bad frames (unknown identifier, wrong length, bad CRC, invalid or jumping counter, incomplete
sample) are counted under ``rejected.can.<kind>`` with the last one described; nothing stops the
bridge. A bridge restarted mid-stream (option ``resume``) waits for a SampleCount before it
numbers samples (the ones before are counted as ``dropped.can.unindexed_samples``).
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from hil.can.codec import DecodedSample, ImuCanCodec, ImuFrameAssembler
from hil.can.dut import DutNavDecoder
from hil.can.dut_emulator import load_dut
from hil.messages import TimeTag
from hil.nav.scenario import ScenarioError, scenario_for_run
from hil.nodes.base import CAN_RX, Node, NodeOptions, Out
from hil.nodes.builders import can_frame_msg, imu_sample_msg
from hil.timesync.sample_index import ImuSampleIndexer


def read_window_ms(rate_hz: float) -> float:
    """The CAN bridge's read window when none is asked for: 20 ms up to 500 Hz (at most ten
    samples a window), 10 ms above. At 400 Hz, on a 2-CPU VM where a thread's wake-up costs ~30 µs
    of CPU, 20 ms took the rig to 0.84-0.92x the CPU of 10 ms (five alternating pairs) for the
    fused output's p99 30-33 ms after its IMU sample instead of 19-22 ms (the target: 50 ms); at
    1 kHz it gave p99 49 ms, and at 2 kHz with CAN FD the same CPU as 10 ms with p99 241 ms
    against 83 ms (docs/benchmarks.md, session 40)."""
    return 20.0 if rate_hz <= 500.0 else 10.0


class CanBridgeOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    channel: str = "vcan0"  # CAN channel read
    interface: str | None = None  # python-can interface; None: socketcan if the channel exists, else hilzenoh
    fd: bool = False  # the IMU's CAN FD mode (the assembler accepts both)
    rate_hz: float | None = None  # nominal IMU rate for dt_ns; None: the run's scenario
    dbc: str | None = None  # the IMU's DBC (default: schemas/imu.dbc)
    publish_raw: bool = True  # publish every frame on can/<channel>
    # After a wake-up for a frame, the live runner waits this long and reads every frame queued
    # meanwhile before the outputs go out: each key's messages of that read (raw frames, IMU
    # samples) leave as one batch, one Zenoh message and one wake-up of each subscriber, instead
    # of one per sample. The samples keep their receive stamps (the frames'), so time sync and
    # the fusion compute the same; only their delivery waits. 0: each sample's outputs at once;
    # None: by the IMU's rate (read_window_ms).
    can_batch_ms: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] | None = None
    dut_mapping: str | None = None  # a device under test on this bus: its mapping TOML


class CanBridgeNode(Node):
    inputs_move_timers = False  # its timers are its own: periodic, or none
    name = "can_bridge"
    Options = CanBridgeOptions
    reads_can = True
    outputs = ("sensor/imu", "timetag/imu")

    def __init__(self, run: Any, options: CanBridgeOptions | None = None) -> None:
        super().__init__(run, options)
        opts: CanBridgeOptions = self.options  # type: ignore[assignment]
        self.channel = opts.channel
        self.raw_key = f"can/{self.channel}"
        self._publish_raw = opts.publish_raw
        self.codec = ImuCanCodec.from_dbc(opts.dbc, fd=opts.fd)
        self.assembler = ImuFrameAssembler(self.codec)
        rate = opts.rate_hz
        if not rate:
            try:
                rate = float(scenario_for_run(run).imu.rate_hz)
            except ScenarioError as err:
                self.error("errors.scenario", f"IMU rate from the run's scenario: {err}; assuming 400 Hz")
                rate = 400.0
        self.indexer = ImuSampleIndexer(max(1, round(1e9 / rate)), wait_for_count=bool(opts.resume))
        # the live runner's read window (hil.runners.live), ms
        self.read_window_ms = opts.can_batch_ms if opts.can_batch_ms is not None else read_window_ms(rate)
        self._seen_problems = 0
        self._seen_status = 0
        self._seen_lost = 0
        self.dut: DutNavDecoder | None = None
        self._dut_ids: frozenset[int] = frozenset()
        if opts.dut_mapping:
            self._setup_dut(opts.dut_mapping)

    def _setup_dut(self, mapping: str) -> None:
        try:
            db, m = load_dut(mapping)
            self.dut = DutNavDecoder(
                db, m, self.run.origin_lat_deg, self.run.origin_lon_deg, self.run.origin_alt_m
            )
        except (ValueError, OSError) as err:
            self.error("errors.dut_config", f"device under test disabled: {err}")
            return
        self._dut_ids = frozenset(msg.frame_id for msg in db.messages)
        self.dut_key = f"nav/{m.estimator}"

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        """``key`` ``@can/<channel>``: a frame read off the bus, received at rig time ``now_ns``."""
        if not key.startswith(CAN_RX):
            return []
        outs: list[Out] = []
        if self._publish_raw:
            outs.append((self.raw_key, can_frame_msg(self.next_seq(self.raw_key), now_ns, self.channel, msg)))
        if self.dut is not None and msg.arbitration_id in self._dut_ids:
            self._dut_frame(msg, now_ns, outs)
            return outs
        asm = self.assembler
        items = asm.feed(msg)
        if asm.problems != self._seen_problems:
            self._seen_problems = asm.problems
            kind, detail = asm.last_problem
            self.error(f"rejected.can.{kind}", detail)
        for item in items:
            if isinstance(item, DecodedSample):
                self._sample(item, now_ns, outs)
            else:
                tag = TimeTag(
                    seq=self.next_seq("timetag/imu"),
                    stamp_ns=now_ns,
                    sensor="imu",
                    kind="sync_frame",
                    device_stamp_ns=item.device_stamp_ns,
                )
                outs.append(("timetag/imu", tag))
        return outs

    def _sample(self, s: DecodedSample, rx_ns: int, outs: list[Out]) -> None:
        c = self.assembler.counters
        n_status, n_lost = c["status"], c["lost_frames"] + c["incomplete_sample"]
        count = self.assembler.last_sample_count if n_status != self._seen_status else None
        step = self.indexer.next(s.device_stamp_ns, count, n_lost != self._seen_lost)
        self._seen_status, self._seen_lost = n_status, n_lost
        if step is None:  # restarted mid-stream, no SampleCount yet: its seq would be a guess
            self.inc("dropped.can.unindexed_samples")
            return
        idx, dt = step
        outs.append(("sensor/imu", imu_sample_msg(idx, rx_ns, dt, s)))

    def _dut_frame(self, msg: Any, rx_ns: int, outs: list[Out]) -> None:
        dut = self.dut
        assert dut is not None
        before = sum(v for k, v in dut.counters.items() if k not in ("frames", "solutions"))
        sol = dut.feed(msg, rx_ns)
        if sum(v for k, v in dut.counters.items() if k not in ("frames", "solutions")) != before:
            self.error("rejected.dut", dut.last_error)
        if sol is not None:
            outs.append((self.dut_key, sol))

    def counters(self) -> dict[str, int]:
        out = {f"can.{k}": v for k, v in self.assembler.counters.items()}
        out.update(self.counts)
        return out
