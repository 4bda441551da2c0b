"""The live pacing of CAN frames (hil.runners.pacing) on a simulated clock: the grid is kept,
frames of a sample are spaced by their wire time, a stall never compresses the grid below wire
speed, and a late time tag states when it left."""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import pytest

from hil.can.codec import ImuCanCodec
from hil.nodes.base import CanBurst
from hil.runners.pacing import CanWire, PacedSender, PacingConfig, Waiter

PERIOD = 2_500_000


class FakeClock:
    """Rig time = monotonic time = epoch time (ns); sleeping advances it, with an overshoot."""

    def __init__(self, overshoot_ns: int = 30_000) -> None:
        self.t = 0
        self.overshoot_ns = overshoot_ns

    def mono(self) -> int:
        self.t += 100  # every read costs a little, as a spin does
        return self.t

    def sleep(self, s: float) -> None:
        self.t += round(s * 1e9) + self.overshoot_ns

    def now_ns(self) -> int:
        return self.mono()

    def mono_of_rig(self, rig_ns: int) -> int:
        return rig_ns

    def rig_of_mono(self, mono_ns: int) -> int:
        return mono_ns

    def epoch_ns(self, rig_ns: int) -> int:
        return rig_ns


@dataclass
class Sink:
    clock: FakeClock
    stamps: bool = True
    sent: list[tuple[int, int | None, can.Message]] = field(default_factory=list)
    bursts: list[tuple[bool, bool]] = field(default_factory=list)
    handovers: list[int] = field(default_factory=list)  # frames per send_burst call

    @property
    def carries_stamps(self) -> bool:
        return self.stamps

    def send_frame(self, frame: Any, stamp_epoch_ns: int | None = None) -> bool:
        self.sent.append((self.clock.t, stamp_epoch_ns, frame))
        return True

    def send_burst(self, frames: Any, stamps_epoch_ns: Any) -> bool:
        assert self.stamps and len(frames) == len(stamps_epoch_ns)  # only a stamped bus gets bursts
        self.handovers.append(len(frames))
        for frame, stamp in zip(frames, stamps_epoch_ns, strict=True):
            self.sent.append((self.clock.t, stamp, frame))
        return True

    def count_burst(self, ok: bool, sync: bool) -> None:
        self.bursts.append((ok, sync))


def _sender(stamps: bool = True, **cfg: Any) -> tuple[PacedSender, FakeClock, Sink]:
    clock = FakeClock()
    sink = Sink(clock, stamps)
    codec = ImuCanCodec.from_dbc(None)
    ps = PacedSender(clock, PacingConfig(**cfg), sink, codec.restamp_sync, trace=True)  # type: ignore[arg-type]
    ps.waiter = Waiter(now=clock.mono, sleep=clock.sleep)
    return ps, clock, sink


def _burst(k: int, n: int = 4) -> CanBurst:
    frames = [can.Message(arbitration_id=0x100 + i, data=bytes(8), is_extended_id=False) for i in range(n)]
    return CanBurst(frames, (k + 1) * PERIOD, k)


@pytest.mark.parametrize("stamps", [True, False])
def test_samples_leave_on_their_grid_with_frames_at_wire_spacing(stamps: bool) -> None:
    ps, _clock, sink = _sender(stamps)
    wire = CanWire()
    for k in range(50):
        ps.send(_burst(k), (k + 1) * PERIOD, backlog=True)
    frame_ns = wire.frame_ns(_burst(0).frames[0])
    assert 100_000 < frame_ns < 140_000  # 8 data bytes at 1 Mbit/s, worst-case stuffing
    for row in ps.trace or []:
        _index, _due, ideal, handed, frames, _sub = row
        assert frames == 4 and 0 <= handed - ideal < 5_000  # on time to a few µs
    # each frame's wire time: 1, 2, 3, 4 frame times after its sample's tick
    for i, (t, stamp, _f) in enumerate(sink.sent):
        k, j = divmod(i, 4)
        due_end = (k + 1) * PERIOD + (j + 1) * frame_ns
        when = stamp if stamps else t
        assert when is not None and 0 <= when - due_end < 5_000
    assert ps.counts["tx_late_samples"] == 0 and len(sink.bursts) == 50
    # a bus that carries stamps gets each sample's four frames in one hand-over
    assert sink.handovers == ([4] * 50 if stamps else [])


