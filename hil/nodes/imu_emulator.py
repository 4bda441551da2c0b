"""The IMU as a CAN device: physics, error model, faults and DBC frames, paced by the caller.

Per sample ``k`` (an interval ending at true time ``t_k``; due once ``now >= (k+1)·dt``): the
error model's increments (``hil.sensors.imu.ImuEmulatorCore``, computed ahead in blocks of one
second of rig time -- its output does not depend on the block, and the same block in every
runner keeps even numpy's last bits the same), the scenario's and commanded faults
(``hil.faults.ImuFaults``), the device-clock stamp, the DBC frames (``hil.can.codec``), a
``can_latency`` delay line, a ``can_burst_error`` corruptor on the frames as they leave, and the
true capture time on ``capture/imu``. One sync (time-tag) frame a second goes first at its edge,
never held by ``can_latency``: it is the time tag the rig measures the transport against.

Restarted mid-run (option ``resume``, or started more than ``RESUME_AFTER_S`` into the run),
the device resumes at the sample index of the current rig time -- not at 0, which would burst
the whole past onto the bus. SampleCount starts at that index and the first sample carries a
status frame, so the bridge's ``seq`` continues without colliding with the samples sent before;
the samples of the dead time are a seq gap. Calibration errors come from the scenario seed and
survive the restart; the noise after it is a fresh stream (a power-cycled device).
"""

from __future__ import annotations

from typing import Any

from hil.can.codec import EncodeError, ImuCanCodec, PreparedFrames
from hil.faults import (
    IMU_FAULTS,
    DelayLine,
    FaultError,
    FrameCorruptor,
    ImuFaults,
    check_fault,
    command_addressee,
    fault_detail,
)
from hil.messages import CaptureTruth, FaultCommand
from hil.nav.scenario import scenario_for_run
from hil.nav.trajectory import truth_for
from hil.nodes.base import CAN_TX, CanBurst, CanWriterOptions, Input, Node, Out
from hil.sensors.clock import clock_config_for, device_clock_for
from hil.sensors.imu import ImuEmulatorCore, sensor_rng

RESUME_AFTER_S = 2.0  # a start this late into the run is a restart: resume, do not burst the past
BLOCK_NS = 1_000_000_000  # physics computed per second of rig time


