"""can_bridge: CAN frames of the IMU -> decoded ``ImuSample``, raw ``CanFrame`` and sync ``TimeTag``.

Reads the bus with python-can (SocketCAN where the channel exists, else the ``hilzenoh``
transport; see ``hil.can.bus.open_can_bus``), checks every frame's E2E CRC and rolling counter,
reassembles samples (``hil.can.codec.ImuFrameAssembler``) and publishes:

- ``hil/<rig>/can/<channel>``  every frame read, ``stamp_ns`` = its receive stamp on rig time;
- ``hil/<rig>/sensor/imu``     each complete sample: ``stamp_ns = rx_stamp_ns`` = receive stamp
  of the frame that completed it, ``device_stamp_ns`` from the frame, ``seq`` = the device's
  sample index (from the status frame's ``SampleCount``, so a lost sample is a seq gap and the
  emulator's capture truth pairs exactly), ``dt_ns`` from the difference of consecutive device
  stamps per sample index (nominal ``1e9 / rate_hz`` for the first one or across a clock step;
  see ``hil.timesync.sample_index``);
- ``hil/<rig>/timetag/imu``    ``TimeTag(kind="sync_frame")`` per sync frame: the edge on the device
  clock paired with the frame's receive stamp, the time-tag the synchronisation service needs.

Receive stamps are python-can's ``msg.timestamp`` (the kernel's for SocketCAN), epoch seconds,
mapped to rig ns as ``(ts * 1e9 - start_epoch_ns) * speed``. Bad frames (unknown identifier,
wrong length, bad CRC, invalid or jumping counter, incomplete sample) are counted under
``rejected.can.<kind>`` with the last one described in the status; nothing stops the bridge.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import can

from hil.can.bus import open_can_bus
from hil.can.codec import DecodedSample, ImuCanCodec, ImuFrameAssembler
from hil.messages import CanFrame, ImuSample, NavSolution, RunInfo, TimeTag
from hil.runtime.builders import can_frame_msg, imu_sample_msg
from hil.runtime.clock import RigClock
from hil.runtime.service import Service, run_service
from hil.timesync.sample_index import ImuSampleIndexer

DEFAULT_RATE_HZ = 400.0


def epoch_s_to_rig_ns(ts_s: float, start_epoch_ns: int, speed: float) -> int:
    """``(ts * 1e9 - start) * speed`` without adding float error to ``ts``'s own ~0.24 µs.

    Split the stamp into whole seconds (exact integer ns arithmetic against the start) and the
    fraction, so the subtraction of two ~1.8e18 ns numbers never happens in floating point.
    """
    whole = int(ts_s)
    frac_ns = round((ts_s - whole) * 1e9)
    wall_ns = whole * 1_000_000_000 + frac_ns - start_epoch_ns
    return wall_ns if speed == 1.0 else int(wall_ns * speed)


class CanBridge(Service):
    """The process shell around ``ImuFrameAssembler``: bus in, contract messages out."""

    name = "can_bridge"

    def setup(self) -> None:
        opts = self.ctx.options
        self.channel: str = str(opts.get("channel") or "vcan0")
        self.fd = bool(opts.get("fd", False))
        rate = float(opts.get("rate_hz") or DEFAULT_RATE_HZ)
        self.nominal_dt_ns = max(1, round(1e9 / rate))
        self._rate_given = bool(opts.get("rate_hz"))
        self.codec = ImuCanCodec.from_dbc(opts.get("dbc"), fd=self.fd)
        self.assembler = ImuFrameAssembler(self.codec)
        self.bus, self.transport = open_can_bus(
            self.channel, opts.get("interface"), fd=self.fd, rig=self.ctx.rig, session=self.ctx.session
        )
        self.pub_imu = self.publisher(self.keys.sensor("imu"), ImuSample)
        self.pub_can = self.publisher(self.keys.can(self.channel), CanFrame)
        self.pub_tag = self.publisher(self.keys.timetag("imu"), TimeTag)
        self.publish_raw = bool(opts.get("publish_raw", True))
        self._seen_problems = 0
        # restarted (option resume): the stream is running, wait for a SampleCount (sample_index.py)
        self._joined_late = bool(opts.get("resume"))
        self._indexer = ImuSampleIndexer(self.nominal_dt_ns, wait_for_count=self._joined_late)
        self._seen_status = 0
        self._seen_lost = 0
        self.emit_event("can_transport", self.transport)

    def extra_status(self) -> dict[str, int]:
        asm = getattr(self, "assembler", None)
        return {f"can.{k}": v for k, v in asm.counters.items()} if asm is not None else {}

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        start, speed = run.start_epoch_ns, run.speed
        if not self._rate_given:
            # the run's scenario says the IMU rate (hil up --imu-rate changes it): nominal dt from it
            from hil.runtime.scenario_io import scenario_for_run

            try:
                self.nominal_dt_ns = max(1, round(1e9 / scenario_for_run(run).imu.rate_hz))
                self._indexer = ImuSampleIndexer(self.nominal_dt_ns, wait_for_count=self._joined_late)
            except ValueError as err:
                self.stats.error("errors.scenario", f"IMU rate from the run's scenario: {err}")
        self._setup_dut(run)
        stop = self.ctx.stop
        while not stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.1)
            except can.CanError as err:  # bus went away: say so, keep trying until stopped
                self.stats.error("errors.can.recv", f"{self.transport}: {err}")
                stop.wait(0.2)
                continue
            if msg is not None:
                self.handle(msg, start, speed)

    def _setup_dut(self, run: RunInfo) -> None:
        """A device under test on the same bus: its frames become ``nav/<name>`` (option dut_mapping)."""
        self.dut = None
        mapping = self.ctx.options.get("dut_mapping")
        if not mapping:
            return
        from hil.can.dut import DutNavDecoder
        from hil.can.dut_emulator import load_dut

        try:
            db, m = load_dut(mapping)
            self.dut = DutNavDecoder(db, m, run.origin_lat_deg, run.origin_lon_deg, run.origin_alt_m)
        except (ValueError, OSError) as err:
            self.stats.error("errors.dut_config", f"device under test disabled: {err}")
            return
        self._dut_ids = frozenset(msg.frame_id for msg in db.messages)
        self.pub_dut = self.publisher(self.keys.nav(m.estimator), NavSolution)

    def _handle_dut(self, msg: can.Message, rx_ns: int) -> None:
        dut = self.dut
        before = sum(v for k, v in dut.counters.items() if k not in ("frames", "solutions"))
        sol = dut.feed(msg, rx_ns)
        if sum(v for k, v in dut.counters.items() if k not in ("frames", "solutions")) != before:
            self.stats.error("rejected.dut", dut.last_error)
        if sol is not None:
            self.pub_dut.put(sol)

    def handle(self, msg: can.Message, start_epoch_ns: int, speed: float) -> None:
        """Per-frame work: raw frame out, assembler step, decoded outputs out."""
        rx_ns = epoch_s_to_rig_ns(msg.timestamp, start_epoch_ns, speed)
        if self.publish_raw:
            self.pub_can.put(can_frame_msg(self.pub_can.next_seq(), rx_ns, self.channel, msg))
        if getattr(self, "dut", None) is not None and msg.arbitration_id in self._dut_ids:
            self._handle_dut(msg, rx_ns)
            return
        out = self.assembler.feed(msg)
        asm = self.assembler
        if asm.problems != self._seen_problems:
            self._seen_problems = asm.problems
            kind, detail = asm.last_problem
            self.stats.error(f"rejected.can.{kind}", detail)
        for item in out:
            if isinstance(item, DecodedSample):
                self._publish_sample(item, rx_ns)
            else:
                self.pub_tag.put(
                    TimeTag(
                        seq=self.pub_tag.next_seq(),
                        stamp_ns=rx_ns,
                        sensor="imu",
                        kind="sync_frame",
                        device_stamp_ns=item.device_stamp_ns,
                    )
                )

    def _publish_sample(self, s: DecodedSample, rx_ns: int) -> None:
        c = self.assembler.counters
        n_status, n_lost = c["status"], c["lost_frames"] + c["incomplete_sample"]
        count = self.assembler.last_sample_count if n_status != self._seen_status else None
        step = self._indexer.next(s.device_stamp_ns, count, n_lost != self._seen_lost)
        self._seen_status, self._seen_lost = n_status, n_lost
        if step is None:  # restarted mid-stream, no SampleCount yet: its seq would be a guess
            self.stats.inc("dropped.can.unindexed_samples")
            return
        idx, dt = step
        self.pub_imu.put(imu_sample_msg(idx, rx_ns, dt, s))
        self.stats.count_rate("in.can.imu_samples")

    def teardown(self) -> None:
        bus = getattr(self, "bus", None)
        if bus is not None:
            bus.shutdown()


SERVICE = CanBridge


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="can_bridge", description=__doc__.splitlines()[0])
    p.add_argument("--rig", default=os.environ.get("HIL_RIG", "default"))
    p.add_argument("--channel", default="vcan0")
    p.add_argument("--interface", default=None, help="auto (default), socketcan, hilzenoh, virtual")
    p.add_argument("--fd", action="store_true", help="CAN FD (one frame per sample)")
    p.add_argument("--rate-hz", type=float, default=DEFAULT_RATE_HZ, help="nominal IMU rate for dt_ns")
    p.add_argument("--dbc", default=None, help="DBC path (default: schemas/imu.dbc or $HIL_DBC)")
    p.add_argument("--no-raw", action="store_true", help="do not publish raw CanFrame messages")
    p.add_argument("--dut-mapping", default=None, help="a device-under-test mapping TOML (see examples/dut)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    options: dict[str, Any] = {
        "channel": args.channel,
        "interface": args.interface,
        "fd": args.fd,
        "rate_hz": args.rate_hz,
        "dbc": args.dbc,
        "publish_raw": not args.no_raw,
        "dut_mapping": args.dut_mapping,
    }
    return run_service(CanBridge, args.rig, options)


if __name__ == "__main__":
    sys.exit(main())