def test_a_stall_is_sent_late_at_wire_speed_and_counted_never_bunched() -> None:
    ps, clock, sink = _sender()
    clock.t = 10 * PERIOD  # the host stalled for ten samples
    for k in range(12):
        ps.send(_burst(k), (k + 1) * PERIOD, backlog=True)
    frame_ns = CanWire().frame_ns(_burst(0).frames[0])
    stamps = [s for _t, s, _f in sink.sent]
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert min(gaps) >= frame_ns  # never faster than the wire carries frames
    assert ps.counts["tx_late_samples"] >= 9 and ps.counts["tx_late_max_us"] > 20_000


def test_skip_policy_drops_passed_slots_and_keeps_the_grid() -> None:
    ps, clock, sink = _sender(late_policy="skip", period_ns=PERIOD)
    clock.t = 10 * PERIOD
    for k in range(12):
        ps.send(_burst(k), (k + 1) * PERIOD, backlog=True)
    assert ps.counts["tx_late_skipped_samples"] == 9
    assert len(sink.bursts) == 3


def test_a_late_time_tag_states_when_it_left() -> None:
    ps, clock, sink = _sender()
    codec = ImuCanCodec.from_dbc(None)
    tick = 1_000
    dev0 = 5 * PERIOD + 7_000_000  # the device counter at the edge (offset 7 ms)
    sync = codec.encode_sync(dev0 - dev0 % tick)
    edge = 5 * PERIOD
    clock.t = edge + 3_000_000  # the sender got to it 3 ms after its edge
    ps.send(CanBurst([sync], edge, 5, sync=True, device_clock=(dev0, 1.0, tick)), edge)
    assert ps.counts["tx_sync_restamped"] == 1 and ps.counts["tx_sync_dropped"] == 0
    ((_t, stamp, frame),) = sink.sent
    assert frame.data[1] & 0x0F == sync.data[1] & 0x0F  # the same transmission's counter
    stated = codec.decode(frame.arbitration_id, frame.data)["DeviceTime"]
    # the device time it states is that of its first bit, a frame time before the stamp
    left = stamp - CanWire().frame_ns(frame)
    want_ns = dev0 + (left - edge)
    assert abs(stated - want_ns) <= 2 * tick, (stated, want_ns)  # DeviceTime is in ns


@pytest.mark.parametrize("stamps", [True, False])
def test_a_time_tag_handed_over_late_is_stamped_with_its_stated_instant_or_dropped(stamps: bool) -> None:
    ps, clock, sink = _sender(stamps)
    clock.overshoot_ns = 2_000_000  # every sleep wakes 2 ms late: the hand-over misses its instant
    codec = ImuCanCodec.from_dbc(None)
    edge = 5 * PERIOD
    clock.t = edge + 3_000_000
    sync = codec.encode_sync(edge)
    ps.send(CanBurst([sync], edge, 5, sync=True, device_clock=(edge, 1.0, 1_000)), edge)
    if stamps:  # the stamp is the instant the tag states (+ its wire time), not the late hand-over
        ((t, stamp, frame),) = sink.sent
        stated = codec.decode(frame.arbitration_id, frame.data)["DeviceTime"]
        assert stamp is not None and t - stamp > 1_000_000
        assert abs(stamp - CanWire().frame_ns(frame) - stated) <= 1_000
        assert ps.counts["tx_sync_dropped"] == 0
    else:  # SocketCAN stamps at send: a tag that cannot meet its instant is not sent
        assert sink.sent == [] and ps.counts["tx_sync_dropped"] == 1


def test_the_pacing_bench_reads_the_emulators_last_counters_from_a_recording() -> None:
    """hil bench pacing took ServiceStatus.counters for a mapping (it is a list of Count) and died."""
    from hil.bench.pacing import _last_counters
    from hil.record.mcapio import read_session

    golden = Path(__file__).parents[1] / "replay" / "golden" / "straight_level_4s.mcap"
    counters = _last_counters(read_session(golden))
    assert counters["tx_fault_dropped_samples"] == 0
    assert set(counters) >= {"tx_corrupted_frames", "tx_saturated_samples"}


