"""The free INS on a drifting IMU clock: the rig's own IMU chain, the INS integrated on its output.

Runs the nodes ``hil sim`` runs for the IMU -- emulator (increments on the true grid, stamps on
the device clock) -> CAN (the wire model) -> bridge (``dt_ns`` from consecutive device stamps) ->
time sync (re-stamp and rig interval) -- on a virtual clock, and integrates the fusion core's free
INS over each sample's interval: the re-stamped ``dt_ns`` of ``synced/imu`` (what the estimators
use) and the device ``dt_ns`` of the raw sample (what they used before time sync carried the
interval). The increments are the exact ones of an ideal IMU on the true sample grid (the
emulator's, paired by seq): the clock is then the only error besides the strapdown's own
discretisation, which is the same with every clock. (The CAN codec rounds every increment to its
DBC scale, 5e-8 rad and 1e-6 m/s; a noise-free signal's rounding is a bias, not white, and would
drown what is measured here: the Earth rate is 1.8e-7 rad per 2.5 ms sample.)
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass

import numpy as np

from hil.messages import ImuSample, Message
from hil.nav.scenario import Scenario, dump_toml, load_scenario, parse_scenario
from hil.nav.strapdown import strapdown_from_initial, strapdown_step, to_nav_state
from hil.nav.trajectory import TruthGenerator
from hil.nodes.can_bridge import CanBridgeNode, CanBridgeOptions
from hil.nodes.imu_emulator import ImuEmulatorNode, ImuEmulatorOptions
from hil.nodes.timesync import TimeSyncNode
from hil.nodes.world import run_info
from hil.runners.sim import Scheduler
from hil.runners.wire import CanWireModel
from hil.sensors.imu import ImuEmulatorCore, sensor_rng

#: A clock with no error of any kind: the reference the drifting ones are compared with.
PERFECT_CLOCK: dict[str, float] = {
    "offset_s": 0.0,
    "drift_ppm": 0.0,
    "drift_rw_ppm_per_sqrt_s": 0.0,
    "jitter_s": 0.0,
    "quantum_s": 0.0,
    "latch_jitter_s": 0.0,
    "transport_jitter_s": 0.0,
}


def clock_scenario(
    clock: dict[str, float] | None, duration_s: float, base: str = "straight_level", imu_preset: str = "ideal"
) -> Scenario:
    """``base`` with an ``imu_preset`` IMU and ``clock`` over the IMU's default clock
    (``[clock.imu]``; None: the default clock, 20 ppm fast)."""
    src = load_scenario(base)
    doc = tomllib.loads(src.source_text)
    doc["duration_s"] = float(duration_s)
    doc["imu"]["preset"] = imu_preset
    doc.pop("event", None)
    if clock:
        doc.setdefault("clock", {})["imu"] = dict(clock)
    return parse_scenario(dump_toml(doc, header=f"{base} for the IMU clock bench"), f"{base}_clock")


@dataclass(frozen=True)
class ClockRun:
    """Free INS errors at the end of the run, m: with the rig interval and with the device one."""

    synced_pos_err_m: float
    device_pos_err_m: float
    synced_vs_true_s: float  # Σ synced dt − true span of the samples (s)
    device_vs_true_s: float  # Σ device dt − true span
    n_samples: int
    true_span_s: float

    @property
    def synced_rel(self) -> float:
        """Relative error of the integration time scale, synced intervals."""
        return self.synced_vs_true_s / self.true_span_s


def imu_chain(scenario: Scenario, duration_s: float) -> tuple[list[ImuSample], list[ImuSample]]:
    """The raw and the synced IMU samples of ``duration_s`` of the rig's IMU chain."""
    run = run_info(scenario, rig="clock", start_epoch_ns=0, speed=1.0, duration_s=duration_s)
    nodes = [
        ImuEmulatorNode(run, ImuEmulatorOptions()),
        CanBridgeNode(run, CanBridgeOptions()),
        TimeSyncNode(run),
    ]
    raw: list[ImuSample] = []
    synced: list[ImuSample] = []

    def write(events: list[tuple[int, int, int, str, Message]]) -> None:
        for _t, _p, _o, key, msg in events:
            if key == "synced/imu":
                synced.append(msg)  # type: ignore[arg-type]
            elif key == "sensor/imu":
                raw.append(msg)  # type: ignore[arg-type]

    sched = Scheduler(nodes, write, CanWireModel(scenario))
    for i, node in enumerate(nodes):
        sched.publish(i, node.start(0), 0)
    end = int(duration_s * 1e9)
    t = 0
    while t <= end:
        t += 1_000_000_000
        sched.window(t)
    sched.finish(end + 1)
    return raw, synced


def exact_increments(scenario: Scenario, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``n`` increments of an ideal IMU on the true grid, ``(n, 3)`` each."""
    truth = TruthGenerator(scenario)
    imu = ImuEmulatorCore(scenario, truth, sensor_rng(scenario.seed, "imu"))
    b = imu.next_batch(n)
    return b.dtheta_b_rad, b.dvel_b_mps


def free_ins_error(scenario: Scenario, dt_s: list[float]) -> float:
    """The free INS over the exact increments with the intervals ``dt_s`` (one per sample, in
    sample order), integrated as the fusion core integrates it (``strapdown_step``): its position
    error against the truth at the end of the last true interval."""
    n = len(dt_s)
    dth, dv = exact_increments(scenario, n)
    truth = TruthGenerator(scenario)
    init = truth.initial_state()
    ins = strapdown_from_initial(init)
    for k in range(n):
        ins = strapdown_step(ins, dth[k], dv[k], dt_s[k])
    t_true = round(n * 1e9 / scenario.imu.rate_hz)
    tb = truth.sample(np.array([t_true], dtype=np.int64))
    return float(np.linalg.norm(to_nav_state(ins, init).pos_ned_m - tb.pos_ned_m[0]))


def clock_run(clock: dict[str, float] | None, duration_s: float) -> ClockRun:
    """The free INS after ``duration_s`` on exact increments, with the intervals of an IMU whose
    clock is ``clock`` after the rig's chain (every sample must arrive: the clock is the test)."""
    sc = clock_scenario(clock, duration_s)
    raw, synced = imu_chain(sc, duration_s)
    if [m.seq for m in synced] != list(range(len(synced))):
        raise RuntimeError("the IMU chain lost or reordered samples; the clock comparison needs them all")
    device_dt = {m.seq: m.dt_ns for m in raw}
    rig = [m.dt_ns * 1e-9 for m in synced]
    dev = [device_dt[m.seq] * 1e-9 for m in synced]
    span = len(synced) / sc.imu.rate_hz  # the true grid's span
    return ClockRun(
        synced_pos_err_m=free_ins_error(sc, rig),
        device_pos_err_m=free_ins_error(sc, dev),
        synced_vs_true_s=sum(rig) - span,
        device_vs_true_s=sum(dev) - span,
        n_samples=len(synced),
        true_span_s=span,
    )


def time_scale_effect(duration_s: float, rel: float) -> tuple[float, float]:
    """The free INS error on the true intervals and on intervals × (1 + ``rel``): the yardstick
    "to the 1e-6 level" is measured with, not assumed. Returns both errors, m."""
    sc = clock_scenario(PERFECT_CLOCK, duration_s)
    n = round(duration_s * sc.imu.rate_hz)
    dt = 1.0 / sc.imu.rate_hz
    return free_ins_error(sc, [dt] * n), free_ins_error(sc, [dt * (1.0 + rel)] * n)
