"""can_bridge: CAN frames of the IMU -> decoded ``ImuSample``, raw ``CanFrame`` and sync ``TimeTag``.

Reads the bus with python-can (SocketCAN where the channel exists, else the ``hilzenoh``
transport; see ``hil.can.bus.open_can_bus``), checks every frame's E2E CRC and rolling counter,
reassembles samples (``hil.can.codec.ImuFrameAssembler``) and publishes:

- ``hil/<rig>/can/<channel>``  every frame read, ``stamp_ns`` = its receive stamp on rig time;
- ``hil/<rig>/sensor/imu``     each complete sample: ``stamp_ns = rx_stamp_ns`` = receive stamp
  of the frame that completed it, ``device_stamp_ns`` from the frame, ``dt_ns`` from the
  difference of consecutive device stamps (nominal ``1e9 / rate_hz`` for the first one or after a
  gap longer than a second);
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
from hil.messages import CanFrame, ImuSample, RunInfo, TimeTag
from hil.runtime.clock import RigClock
from hil.runtime.service import Service, run_service

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
        self._prev_device_ns: int | None = None
        self.emit_event("can_transport", self.transport)

    def extra_status(self) -> dict[str, int]:
        asm = getattr(self, "assembler", None)
        return {f"can.{k}": v for k, v in asm.counters.items()} if asm is not None else {}

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        start, speed = run.start_epoch_ns, run.speed
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

    def handle(self, msg: can.Message, start_epoch_ns: int, speed: float) -> None:
        """Per-frame work: raw frame out, assembler step, decoded outputs out."""
        rx_ns = epoch_s_to_rig_ns(msg.timestamp, start_epoch_ns, speed)
        if self.publish_raw:
            self.pub_can.put(
                CanFrame(
                    seq=self.pub_can.next_seq(),
                    stamp_ns=rx_ns,
                    channel=self.channel,
                    arbitration_id=msg.arbitration_id & 0x1FFFFFFF,
                    is_extended_id=bool(msg.is_extended_id),
                    is_fd=bool(msg.is_fd),
                    bitrate_switch=bool(msg.bitrate_switch),
                    is_error_frame=bool(msg.is_error_frame),
                    data_hex=bytes(msg.data[:64]).hex(),
                )
            )
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
        prev = self._prev_device_ns
        dt = s.device_stamp_ns - prev if prev is not None else 0
        if not 0 < dt <= 1_000_000_000:
            dt = self.nominal_dt_ns
        self._prev_device_ns = s.device_stamp_ns
        self.pub_imu.put(
            ImuSample(
                seq=self.pub_imu.next_seq(),
                stamp_ns=rx_ns,
                device_stamp_ns=s.device_stamp_ns,
                rx_stamp_ns=rx_ns,
                dt_ns=dt,
                dtheta_b_rad=list(s.dtheta_b_rad),
                dvel_b_mps=list(s.dvel_b_mps),
                status=s.status,
            )
        )
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
    }
    return run_service(CanBridge, args.rig, options)


if __name__ == "__main__":
    sys.exit(main())