def test_a_sample_behind_its_sync_frame_is_judged_on_the_ideal_wire_not_late() -> None:
    """On a sync edge the time tag goes first and the sample's frames follow it on the wire, as
    on a real bus: that is the ideal schedule, not lateness; a real stall still counts."""
    ps, clock, sink = _sender()
    codec = ImuCanCodec.from_dbc(None)
    wire = CanWire()
    for k in range(20):
        due = (k + 1) * PERIOD
        if k % 10 == 9:  # a sync edge on this tick
            sync = codec.encode_sync(due)
            ps.send(CanBurst([sync], due, k, sync=True, device_clock=(due, 1.0, 1_000)), due)
        ps.send(_burst(k), due, backlog=True)
    assert ps.counts["tx_late_samples"] == 0
    rows = ps.trace or []
    edge = rows[9]
    sync_ns, frame_ns = wire.frame_ns(sink.sent[36][2]), wire.frame_ns(_burst(0).frames[0])
    # the sample's first frame ends a sync frame and a frame after its tick, and that is on time
    assert edge[2] == edge[1] + sync_ns + frame_ns
    assert all(0 <= handed - ideal < 5_000 for _i, _d, ideal, handed, _f, _s in rows)
    # a stall after it is still late against the same ideal wire
    clock.t = 40 * PERIOD
    ps.send(_burst(20), 21 * PERIOD, backlog=True)
    assert ps.counts["tx_late_samples"] == 1


def _slice_of_this_thread() -> int | None:
    """The calling thread's scheduler slice (ns) from sched_getattr, None where unreadable."""
    import ctypes
    import os

    from hil.runners import pacing

    nr = pacing._SYS_SCHED_GETATTR.get(os.uname().machine)
    if nr is None:
        return None
    buf = ctypes.create_string_buffer(pacing._SCHED_ATTR.size)
    if ctypes.CDLL(None, use_errno=True).syscall(nr, 0, buf, pacing._SCHED_ATTR.size, 0) != 0:
        return None
    return int(pacing._SCHED_ATTR.unpack(buf.raw)[5])


def test_the_sender_asks_for_a_short_slice_or_says_why_not() -> None:
    """In a thread of its own (the attribute is per thread): the slice is set where the kernel
    has EEVDF's custom slices (Linux 6.12+), else one line says why; never an exception."""
    import threading

    from hil.runners.pacing import short_slice

    got: dict[str, Any] = {}

    def probe() -> None:
        before = _slice_of_this_thread()
        got["note"] = short_slice(100)
        got["after"] = _slice_of_this_thread()
        got["off"] = short_slice(0)
        got["before"] = before

    t = threading.Thread(target=probe)
    t.start()
    t.join(10)
    assert not t.is_alive()
    assert got["off"] is None
    if got["note"] is None:
        assert got["after"] == 100_000, got
    else:
        assert isinstance(got["note"], str) and "slice" in got["note"], got


def test_the_slice_option_reaches_the_emulator_from_hil_up() -> None:
    from hil.cli import build_parser
    from hil.runtime.options import fill_options, options_class
    from hil.runtime.supervisor import UpOptions

    up_args = build_parser().parse_args(["up"])
    assert up_args.sched_slice_us == UpOptions().sched_slice_us == 100
    assert options_class("imu_emulator")().sched_slice_us == 100  # type: ignore[attr-defined]
    assert fill_options("imu_emulator", UpOptions(sched_slice_us=0))["sched_slice_us"] == 0
    with pytest.raises(SystemExit):
        build_parser().parse_args(["up", "--sched-slice-us", "-1"])


def test_a_service_takes_the_rigs_cpus_from_its_environment_or_says_why_not() -> None:
    """``HIL_CPUS`` (``hil up --rig-cpus``) pins the thread that reads it -- first thing in
    ``hil service``, so every thread after inherits it. In a thread of its own here."""
    import os
    import threading

    from hil.runners.pacing import rig_cpus_from_env

    got: dict[str, Any] = {}

    def probe() -> None:
        got["note"] = rig_cpus_from_env({"HIL_CPUS": "0"})
        got["cpus"] = os.sched_getaffinity(0)
        got["bad"] = rig_cpus_from_env({"HIL_CPUS": "zero"})
        got["unset"] = rig_cpus_from_env({})

    t = threading.Thread(target=probe)
    t.start()
    t.join(10)
    assert got["note"] is None and got["cpus"] == {0}, got
    assert "HIL_CPUS" in got["bad"] and got["unset"] is None, got
    # the one parser of CPU lists (--cpu-affinity, --rig-cpus, HIL_CPUS, the benches)
    from hil.runners.pacing import parse_cpus

    assert parse_cpus("0, 2") == [0, 2] and parse_cpus("") == []
    for bad in ("x", "-1", "1.5"):
        with pytest.raises(ValueError):
            parse_cpus(bad)


_PIN = """
import json, os, threading, time
from hil.runners.pacing import pin_process, unpin_process
stop = threading.Event()
t = threading.Thread(target=stop.wait, daemon=True); t.start()  # a thread that was there before
before = os.sched_getaffinity(0)
mask, note = pin_process([0])
pinned = sorted({tuple(sorted(os.sched_getaffinity(int(x)))) for x in os.listdir("/proc/self/task")})
late = []
t2 = threading.Thread(target=lambda: late.append(sorted(os.sched_getaffinity(0)))); t2.start(); t2.join()
unpin_process(mask)
after = sorted({tuple(sorted(os.sched_getaffinity(int(x)))) for x in os.listdir("/proc/self/task")})
stop.set(); t.join()
print(json.dumps({"note": note, "pinned": pinned, "late": late, "after": after, "before": sorted(before)}))
"""