class ImuEmulatorOptions(CanWriterOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The bus and pacing (``CanWriterOptions``; ``fd``: one frame per sample) and the DBC."""

    dbc: str | None = None  # the IMU's DBC (default: schemas/imu.dbc)


class ImuEmulatorNode(Node):
    name = "imu_emulator"
    Options = ImuEmulatorOptions
    inputs = (Input("control/fault", {"control": FaultCommand}),)
    outputs = ("capture/imu",)
    writes_can = True
    sends_time_tags = True

    def __init__(self, run: Any, options: ImuEmulatorOptions | None = None) -> None:
        super().__init__(run, options)
        opts: ImuEmulatorOptions = self.options  # type: ignore[assignment]
        s = scenario_for_run(run)
        self.core = ImuEmulatorCore(s, truth_for(s), sensor_rng(s.seed, "imu"))
        self.clock = device_clock_for(s, "imu")
        self.can_wire_latency_ns = round(clock_config_for(s, "imu").transport_latency_s * 1e9)
        self.codec = ImuCanCodec.from_dbc(opts.dbc, fd=opts.fd)
        self.faults = ImuFaults(s.seed, s.events)
        # can_latency: a sample's frames go through the delay line (released at once when no
        # window is active); the sync frame does not
        self.delay: DelayLine[CanBurst] = DelayLine(sensor_rng(s.seed, "imu.can_latency"))
        self.corruptor = FrameCorruptor()
        self.rate_hz = float(s.imu.rate_hz)
        self.dt_ns = round(1e9 / self.rate_hz)
        self.n_total = round(run.duration_s * self.rate_hz)
        self.sync_every = max(1, round(self.rate_hz))  # one sync/time-tag frame per second
        self.k = 0  # samples done; sample k ends at (k+1)*dt
        self._batch: Any = None
        self._i = 0
        self._t_true: list[int] = []
        self._stamps: list[int] = []  # the block's device stamps, at clock revision _stamps_revision
        self._stamps_revision = -1
        # the block encoded ahead: raw deltas (None: the checked way) and its frames' words
        self._prepared = PreparedFrames((), [], None)
        self._commands: list[FaultCommand] = []
        self._not_sent: dict[str, int] = {}

    def start(self, now_ns: int) -> list[Out]:
        if not (self.options.resume or now_ns > RESUME_AFTER_S * 1e9):
            return []
        k = min(max(0, now_ns // self.dt_ns), self.n_total)
        self.k = k
        self.core.count = k  # the next block starts at the interval ending at (k+1)*dt
        self.codec.samples_encoded = k  # SampleCount = device sample index
        detail = f"imu_emulator restarted: resumes at sample {k} (t={k * self.dt_ns / 1e9:.3f} s)"
        return [self.event("resumed", detail, now_ns)]

    def next_tick_ns(self) -> int | None:
        held = self.delay.next_release_ns()
        nxt = (self.k + 1) * self.dt_ns if self.k < self.n_total else None
        if held is None:
            return nxt
        return held if nxt is None else min(nxt, held)

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        if key == "control/fault":
            self._command(msg)
        return []

    def _command(self, cmd: FaultCommand) -> None:
        """Checked on arrival (a bad one counted, never raised), applied at the next sample."""
        mine, nobodys = command_addressee(cmd, IMU_FAULTS, "imu")
        if not (mine or nobodys):
            return
        try:
            check_fault(cmd.kind, cmd.target, cmd.param_map())
        except FaultError as err:
            self.error("rejected.control.fault", str(err))
            return
        if mine:
            self._commands.append(cmd)

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = [self._release(b) for b in self.delay.due(now_ns)]
        for _ in range(min(now_ns // self.dt_ns, self.n_total) - self.k):
            self._sample(now_ns, outs)
        return outs

    def _release(self, burst: CanBurst) -> Out:
        """Frames leave: a running burst error corrupts them now, in the order they go out."""
        if self.corruptor.pending:
            for frame in burst.frames:
                self.corruptor(frame)
        return CAN_TX, burst

    def _next_increments(self) -> tuple[int, int, Any, Any]:
        """The next sample's index in its block, true time and increments."""
        if self._batch is None or self._i >= len(self._batch.t_ns):
            t_end = ((self.k + 1) * self.dt_ns // BLOCK_NS + 1) * BLOCK_NS
            n = min(self.n_total, (t_end - 1) // self.dt_ns) - self.k
            b = self._batch = self.core.next_batch(max(1, n))
            self._i = 0
            # the block's device stamps and raw deltas in one numpy pass each, as the per-sample
            # calls would give them (the stamps until a commanded clock step makes them stale)
            self._t_true = b.t_ns.tolist()
            stamps = self.clock.device_ns_array(b.t_ns)
            self._stamps = stamps.tolist()
            self._stamps_revision = self.clock.revision
            # and its raw deltas and frames' words (counters, signals, CRCs), as the per-sample
            # encoding would make them
            self._prepared = self.codec.prepare_block(stamps, b.dtheta_b_rad, b.dvel_b_mps)
        b, i = self._batch, self._i
        self._i += 1
        return i, self._t_true[i], b.dtheta_b_rad[i], b.dvel_b_mps[i]

    def _sample(self, now_ns: int, outs: list[Out]) -> None:
        k = self.k
        i, t_true, dtheta, dvel = self._next_increments()
        if self._commands:
            self._take_commands(t_true, outs)
        for edge, f in self.faults.timeline.edges(t_true):
            outs.append(self.event(edge, fault_detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin), t_true))
        act = self.faults.apply(k, t_true, dtheta, dvel)
        fresh = self._stamps_revision == self.clock.revision
        dev = self._stamps[i] if fresh else self.clock.device_ns(t_true)
        if act.corrupt_frames:
            self.corruptor.arm(act.corrupt_frames)
        if act.send and (k + 1) % self.sync_every == 0:
            # the sync edge is this capture: its frame goes first and is never held
            try:
                sync = self.codec.encode_sync(dev)
            except (EncodeError, TypeError, ValueError) as err:
                self.error("tx_encode_errors", f"sync not encodable: {err}")
            else:
                counter, rate = self.clock.counter(t_true)
                burst = CanBurst(
                    [sync], t_true, k, sync=True, device_clock=(counter, rate, self.clock.quantum_ns)
                )
                burst.corrupted = self.corruptor.pending > 0  # _release corrupts it now if so
                outs.append(self._release(burst))
        # encoded even when not sent: the device's counters and SampleCount advance
        raws = self._prepared.raws[i] if act.dtheta_b_rad is dtheta and act.dvel_b_mps is dvel else None
        try:
            frames: list[Any] | None
            if raws is None:
                frames = self.codec.encode_sample(
                    device_stamp_ns=dev, dtheta_b_rad=act.dtheta_b_rad, dvel_b_mps=act.dvel_b_mps
                )
            else:  # the block's words, made with this stamp (a clock step since, or stale: here)
                frames = self.codec.encode_prepared(self._prepared, i) if fresh else None
                if frames is None:
                    frames = self.codec.encode_quantised(dev, raws)
        except (EncodeError, TypeError, ValueError) as err:
            self.error("tx_encode_errors", f"sample not encodable: {err}")
            frames = None
        if not act.send:
            self._not_sent[act.reason] = self._not_sent.get(act.reason, 0) + 1
        elif frames is not None:
            burst = CanBurst(list(frames), t_true, k)
            if self.delay.passes(t_true, act.latency_ns, act.jitter_ns):
                outs.append(self._release(burst))  # no can_latency, nothing held: now
            else:
                self.delay.push(t_true, act.latency_ns, act.jitter_ns, burst)
                outs.extend(self._release(b) for b in self.delay.due(now_ns))
        outs.append(("capture/imu", CaptureTruth(seq=k, stamp_ns=t_true, sensor="imu", true_stamp_ns=t_true)))
        self.k = k + 1

    def _take_commands(self, t_ns: int, outs: list[Out]) -> None:
        cmds, self._commands = self._commands, []
        for cmd in cmds:
            if cmd.kind == "clock_step":
                p = cmd.param_map()
                self.clock.add_step(t_ns, round(p["step_s"] * 1e9))
                detail = fault_detail(cmd.kind, t_ns, None, p, "command")
                outs.append(self.event("fault_start", detail, t_ns))
                continue
            self.faults.timeline.add(cmd.kind, t_ns, cmd.duration_s, cmd.param_map())

    def counters(self) -> dict[str, int]:
        """What the device counts (the live runner adds its transmitter's tx_frames, retries, ...)."""
        out = {f"fault.imu_samples_not_sent.{r}": n for r, n in sorted(self._not_sent.items())}
        out.update(
            tx_fault_dropped_samples=sum(self._not_sent.values()),
            tx_corrupted_frames=self.corruptor.corrupted,
            tx_saturated_samples=self.codec.saturated_samples,
        )
        if self.delay.delayed:  # absent when never delayed
            out["fault.can_latency.delayed_samples"] = self.delay.delayed
        out.update(self.counts)
        return out
