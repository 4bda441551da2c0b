"""Fusion core: synchronised inputs in a total order, the shared free INS, estimators side by side.

Pure and deterministic: no I/O, no clock. Inputs arrive in any order; they are released in the
total order ``(stamp_ns, source rank, seq)`` once they are older than the watermark
``newest stamp seen - lag_ns`` (so a GNSS fix that arrives late, but within the lag, is still
fused at its time of validity between the IMU steps around it). An input that arrives behind the
released watermark is dropped and named in ``take_dropped()`` -- the service journals those, so
``hil rerun`` feeds exactly the same sequence through ``process()`` and gets every output bit for
bit.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.estimators.base import INPUTS, Estimator, ImuInput, InitialState
from hil.messages import FusionJournal, FusionSettings, GnssFix, ImuSample, Measurement, NavSolution
from hil.nav.types import NavState
from hil.sensor_table import SENSOR_NAMES, SENSORS, rank_of

FREE_INS = "ins"


@dataclass(frozen=True)
class FusionConfig:
    estimators: tuple[str, ...] = ()
    lag_ns: int = 200_000_000  # > worst GNSS latency + jitter, so fixes are fused in time order
    output_every: int = 8  # publish every N-th IMU step (by IMU seq: deterministic under loss)
    max_future_ns: int = 5_000_000_000  # an input this far ahead of the newest is rejected, not trusted
    max_buffered: int = 20_000  # bound on the reorder buffer (e.g. GNSS during an IMU outage)
    # plausibility bounds: a value beyond these is not a measurement, it is a fault or an attack;
    # one such input would poison the shared free INS (and every estimator) for the whole run
    max_dtheta_rad: float = 1.0  # per IMU interval (~57 deg: far beyond any DBC full scale)
    max_dvel_mps: float = 100.0  # per IMU interval
    max_pos_m: float = 2.0e7  # NED distance from the origin (Earth's half circumference)
    max_vel_mps: float = 2000.0
    gap_confirm_inputs: int = 40  # consecutive consistent "future" IMU inputs that prove a real gap
    # the seed estimators that run in feedback form (hil.estimators.feedback), and ekf15's
    # calibration states ("", "gyro", "gyro+accel"): both decided by the IMU grade when the
    # fusion starts (hil.nodes.fusion), journaled in fusion/config so rerun builds the same
    feedback: tuple[str, ...] = ()
    ekf_calibration: str = ""

    @property
    def lag_s(self) -> float:
        return self.lag_ns / 1e9

    def settings(self, seq: int, stamp_ns: int) -> FusionSettings:
        """This configuration as the typed message the recording keeps (``fusion/config``)."""
        return FusionSettings(
            seq=seq,
            stamp_ns=stamp_ns,
            estimators=list(self.estimators),
            lag_ns=self.lag_ns,
            output_every=self.output_every,
            max_future_ns=self.max_future_ns,
            max_buffered=self.max_buffered,
            max_dtheta_rad=self.max_dtheta_rad,
            max_dvel_mps=self.max_dvel_mps,
            max_pos_m=self.max_pos_m,
            max_vel_mps=self.max_vel_mps,
            gap_confirm_inputs=self.gap_confirm_inputs,
            feedback=list(self.feedback),
            ekf_calibration=self.ekf_calibration,
        )

    @classmethod
    def from_settings(cls, m: FusionSettings) -> FusionConfig:
        """The configuration a recording says the fusion ran with. A recording made before the
        feedback form and the calibration states has neither field: open loop, 15 states, which
        is what it ran."""
        tuples = ("estimators", "feedback")
        fields = {f: getattr(m, f) for f in cls.__dataclass_fields__ if f not in tuples}
        return cls(estimators=tuple(m.estimators), feedback=tuple(m.feedback), **fields)


def implausible(msg: Measurement, cfg: FusionConfig) -> str:
    """Why an input cannot be a measurement ("" if it can): non-finite or absurd values."""
    if isinstance(msg, ImuSample):
        if not all(math.isfinite(v) and abs(v) <= cfg.max_dtheta_rad for v in msg.dtheta_b_rad):
            return "dtheta"
        if not all(math.isfinite(v) and abs(v) <= cfg.max_dvel_mps for v in msg.dvel_b_mps):
            return "dvel"
        return ""
    if not isinstance(msg, GnssFix):
        return ""
    if not all(math.isfinite(v) and abs(v) <= cfg.max_pos_m for v in msg.pos_ned_m):
        return "pos"
    if not all(math.isfinite(v) and abs(v) <= cfg.max_vel_mps for v in msg.vel_ned_mps):
        return "vel"
    if not all(math.isfinite(v) and 0.0 < v < 1e6 for v in (*msg.pos_sigma_m, *msg.vel_sigma_mps)):
        return "sigma"
    return ""


def handler_of(est: Any, sensor: str) -> Any:
    """``est``'s handler of ``sensor``: ``Estimator.handler``, or ``on_<sensor>`` of an object
    that keeps the contract without deriving from the base class."""
    if isinstance(est, Estimator):
        return est.handler(sensor)
    return getattr(est, f"on_{sensor}", None)


def input_key(msg: Measurement) -> tuple[int, int, int]:
    """The total order: rig time of validity, then the sensor's rank, then seq."""
    return (msg.stamp_ns, rank_of(msg.sensor), msg.seq)