def test_hil_ups_own_threads_go_to_the_rigs_cpus_and_come_back() -> None:
    """The supervisor's hub routes on Zenoh's threads, which may exist before it runs (a bench):
    every thread is moved, one started later inherits it, and all are put back at the end."""
    import json
    import subprocess
    import sys

    from tests.conftest import REPO

    out = subprocess.run([sys.executable, "-c", _PIN], cwd=REPO, capture_output=True, text=True, timeout=60)
    res = json.loads(out.stdout)
    assert res["note"] is None and res["pinned"] == [[0]] and res["late"] == [[0]], res
    assert res["after"] == [res["before"]], res


def test_hil_up_refuses_cpus_this_machine_lacks() -> None:
    from tests.conftest import run_hil

    proc = run_hil("up", "--rig-cpus", "4096", "--duration", "1", timeout=60)
    assert proc.returncode == 2 and "--rig-cpus" in proc.stderr and "Traceback" not in proc.stderr, (
        proc.stderr
    )


_UP_CPUS = """
import json, sys
from hil.runtime import supervisor
seen = {}
def run(self):
    seen["env"] = self._child_env().get("HIL_CPUS")
    seen["slice"] = self.options_for("imu_emulator").get("sched_slice_us")
    seen["sender"] = self.options_for("imu_emulator").get("cpu_affinity")
    return 0
supervisor.Supervisor.run = run
from hil.cli import main
main(["up", "--quiet", "--duration", "1", "--record", sys.argv[1], "--rig", "cpus", "--rig-cpus", "0",
      "--cpu-affinity", "1", "--sched-slice-us", "250"])
print(json.dumps(seen))
"""


def test_hil_up_hands_its_services_the_rigs_cpus_and_the_sender_its_own(tmp_path: Path) -> None:
    import json
    import subprocess
    import sys

    from tests.conftest import REPO

    out = subprocess.run(
        [sys.executable, "-c", _UP_CPUS, str(tmp_path / "x.mcap")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen == {"env": "0", "slice": 250, "sender": [1]}, out.stdout + out.stderr


def test_hil_up_says_how_many_samples_left_late_and_what_would_help() -> None:
    from hil.messages import ServiceStatus, counts
    from hil.runtime.supervisor import Supervisor, UpOptions

    def status(name: str, c: dict[str, int]) -> ServiceStatus:
        return ServiceStatus(
            seq=0, stamp_ns=0, service=name, state="running", pid=1, uptime_s=1.0, counters=counts(c)
        )

    sup = Supervisor(UpOptions(live=False))
    assert sup.pacing_line() == ""  # nothing counted yet
    sup.view.status["can_bridge"] = status("can_bridge", {"can.samples": 8000})
    sup.view.status["imu_emulator"] = status("imu_emulator", {"tx_late_samples": 536, "tx_late_max_us": 7448})
    line = sup.pacing_line()
    assert line.startswith("IMU frames: 536 of 8000 samples") and "7.4 ms" in line
    assert ("--rig-cpus 0" in line) == ((os.cpu_count() or 1) >= 2)
    assert "--rt-priority 50" in line and line.endswith("(docs/timing.md)")
    sup.view.status["imu_emulator"] = status("imu_emulator", {"tx_late_samples": 20, "tx_late_max_us": 900})
    assert "--rig-cpus" not in sup.pacing_line() and "--rt-priority" not in sup.pacing_line()  # on time
    late = status("imu_emulator", {"tx_late_samples": 536, "tx_late_max_us": 7448})
    placed = Supervisor(UpOptions(live=False, rig_cpus=[0], cpu_affinity=[1]))
    placed.view.status.update(sup.view.status)
    placed.view.status["imu_emulator"] = late
    line = placed.pacing_line()
    assert "--rig-cpus" not in line and "--rt-priority 50" in line  # placed: priority is what is left
    rt = Supervisor(UpOptions(live=False, rt_priority=50))
    rt.view.status.update(sup.view.status)
    rt.view.status["imu_emulator"] = late
    assert (
        rt.pacing_line()
        == "IMU frames: 536 of 8000 samples handed to the bus more than 200 µs late (worst 7.4 ms)"
    )
