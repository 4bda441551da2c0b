"""``hil bench can``: the IMU CAN codec's cost against cantools, and the protocol's bus load.

Measures, in one run on this machine:

- decode cost per frame of the bridge's path (``ImuFrameAssembler.feed``: length, counter, E2E CRC,
  continuity, reassembly, scaling) against cantools' plain ``Database.decode_message`` (scaling
  only, no checks) over the same classic and FD frame streams;
- encode cost per sample (``ImuCanCodec.encode_sample``, counters + CRC included);
- bus load per mode and rate, from the frame arithmetic (worst-case stuffing) and from the
  ``ImuCanNode`` meter driven for one simulated second on an in-memory bus.
"""

from __future__ import annotations

import sys
import time

import can

from hil.bench import command_line, write_section
from hil.can.busload import sample_load
from hil.can.codec import ImuCanCodec, ImuFrameAssembler
from hil.can.node import ImuCanNode
from hil.runtime.argtypes import OneLineParser


class _NullBus(can.BusABC):
    """Accepts every frame: isolates the node's own cost and its load meter."""

    def __init__(self) -> None:
        super().__init__(channel="null")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        return None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def _stream(fd: bool, n: int) -> list[can.Message]:
    codec = ImuCanCodec.from_dbc(fd=fd)
    frames: list[can.Message] = []
    for i in range(n):
        frames += codec.encode_sample(
            device_stamp_ns=i * 2_500_000,
            dtheta_b_rad=[1e-5, -2e-5, 3e-6 * (i % 7)],
            dvel_b_mps=[0.01, 0.0, -0.0245],
        )
    return frames


def measure_decode(fd: bool, n: int) -> dict[str, float]:
    frames = _stream(fd, n)
    codec = ImuCanCodec.from_dbc(fd=fd)
    asm = ImuFrameAssembler(codec)
    t0 = time.perf_counter()
    out = 0
    for f in frames:
        out += len(asm.feed(f))
    ours = (time.perf_counter() - t0) / len(frames)
    db = codec.db
    t0 = time.perf_counter()
    for f in frames:
        db.decode_message(f.arbitration_id, f.data)
    ref = (time.perf_counter() - t0) / len(frames)
    assert out == n, f"decoded {out} of {n} samples"
    t0 = time.perf_counter()
    enc = ImuCanCodec.from_dbc(fd=fd)
    for i in range(n):
        enc.encode_sample(device_stamp_ns=i, dtheta_b_rad=[1e-5, 0.0, 0.0], dvel_b_mps=[0.0, 0.0, -0.0245])
    enc_s = (time.perf_counter() - t0) / n
    return {"frames": len(frames), "ours_us": ours * 1e6, "cantools_us": ref * 1e6, "encode_us": enc_s * 1e6}


def measure_bridge(fd: bool, n: int) -> float:
    """µs per sample of the live bridge's per-frame work: ``CanBridgeNode.on_message`` (assembler,
    ImuSample, raw CanFrame) and the runner publishing its outputs on a real, isolated Zenoh
    session with no subscriber -- what ``hil.runners.live`` does for every frame it reads."""
    from hil.bus.session import BusConfig, open_session
    from hil.nodes.can_bridge import CanBridgeNode
    from hil.runners.live import service_for
    from hil.runners.sim import SimOptions, sim_run_info
    from hil.runtime.service import ServiceContext

    session = open_session(BusConfig(listen=("tcp/127.0.0.1:0",), connect=()))
    ctx = ServiceContext(
        name="can_bridge",
        rig="benchcan",
        session=session,
        options={"interface": "virtual", "channel": "bench", "fd": fd},
    )
    bridge = service_for(CanBridgeNode)(ctx)
    bridge.setup()
    try:
        node = bridge.node = bridge.make_node(sim_run_info(SimOptions(rig="benchcan", duration_s=10.0)))
        frames = _stream(fd, n)
        t0 = time.perf_counter()
        for i, f in enumerate(frames):
            bridge._publish(node.on_message("@can/bench", f, i * 1000), "input")
        return (time.perf_counter() - t0) / n * 1e6
    finally:
        bridge.teardown()
        session.close()


def measure_load(fd: bool, rate: float) -> tuple[float, float]:
    """(frame arithmetic, node meter after one simulated second) at ``rate`` samples/s."""
    t = [0.0]
    bus = _NullBus()
    node = ImuCanNode(bus, ImuCanCodec.from_dbc(fd=fd), None, now=lambda: t[0])
    for i in range(int(rate)):
        t[0] = i / rate
        node.send_sample(i * round(1e9 / rate), [0.0] * 3, [0.0] * 3)
        if i % int(rate) == 0:
            node.send_sync(i)
    codec = node.codec
    frames = [(codec.fd_layout.length, True)] if fd else [(lay.length, False) for lay in codec.part_layouts]
    load = node.bus_load()
    bus.shutdown()
    return sample_load(frames, rate), load


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="hil bench can", description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--no-write", action="store_true", help="print only, do not update docs/benchmarks.md")
    args = ap.parse_args(argv)
    rows = [
        "| stream | frames | bridge path µs/frame | cantools decode_message µs/frame | cantools time / ours "
        "| encode µs/sample |"
    ]
    rows.append("| --- | --- | --- | --- | --- | --- |")
    for fd in (False, True):
        m = measure_decode(fd, args.samples)
        rows.append(
            f"| {'CAN FD, 1 frame/sample' if fd else 'classic, 4 frames/sample'} | {m['frames']:.0f} | "
            f"{m['ours_us']:.2f} | {m['cantools_us']:.2f} | {m['cantools_us'] / m['ours_us']:.2f}x | "
            f"{m['encode_us']:.1f} |"
        )
    bridge_rows = [
        "| stream | bridge node + publish µs/sample | CPU share at 400 Hz | at 2 kHz |",
        "| --- | --- | --- | --- |",
    ]
    for fd in (False, True):
        us = measure_bridge(fd, min(args.samples, 5000))
        bridge_rows.append(
            f"| {'CAN FD' if fd else 'classic'} | {us:.1f} | {us * 400 / 1e4:.1f} % "
            f"| {us * 2000 / 1e4:.1f} % |"
        )
    load_rows = ["| mode | rate | bus load, frame arithmetic | bus load, node meter (incl. status + sync) |"]
    load_rows.append("| --- | --- | --- | --- |")
    for fd in (False, True):
        for rate in (400.0, 1000.0):
            calc, meter = measure_load(fd, rate)
            load_rows.append(
                f"| {'CAN FD 1/5 Mbit/s' if fd else 'classic 1 Mbit/s'} | {rate:.0f} Hz "
                f"| {calc * 100:.1f} % | {meter * 100:.1f} % |"
            )
    body = (
        "Decode: the bridge's full per-frame path (DLC, counter, E2E CRC, continuity, reassembly, "
        "scaling) vs cantools' `decode_message` (scaling only), same frames, one run.\n\n"
        + "\n".join(rows)
        + "\n\nBridge per-sample work (assembler, ImuSample and raw CanFrame encoded and published on a "
        "real Zenoh session):\n\n"
        + "\n".join(bridge_rows)
        + "\n\nBus load (worst-case bit stuffing):\n\n"
        + "\n".join(load_rows)
        + "\n"
    )
    print(body)
    if not args.no_write:
        write_section("can", body, command_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