def input_id(msg: Measurement) -> str:
    return f"{msg.sensor}:{msg.seq}"


@dataclass
class FusionCore:
    init: InitialState
    config: FusionConfig
    make_estimator: Callable[[str, InitialState], Estimator] | None = None
    counters: dict[str, int] = field(default_factory=dict)
    params: dict[str, dict[str, Any]] = field(default_factory=dict)  # per estimator, e.g. from tuning

    @classmethod
    def for_scenario(cls, scenario: Any, config: FusionConfig, align_ns: int = 0) -> FusionCore:
        """The one way live, sim and rerun build the core: truth alignment, IMU-derived tuning.

        ``align_ns`` > 0 aligns from the truth at that rig time instead of at zero: what a fusion
        restarted mid-run does (services/fusion.py), the rig's equivalent of an in-flight
        re-alignment. Its outputs then differ from an uninterrupted run's, and say so in an event.
        """
        from hil.estimators.tuning import params_for
        from hil.nav.trajectory import TruthGenerator

        imu = scenario.imu.params
        params = params_for(
            imu,
            scenario.gnss,
            gyro_cal=config.ekf_calibration.startswith("gyro"),
            accel_cal=config.ekf_calibration == "gyro+accel",
            feedback=config.feedback,
        )

        truth = TruthGenerator(scenario)
        init = truth.initial_state()
        if align_ns > 0:
            from dataclasses import replace as dc_replace

            tb = truth.sample(np.array([align_ns], dtype=np.int64))
            init = dc_replace(
                init,
                stamp_ns=int(align_ns),
                lat_rad=float(tb.lat_rad[0]),
                lon_rad=float(tb.lon_rad[0]),
                alt_m=float(tb.alt_m[0]),
                vel_ned_mps=tb.vel_ned_mps[0].copy(),
                q_nb=tb.q_nb[0].copy(),
            )
        return cls(init, config, params=params)

    def start_output_seq(self, seq: int) -> None:
        """Number outputs from ``seq`` on (a restarted fusion must not reuse an earlier seq)."""
        for name in (FREE_INS, *self.config.estimators):
            self._out_seq[name] = max(self._out_seq.get(name, 0), int(seq))

    def __post_init__(self) -> None:
        from hil.nav import strapdown

        self._sd = strapdown
        self._ins = strapdown.strapdown_from_initial(self.init)
        self._origin = (self.init.origin_lat_rad, self.init.origin_lon_rad, self.init.origin_alt_m)
        maker = self.make_estimator
        if maker is None:
            from hil.estimators.registry import make_estimator

            def maker(name: str, init: InitialState) -> Estimator:
                return make_estimator(name, init, self.params.get(name))

        self._failed: set[str] = set()
        self.last_error = ""
        self.estimators: list[Estimator] = []
        for name in self.config.estimators:
            try:
                self.estimators.append(maker(name, self.init))
            except Exception as err:  # one broken estimator must not take the others down
                self._inc(f"errors.estimator_init.{name}")
                self.last_error = f"estimator {name} could not start: {type(err).__name__}: {err}"
        # per sensor (other than the IMU, which every estimator takes): the estimators' handlers,
        # in estimator order, resolved once
        self._handlers: dict[str, list[tuple[str, Any]]] = {
            sensor: [(e.name, h) for e in self.estimators if (h := handler_of(e, sensor)) is not None]
            for sensor in SENSOR_NAMES
            if not SENSORS[sensor].paces_fusion
        }
        self._pacer = {n for n in SENSOR_NAMES if SENSORS[n].paces_fusion}
        self._heap: list[tuple[tuple[int, int, int], int, Measurement]] = []
        self._arrivals = 0  # tie-break for identical keys: first arrival first, never compare messages
        self._future_lead_ns: int | None = None
        self._future_run = 0
        self._newest_ns: int | None = None
        self._last_key: tuple[int, int, int] = (-(2**62), -1, -1)
        self._dropped: list[str] = []
        self._out_seq: dict[str, int] = {}
        self._last_imu_seq = -1
        self._last_gnss_seq = -1
        self.consumed = 0

    # -- arrival side (live) ---------------------------------------------------------------
    def push(self, msg: Measurement) -> list[NavSolution]:
        key = input_key(msg)
        why = implausible(msg, self.config)
        if why:
            self._inc(f"rejected.implausible.{msg.sensor}.{why}")
            self._dropped.append("implausible:" + input_id(msg))
            return []
        if self._newest_ns is not None and msg.stamp_ns > self._newest_ns + self.config.max_future_ns:
            # One wild stamp is rejected; a run of consistent ones is a real gap in the input (a
            # router outage, a paused replay): accept it, or the fusion would refuse input forever.
            lead = self._future_lead_ns
            if lead is None or not lead <= msg.stamp_ns <= lead + self.config.max_future_ns:
                self._future_lead_ns, self._future_run = msg.stamp_ns, 0
            self._future_run += 1
            if msg.sensor not in self._pacer or self._future_run < self.config.gap_confirm_inputs:
                self._inc("rejected.future_stamp")
                self._dropped.append("future:" + input_id(msg))
                return []
            self._inc("input_gaps")
            self._newest_ns = msg.stamp_ns
        self._future_lead_ns, self._future_run = None, 0
        if key <= self._last_key:
            self._inc(f"dropped_late.{msg.sensor}")
            self._dropped.append("late:" + input_id(msg))
            return []
        heapq.heappush(self._heap, (key, self._arrivals, msg))
        self._arrivals += 1
        # The IMU is the fusion's clock: only its progress moves the watermark, so a GNSS fix that
        # arrives before the IMU samples around its time of validity waits for them.
        if msg.sensor in self._pacer and (self._newest_ns is None or msg.stamp_ns > self._newest_ns):
            self._newest_ns = msg.stamp_ns
        if self._newest_ns is None:
            return []
        if len(self._heap) > self.config.max_buffered:
            self._inc("released_on_overflow")
            return self._release(self._heap[0][0][0])
        return self._release(self._newest_ns - self.config.lag_ns)

    def flush(self) -> list[NavSolution]:
        """End of input: release everything still buffered."""
        return self._release(2**62)

    def journal(self, seq: int, stamp_ns: int) -> FusionJournal:
        """What was decided since the last journal: the live service and hil sim publish this."""
        return FusionJournal(
            seq=seq,
            stamp_ns=stamp_ns,
            watermark_ns=self.watermark_ns,
            consumed=self.consumed,
            dropped=self.take_dropped(),
        )

    def take_dropped(self) -> list[str]:
        out, self._dropped = self._dropped, []
        return out

    @property
    def watermark_ns(self) -> int:
        return self._last_key[0]

    def _release(self, watermark_ns: int) -> list[NavSolution]:
        out: list[NavSolution] = []
        while self._heap and self._heap[0][0][0] <= watermark_ns:
            key, _arrival, msg = heapq.heappop(self._heap)
            if key == self._last_key:  # a duplicate that was buffered twice
                self._inc(f"dropped_duplicate.{msg.sensor}")
                self._dropped.append("dup:" + input_id(msg))
                continue
            self._last_key = key
            out.extend(self.process(msg))
        return out

    # -- processing side (live after release, and rerun) -----------------------------------
    def process(self, msg: Measurement) -> list[NavSolution]:
        """Consume one input in total order; return the solutions it produced."""
        self.consumed += 1
        if isinstance(msg, ImuSample):
            return self._on_imu(msg)
        self._on_measurement(msg)
        return []

    def _on_imu(self, msg: ImuSample) -> list[NavSolution]:
        dt_s = msg.dt_ns * 1e-9
        dtheta = np.asarray(msg.dtheta_b_rad, dtype=np.float64)
        dvel = np.asarray(msg.dvel_b_mps, dtype=np.float64)
        self._ins = self._sd.strapdown_step(self._ins, dtheta, dvel, dt_s)
        ins_nav = self._sd.to_nav_state(self._ins, self._origin)
        imu = ImuInput(stamp_ns=msg.stamp_ns, dt_s=dt_s, dtheta_b_rad=dtheta, dvel_b_mps=dvel)
        for est in self.estimators:
            if est.name in self._failed:
                continue
            try:
                est.on_imu(imu, ins_nav)
            except Exception as err:
                self._fail(est.name, err)
        self._last_imu_seq = msg.seq
        if msg.seq % self.config.output_every:
            return []
        out: list[NavSolution] = []
        for name, get in [(FREE_INS, lambda: ins_nav)] + [
            (e.name, e.solution) for e in self.estimators if e.name not in self._failed
        ]:
            try:
                out.append(self._solution(name, get(), msg.stamp_ns))
            except ArithmeticError:
                # NaN never reaches a published solution: counted, not published
                self._inc(f"errors.nonfinite.{name}")
        return out

    def _on_measurement(self, msg: Measurement) -> None:
        """An aiding measurement at its time of validity, to every estimator that takes its kind."""
        convert = INPUTS.get(msg.sensor)
        data = convert(msg) if convert is not None else msg
        if data is None:
            self._inc(f"{msg.sensor}.unusable")
            return
        handlers = self._handlers.get(msg.sensor, ())
        if handlers:
            ins_nav = self._sd.to_nav_state(self._ins, self._origin)
            for name, handle in handlers:
                if name in self._failed:
                    continue
                try:
                    handle(data, ins_nav)
                except Exception as err:
                    self._fail(name, err)
        if msg.sensor == "gnss":
            self._last_gnss_seq = msg.seq

    def _fail(self, name: str, err: Exception) -> None:
        """An estimator that raises is taken out (and says so); the others go on."""
        self._failed.add(name)
        self._inc(f"errors.estimator_failed.{name}")
        self.last_error = f"estimator {name} failed: {type(err).__name__}: {err}"

    def _solution(self, name: str, nav: NavState, stamp_ns: int) -> NavSolution:
        from hil.nav.earth import ned_to_lla

        parts = [nav.pos_ned_m, nav.vel_ned_mps, nav.q_nb]
        if nav.pos_sigma_m is not None:
            parts.append(nav.pos_sigma_m)
        if nav.vel_sigma_mps is not None:
            parts.append(nav.vel_sigma_mps)
        if nav.att_sigma_rad is not None:
            parts.append(nav.att_sigma_rad)
        if not all(np.all(np.isfinite(p)) for p in parts):
            raise ArithmeticError(f"{name}: non-finite solution")
        lat, lon, alt = ned_to_lla(nav.pos_ned_m, *self._origin)
        seq = self._out_seq.get(name, 0)
        self._out_seq[name] = seq + 1
        return NavSolution(
            seq=seq,
            stamp_ns=stamp_ns,
            estimator=name,
            pos_ned_m=[float(v) for v in nav.pos_ned_m],
            vel_ned_mps=[float(v) for v in nav.vel_ned_mps],
            q_nb=[float(v) for v in nav.q_nb],
            lat_deg=float(np.degrees(lat)),
            lon_deg=float(np.degrees(lon)),
            alt_m=float(alt),
            pos_sigma_m=None if nav.pos_sigma_m is None else [float(v) for v in nav.pos_sigma_m],
            vel_sigma_mps=None if nav.vel_sigma_mps is None else [float(v) for v in nav.vel_sigma_mps],
            att_sigma_rad=None if nav.att_sigma_rad is None else [float(v) for v in nav.att_sigma_rad],
            imu_seq=self._last_imu_seq,
            gnss_seq=self._last_gnss_seq,
        )

    def status_counters(self) -> dict[str, int]:
        """What the status topic counts: rejections, drops, the buffer, inputs consumed."""
        out = dict(self.counters)
        out["buffered"] = len(self._heap)
        out["consumed"] = self.consumed
        return out

    def estimator_health(self) -> dict[str, dict[str, float]]:
        """Each running estimator's health, as the real numbers it reports (advisory: an
        estimator whose ``health()`` raises reports nothing rather than stopping the fusion)."""
        out: dict[str, dict[str, float]] = {}
        for est in self.estimators:
            if est.name in self._failed:
                continue
            try:
                out[est.name] = {k: float(v) for k, v in est.health().items()}
            except Exception:  # health is advisory
                self._inc(f"errors.health.{est.name}")
        return out

    def _inc(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1
