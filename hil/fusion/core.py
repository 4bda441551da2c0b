"""Fusion core: synchronised inputs in a total order, the shared free INS, estimators side by side.

Pure and deterministic: no I/O, no clock. Inputs arrive in any order; the estimators take them in
the total order ``(stamp_ns, source rank, seq)`` on a delayed fusion horizon, the watermark
``newest IMU stamp - lag_ns``: a GNSS fix that arrives late, but within the lag, is fused at its
time of validity between the IMU steps around it. With the output predictor (the default,
``hil.fusion.predictor``: PX4 EKF2's scheme) what is published is not the horizon's state but
each estimator's horizon state carried to the newest IMU sample by the IMU increments since, at
the arrival of that sample; without it (recordings made before it, or
``output_predictor=False``), the horizon's state is published as it is reached, ``lag`` late.

``lag_ns`` is thus the bound on a source's latency: an input older than the released horizon is
refused (``late``, counted, journaled) and a source whose latency crosses the bound raises a
``latency_over_bound`` event (``latency_within_bound`` when it comes back). With the predictor an
IMU sample that arrives behind a newer one (a time sync step) still reaches the estimators on the
horizon, but not the predictor, which has integrated past it: it is named in
``take_unpredicted()``. Every refusal is named in ``take_dropped()``; the service journals both,
so ``hil rerun`` feeds exactly the same sequence through ``replay()`` and gets every output bit
for bit.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.estimators.base import INPUTS, Estimator, ImuBlock, InitialState, imu_bias_floats_of
from hil.fusion.gnss_gate import GateSettings, GnssGate, ReceiverModel, Transition
from hil.fusion.predictor import NO_BIAS, Motion, OutputPredictor, carry_rows
from hil.messages import FusionJournal, FusionSettings, GnssFix, ImuSample, Measurement, NavSolution
from hil.nav.attitude import RESET_ACCEL_SPAN_NS, levelled_attitude, velocity_rate
from hil.nav.earth import _origin_floats, ned_to_lla_one
from hil.nav.limits import MAX_GNSS_SIGMA
from hil.nav.sensor_specs import G0_MPS2
from hil.nav.types import NavState, nav_floats
from hil.sensor_table import SENSOR_NAMES, SENSORS, rank_of

FREE_INS = "ins"
#: The most IMU intervals the core defers before its estimators step them (``ImuBlock``): a bound
#: on the block, whatever reads them or not.
IMU_BLOCK_MAX = 64
isfinite, degrees = math.isfinite, math.degrees


@dataclass(frozen=True)
class FusionConfig:
    estimators: tuple[str, ...] = ()
    # the fusion horizon's delay behind the newest IMU stamp, and so the bound on a source's
    # latency: > worst GNSS latency + jitter (0.1 s; car_drive's latency event 0.25 + 0.02 s)
    lag_ns: int = 500_000_000
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
    # aiding inputs (GNSS) held in the reorder buffer: 200 s of 10 Hz fixes through an IMU outage;
    # beyond, the one furthest ahead is evicted (journaled), so junk stamped into the future
    # never fills the buffer and forces the watermark past the IMU (0: no bound)
    max_buffered_aiding: int = 2_000
    # the GNSS integrity gate (hil.fusion.gnss_gate): NIS bound per test, 0 = off
    gnss_gate_chi2: float = 36.0
    gnss_alarm_after_ns: int = 2_000_000_000  # rejections this long raise gnss_integrity_alarm
    gnss_reacquire_after_ns: int = 30_000_000_000  # and this long let fixes through again
    gnss_gate_reference: str = "ekf15"  # whose prediction decides for all ("": each its own)
    # a reacquired fix re-initialises the estimators that can (and a flagged IMU sample makes the
    # INS no witness until one has): hil.fusion.gnss_gate's rule 4; False: one fix let through
    gnss_reset: bool = True
    # ... and a flagged IMU sample does so only while GNSS is trusted (rule 4; False: recordings
    # before it, where a spoof under way at the fault was the reset's truth)
    gnss_reset_needs_trust: bool = True
    # ... and the free INS too, the open-loop filters (which correct it) starting again on that
    # fix (rule 4; False: recordings before it, whose free INS kept what the fault left)
    gnss_reset_free_ins: bool = True
    # ... levelling the tilt against the acceleration the GNSS velocity shows (a turn's, which
    # levelling on the specific force alone takes for a tilt) and, for the free INS, on the mean
    # specific force of the clean samples of the last RESET_LEVEL_WINDOW_NS (False: recordings
    # before it, levelled on a = 0 and on the last sample alone, whose quantization tilted it)
    gnss_reset_accel: bool = True
    # rule 4's fix after an IMU fault must continue the GNSS track before it (a spoof that began
    # inside the fault is held out, not taken for truth); False: recordings before it
    gnss_reset_checks_track: bool = True
    gnss_sigma_floor: bool = True  # a fix's σ never below the receiver model's
    # a publisher's GNSS fixes closer together than this share of the receiver's period are
    # refused at arrival ("rate" in the journal): a receiver cannot fix faster than it does,
    # and a flood of copies must not cost an estimator update each (0: no such rule)
    gnss_min_interval: float = 0.5
    # publish each estimator's horizon state carried to the newest IMU sample (hil.fusion.predictor);
    # False: publish the horizon's state when it is reached, lag_ns late (the fusion before it)
    output_predictor: bool = True
    # the compensation filters coast through a GNSS gap (hil.estimators.compensation); False: they
    # continue the last difference at its last rate (the fusion before the coasts)
    gnss_coast: bool = True
    # how ekf15 and the feedback INS are told the IMU's bias wander (hil.estimators.tuning's
    # BIAS_MODELS): the emulator's Gauss-Markov, or "instability", what recordings before it ran
    imu_bias_model: str = "gauss_markov"

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
            max_buffered_aiding=self.max_buffered_aiding,
            gnss_gate_chi2=self.gnss_gate_chi2,
            gnss_alarm_after_ns=self.gnss_alarm_after_ns,
            gnss_reacquire_after_ns=self.gnss_reacquire_after_ns,
            gnss_gate_reference=self.gnss_gate_reference,
            gnss_reset=self.gnss_reset,
            gnss_reset_needs_trust=self.gnss_reset_needs_trust,
            gnss_reset_free_ins=self.gnss_reset_free_ins,
            gnss_reset_accel=self.gnss_reset_accel,
            gnss_reset_checks_track=self.gnss_reset_checks_track,
            gnss_sigma_floor=self.gnss_sigma_floor,
            gnss_min_interval=self.gnss_min_interval,
            output_predictor=self.output_predictor,
            gnss_coast=self.gnss_coast,
            imu_bias_model=self.imu_bias_model,
        )

    def gate_settings(self) -> GateSettings:
        return GateSettings(
            chi2=self.gnss_gate_chi2,
            alarm_after_ns=self.gnss_alarm_after_ns,
            reacquire_after_ns=self.gnss_reacquire_after_ns,
            reference=self.gnss_gate_reference,
            floor_sigma=self.gnss_sigma_floor,
            reset=self.gnss_reset,
            reset_needs_trust=self.gnss_reset_needs_trust,
            reset_checks_track=self.gnss_reset_checks_track,
        )

    @classmethod
    def from_settings(cls, m: FusionSettings) -> FusionConfig:
        """The configuration a recording says the fusion ran with. A recording made before the
        feedback form and the calibration states has neither field: open loop, 15 states, which
        is what it ran."""
        tuples = ("estimators", "feedback")
        fields = {f: getattr(m, f) for f in cls.__dataclass_fields__ if f not in tuples}
        return cls(estimators=tuple(m.estimators), feedback=tuple(m.feedback), **fields)


_INF = math.inf


def implausible(msg: Measurement, cfg: FusionConfig) -> str:
    """Why an input cannot be a measurement ("" if it can): non-finite or absurd values."""
    if isinstance(msg, ImuSample):
        d, v, m, n = msg.dtheta_b_rad, msg.dvel_b_mps, cfg.max_dtheta_rad, cfg.max_dvel_mps
        if (  # the common case, unrolled: a chained comparison is False for NaN and, m finite, inf
            m < _INF and n < _INF and len(d) == 3 and len(v) == 3
            and -m <= d[0] <= m and -m <= d[1] <= m and -m <= d[2] <= m
            and -n <= v[0] <= n and -n <= v[1] <= n and -n <= v[2] <= n
        ):  # fmt: skip
            return ""
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
    if not all(math.isfinite(v) and 0.0 < v < MAX_GNSS_SIGMA for v in (*msg.pos_sigma_m, *msg.vel_sigma_mps)):
        return "sigma"
    return ""


_F64 = np.dtype(np.float64)
# ImuSample.status bits that say the increments are not the motion: GYRO_FAULT, ACCEL_FAULT,
# GYRO_SATURATED, ACCEL_SATURATED (hil.can.codec's bits 0-3)
IMU_FAULT_STATUS = 0b1111


#: A stream the output predictor carries: name, position, velocity, attitude (floats), the IMU
#: biases it removes (``b_g`` then ``b_a``, six floats; None: none) and the solution's σ
#: (position, velocity, attitude; None: none).
_Stream = tuple[str, Sequence[float], Sequence[float], Sequence[float], Any, Any]
_NO_SIGMA = (None, None, None)


def _floats(a: Any) -> list[float]:
    """A float64 array (or any sequence of numbers) as a list of Python floats."""
    if type(a) is np.ndarray and a.dtype == _F64:
        out: list[float] = a.tolist()
        return out
    return [float(v) for v in a]


def handler_of(est: Any, sensor: str) -> Any:
    """``est``'s handler of ``sensor``: ``Estimator.handler``, or ``on_<sensor>`` of an object
    that keeps the contract without deriving from the base class."""
    if isinstance(est, Estimator):
        return est.handler(sensor)
    return getattr(est, f"on_{sensor}", None)


def block_step_of(est: Any) -> Callable[[ImuBlock], None]:
    """How ``est`` takes a block of IMU intervals: its ``on_imu_block``, or (an object keeping
    the contract without deriving from ``Estimator``) its ``on_imu`` of each in turn."""
    step = getattr(est, "on_imu_block", None)
    if step is not None:
        return step  # type: ignore[no-any-return]

    def each(block: ImuBlock) -> None:
        for imu, ins in zip(block.inputs(), block.ins, strict=True):
            est.on_imu(imu, ins)

    return each


# a relayed verdict's companion entry (``gate_relay``): the reference re-initialised on that fix
_RESET_MARK = "#reset"
# a reset after an IMU fault levels the free INS on the mean specific force of the clean samples
# of this long (the newest first; at most _CLEAN_ROWS_MAX of them: 0.1 s at 2 kHz)
RESET_LEVEL_WINDOW_NS = 100_000_000
_CLEAN_ROWS_MAX = 256
_RECENT_FIXES_MAX = 64  # more than RESET_ACCEL_SPAN_NS of a 20 Hz receiver's


def input_key(msg: Measurement) -> tuple[int, int, int]:
    """The total order: rig time of validity, then the sensor's rank, then seq."""
    return (msg.stamp_ns, rank_of(msg.sensor), msg.seq)


def input_id(msg: Measurement, source: str = "") -> str:
    """An input's name in the journal: ``sensor:seq``, and ``@publisher`` when it is known (the
    Zenoh source id, live), so a forged copy of ``gnss:42`` is not the rig's ``gnss:42``."""
    return f"{msg.sensor}:{msg.seq}@{source}" if source else f"{msg.sensor}:{msg.seq}"


def before_alignment(stamp_ns: int, align_ns: int) -> bool:
    """An input a fusion aligned at ``align_ns`` (a restarted one: ``realign_point``; 0 for a run
    from the start) never takes: valid before the state it starts from. The one rule for what it
    held (``FusionNode._realign``), what reaches it after (``FusionCore.push``: ``prealign``) and
    what ``hil rerun`` gives each life (whether such an input reached it live is chance)."""
    return stamp_ns < align_ns


def parse_journal_id(entry: str) -> tuple[str, str, str]:
    """``(why, "sensor:seq", publisher)`` of a ``dropped`` entry (``why`` "" when it has none, as
    in recordings made before reasons were given; publisher "" when it was not known)."""
    body, _, source = entry.partition("@")
    parts = body.split(":")
    if len(parts) >= 3:
        return parts[0], ":".join(parts[1:3]), source
    return "", body, source


BOUND_CLEAR_NS = 1_000_000_000  # a source beyond the latency bound is back after this long without a refusal
JOURNAL_MAX_ENTRIES = 1_000  # per journal message: a flood's decisions go out in several


@dataclass
class FusionCore:
    init: InitialState
    config: FusionConfig
    make_estimator: Callable[[str, InitialState], Estimator] | None = None
    counters: dict[str, int] = field(default_factory=dict)
    params: dict[str, dict[str, Any]] = field(default_factory=dict)  # per estimator, e.g. from tuning
    receiver: ReceiverModel | None = None  # the scenario's GNSS receiver: without it, no gate
    # a restarted fusion's re-alignment (``for_scenario``'s ``align_ns``; 0: none): an input valid
    # before it is older than the state the core starts from, and is refused (``prealign``)
    align_ns: int = 0

    @classmethod
    def for_scenario(cls, scenario: Any, config: FusionConfig, align_ns: int = 0) -> FusionCore:
        """The one way live, sim and rerun build the core: truth alignment, IMU-derived tuning.

        ``align_ns`` > 0 aligns from the truth at that rig time instead of at zero: what a fusion
        restarted mid-run does (services/fusion.py), the rig's equivalent of an in-flight
        re-alignment. Its outputs then differ from an uninterrupted run's, and say so in an event.
        """
        from hil.estimators.tuning import params_for
        from hil.nav.trajectory import truth_for

        imu = scenario.imu.params
        params = params_for(
            imu,
            scenario.gnss,
            gyro_cal=config.ekf_calibration.startswith("gyro"),
            accel_cal=config.ekf_calibration == "gyro+accel",
            feedback=config.feedback,
            bias_model=config.imu_bias_model,
        )
        if not config.gnss_coast:  # a recording made before the compensation filters' coasts
            for name in ("comp1", "comp2", "comp3", "comp3f", "compvs", "cf2", "cf3"):
                params[name] = params.get(name, {}) | {"gnss_coast": False}

        truth = truth_for(scenario)
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
        receiver = ReceiverModel.for_scenario(scenario)
        return cls(init, config, params=params, receiver=receiver, align_ns=max(0, align_ns))

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
        self._ests: list[Estimator] = []
        # the IMU intervals taken on the horizon and not yet stepped by the estimators: stepped
        # together when something reads them (``_step_estimators``), never more than IMU_BLOCK_MAX
        self._block = ImuBlock()
        for name in self.config.estimators:
            try:
                self._ests.append(maker(name, self.init))
            except Exception as err:  # one broken estimator must not take the others down
                self._inc(f"errors.estimator_init.{name}")
                self.last_error = f"estimator {name} could not start: {type(err).__name__}: {err}"
        # per sensor (other than the IMU, which every estimator takes): the estimators' handlers,
        # in estimator order, resolved once
        self._handlers: dict[str, list[tuple[str, Any]]] = {
            sensor: [(e.name, h) for e in self._ests if (h := handler_of(e, sensor)) is not None]
            for sensor in SENSOR_NAMES
            if not SENSORS[sensor].paces_fusion
        }
        self._block_steps = [(e.name, block_step_of(e)) for e in self._ests]
        # who re-initialises on a fix the gate reacquires (rule 4); the others take it as a fix
        self._resets: dict[str, Callable[..., None] | None] = {
            e.name: getattr(e, "reset_to_gnss", None) or self._restart_of(e) for e in self._ests
        }
        # those that re-initialise themselves, told the GNSS acceleration (``gnss_reset_accel``)
        self._resets_accel = {e.name for e in self._ests if getattr(e, "reset_to_gnss", None) is not None}
        self._pacer = {n for n in SENSOR_NAMES if SENSORS[n].paces_fusion}
        self._heap: list[tuple[tuple[int, int, int], int, Measurement, str]] = []
        # the aiding entries in the heap (arrival ids), and the furthest-ahead first, lazily
        self._aiding_live: set[int] = set()
        self._aiding_max: list[tuple[int, int, int, int, Measurement, str]] = []
        self._evicted: set[int] = set()
        self.gate: GnssGate | None = None
        cfg = self.config
        if self.receiver is not None and (cfg.gnss_gate_chi2 > 0 or cfg.gnss_sigma_floor):
            self.gate = GnssGate(cfg.gate_settings(), self.receiver)
        self._gated: list[str] = []
        # a split ``hil rerun`` (hil.record.rerun.split_estimators): the core that runs the gate's
        # reference keeps its verdicts by input (``gate_verdicts``, a dict), the core without it
        # takes them (``gate_relay``) in place of its own reference-less ones
        self.gate_verdicts: dict[str, bool | None] | None = None
        self.gate_relay: dict[str, bool | None] | None = None
        self._last_imu_ns = self.init.stamp_ns
        self._last_row: tuple[float, ...] | None = None  # the last IMU sample's (dt, Δθ, Δv)
        # the IMU samples since the last flagged one, newest last (stamp, row): the free INS's
        # reset levels on their mean specific force (``gnss_reset_accel``)
        self._clean_rows: deque[tuple[int, tuple[float, ...]]] = deque(maxlen=_CLEAN_ROWS_MAX)
        # the GNSS fixes taken in, (stamp, velocity), newest last: the velocity's rate at a reset
        self._recent_fixes: deque[tuple[int, Any, str]] = deque(maxlen=_RECENT_FIXES_MAX)
        # the stamp of each GNSS publisher's last fix taken in (the rate rule)
        self._gnss_min_gap_ns = 0
        if self.receiver is not None and cfg.gnss_min_interval > 0:
            self._gnss_min_gap_ns = round(cfg.gnss_min_interval * self.receiver.period_ns)
        self._last_fix_ns: dict[str, int] = {}
        self._arrivals = 0  # tie-break for identical keys: first arrival first, never compare messages
        self._future_lead_ns: int | None = None
        self._future_run = 0
        self._newest_ns: int | None = None
        self._newest_key: tuple[int, int, int] | None = None
        self._last_key: tuple[int, int, int] = (-(2**62), -1, -1)
        self._dropped: list[str] = []
        self._unpredicted: list[str] = []  # IMU samples the horizon took and the predictor did not
        self._out_seq: dict[str, int] = {}
        self._last_imu_seq = -1
        self._last_gnss_seq = -1
        self.consumed = 0
        # the output predictor (None: the horizon's state is published), the horizon released
        # so far (an input at or before it is late), the sources now beyond the bound, and the
        # latency events not yet taken
        self.predictor: OutputPredictor | None = None
        self._ins_nav: NavState | None = None  # the free INS at the horizon, as estimators saw it
        if cfg.output_predictor:
            g = self._sd._gravity(self.init.lat_rad, self.init.alt_m)
            self.predictor = OutputPredictor(self.init.stamp_ns, g)
        self._horizon_ns = -(2**62)
        self._over_bound: set[str] = set()
        self._latency_events: list[Transition] = []
        self._latency_max_ns: dict[str, int] = {}
        self._last_refused_ns: dict[str, int] = {}

    def _restart_of(self, est: Estimator) -> Callable[[Any], None] | None:
        """How an estimator that corrects the free INS starts again on the fix that re-initialised
        it (``gnss_reset_free_ins``): given the fix and the new free INS."""
        restart = getattr(est, "restart_on_gnss", None) if self.config.gnss_reset_free_ins else None
        if restart is None:
            return None
        return lambda gnss: restart(gnss, self._ins_nav)

    def _level_force(self) -> tuple[float, float, float] | None:
        """The mean specific force of the clean IMU samples of the last ``RESET_LEVEL_WINDOW_NS``
        (None: none since the fault). One sample's is its quantization too: an accelerometer
        step of a tactical IMU at 400 Hz (0.24 m/s²) is 24 mrad of tilt."""
        rows = self._clean_rows
        if not rows:
            return None
        since = rows[-1][0] - RESET_LEVEL_WINDOW_NS
        dt = dx = dy = dz = 0.0
        for stamp_ns, row in reversed(rows):
            if stamp_ns < since:
                break
            dt += row[0]
            dx += row[4]
            dy += row[5]
            dz += row[6]
        return (dx / dt, dy / dt, dz / dt) if dt > 0.0 else None

    def _reset_free_ins(self, gnss: Any, accel: tuple[float, float, float] | None = None) -> None:
        """The free INS re-initialised on a fix the gate reacquired (rule 4, after an IMU fault):
        position and velocity from the fix (carried to the last IMU sample), tilt levelled from
        that sample's specific force, heading from the ground track (ekf15's reset does the same;
        ``hil.nav.attitude.levelled_attitude``). The fault left it tens of degrees off, which no
        filter correcting it can pull back."""
        f_b = self._level_force() if self.config.gnss_reset_accel else None
        if f_b is None:
            row = self._last_row  # None before the first IMU sample: the body level, at rest
            f_b = (0.0, 0.0, -G0_MPS2) if row is None else (row[4] / row[0], row[5] / row[0], row[6] / row[0])
        old = self._sd.StrapdownState.of(self._ins)
        q, _tracked = levelled_attitude(f_b, gnss.vel_ned_mps, old.q, accel_ned=accel)
        lag_s = (self._last_imu_ns - gnss.stamp_ns) * 1e-9
        pos = [float(p) + float(v) * lag_s for p, v in zip(gnss.pos_ned_m, gnss.vel_ned_mps, strict=True)]
        lat, lon, alt = ned_to_lla_one(pos[0], pos[1], pos[2], *self._origin)
        vel = [float(v) for v in gnss.vel_ned_mps]
        self._ins = self._sd.StrapdownState(lat, lon, alt, vel, q.tolist(), old[10:13], old[13:16])
        self._ins_nav = self._sd.LazyNavState(self._ins, self._origin)
        self._inc("gnss_gate.reset.ins")

    @property
    def estimators(self) -> list[Estimator]:
        """The estimators, their IMU steps taken up to the horizon (what a caller reads of them)."""
        self._step_estimators()
        return self._ests

    def _step_estimators(self) -> None:
        """Hand the deferred IMU intervals to every running estimator, in one call each.

        Deferring changes no bits: each estimator still takes every interval in order before
        anything reads it (a solution, an aiding input, health), and the estimators share no
        state (the free INS is stepped at once, each interval's copy kept in the block)."""
        block = self._block
        if not len(block):
            return
        self._block = ImuBlock()
        for name, step in self._block_steps:
            if name in self._failed:
                continue
            try:
                step(block)
            except Exception as err:
                self._fail(name, err)

    # -- arrival side (live) ---------------------------------------------------------------
    def push(self, msg: Measurement, source: str = "") -> list[NavSolution]:
        """An input as it arrived (``source``: its publisher, "" offline); the solutions its
        arrival released."""
        key = input_key(msg)
        why = implausible(msg, self.config)
        if why:
            self._inc(f"rejected.implausible.{msg.sensor}.{why}")
            self._dropped.append("implausible:" + input_id(msg, source))
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
                self._dropped.append("future:" + input_id(msg, source))
                return []
            self._inc("input_gaps")
            self._newest_ns = msg.stamp_ns
        self._future_lead_ns, self._future_run = None, 0
        if before_alignment(msg.stamp_ns, self.align_ns):
            # A restarted fusion keeps nothing from before its re-alignment: not what it held
            # (``FusionNode._realign``), nor what reaches it after -- a fix published before its
            # subscription to the fixes took effect is never received, one published just after
            # is, and only this refusal (journaled, as rerun reads it) makes the two alike.
            self._inc(f"dropped_before_alignment.{msg.sensor}")
            self._dropped.append("prealign:" + input_id(msg, source))
            return []
        pacer = msg.sensor in self._pacer
        late = msg.stamp_ns <= self._horizon_ns if self.predictor is not None else key <= self._last_key
        if late:
            self._inc(f"dropped_late.{msg.sensor}")
            self._dropped.append("late:" + input_id(msg, source))
            self._beyond_bound(msg, source)
            return []
        predicted = True
        if self.predictor is not None and pacer and self._newest_key is not None and key <= self._newest_key:
            # behind a newer IMU sample (a time sync step, say): the predictor has integrated past
            # it, the horizon has not. A copy of one it holds is a duplicate.
            same = self.predictor.seq_at(msg.stamp_ns)
            if same is not None:
                why = "dup" if same == msg.seq else "order"
                self._inc(f"dropped_{'duplicate' if why == 'dup' else why}.{msg.sensor}")
                self._dropped.append(f"{why}:" + input_id(msg, source))
                return []
            predicted = False
            self._inc(f"unpredicted.{msg.sensor}")
            self._unpredicted.append(input_id(msg, source))
        if self._gnss_min_gap_ns and msg.sensor == "gnss" and self._too_soon(msg.stamp_ns, source):
            self._inc("rejected.gnss_rate")
            self._dropped.append("rate:" + input_id(msg, source))
            return []
        if not pacer:
            self._within_bound(msg, source)
        return self._accept(msg, source, key, predicted)

    def replay(self, msg: Measurement, source: str = "", predicted: bool = True) -> list[NavSolution]:
        """An input the live fusion accepted, in the total order (``hil rerun``): the same path
        as ``push`` after its admission rules, whose refusals the journal names, as are the IMU
        samples the output predictor did not take (``predicted`` False)."""
        if self.predictor is None:
            return self.process(msg, source)
        return self._accept(msg, source, input_key(msg), predicted)

    def _accept(
        self, msg: Measurement, source: str, key: tuple[int, int, int], predicted: bool = True
    ) -> list[NavSolution]:
        """An admitted input: buffered, the horizon moved if it is an IMU sample, and (with the
        predictor, unless it came behind a newer sample) the solutions at that sample."""
        arrival = self._arrivals
        heapq.heappush(self._heap, (key, arrival, msg, source))
        self._arrivals += 1
        # The IMU is the fusion's clock: only its progress moves the watermark, so a GNSS fix that
        # arrives before the IMU samples around its time of validity waits for them.
        pacer = msg.sensor in self._pacer
        if pacer:
            if self._newest_ns is None or msg.stamp_ns > self._newest_ns:
                self._newest_ns = msg.stamp_ns
            if self._newest_key is None or key > self._newest_key:
                self._newest_key = key
        elif self.config.max_buffered_aiding > 0:
            self._hold_aiding(key, arrival, msg, source)
        if self._newest_ns is None:
            return []
        if len(self._heap) - len(self._evicted) > self.config.max_buffered:
            self._inc("released_on_overflow")
            out = self._release(self._heap[0][0][0])
        else:
            out = self._release(self._newest_ns - self.config.lag_ns)
        if self.predictor is not None and pacer and predicted:
            out.extend(self._predicted(msg))  # type: ignore[arg-type]
        return out

    def _beyond_bound(self, msg: Measurement, source: str) -> None:
        """A source's input refused as older than the horizon: an event when the source crosses
        the bound (not for each input)."""
        if self._newest_ns is None:
            return
        self._last_refused_ns[msg.sensor] = self._newest_ns
        if msg.sensor in self._over_bound:
            return
        self._over_bound.add(msg.sensor)
        self._inc(f"latency_over_bound.{msg.sensor}")
        late_s = (self._newest_ns - msg.stamp_ns) / 1e9
        detail = (
            f"{input_id(msg, source)} arrived {late_s:.3f} s after its time of validity, behind the "
            f"fusion horizon ({self.config.lag_s:g} s behind the newest IMU sample): refused; raise "
            f"the fusion's lag_s to fuse this source"
        )
        self._latency_events.append(Transition("latency_over_bound", msg.sensor, self._newest_ns, detail))

    def _within_bound(self, msg: Measurement, source: str) -> None:
        """An aiding input taken in: its latency (how far behind the newest IMU sample it came)
        for the status, and the event when its source is back within the bound (none of its
        inputs refused for ``BOUND_CLEAR_NS``: a latency wavering about the bound is one
        episode, not an event per input)."""
        if self._newest_ns is None:
            return
        late = self._newest_ns - msg.stamp_ns
        if late > self._latency_max_ns.get(msg.sensor, -(2**62)):
            self._latency_max_ns[msg.sensor] = late
        refused = self._last_refused_ns.get(msg.sensor, -(2**62))
        if msg.sensor in self._over_bound and self._newest_ns - refused >= BOUND_CLEAR_NS:
            self._over_bound.discard(msg.sensor)
            detail = f"{input_id(msg, source)} arrived {late / 1e9:.3f} s after its time of validity: fused"
            event = Transition("latency_within_bound", msg.sensor, self._newest_ns, detail)
            self._latency_events.append(event)

    def take_latency_events(self) -> list[Transition]:
        """Sources that crossed the latency bound (either way) since the last call."""
        out, self._latency_events = self._latency_events, []
        return out

    def _predicted(self, msg: ImuSample) -> list[NavSolution]:
        """The newest IMU sample into the predictor, and at every ``output_every``-th the
        solutions there: each horizon state carried forward by the IMU's motion since."""
        pred = self.predictor
        assert pred is not None
        d, v = msg.dtheta_b_rad, msg.dvel_b_mps
        pred.step(msg.stamp_ns, (d[0], d[1], d[2]), (v[0], v[1], v[2]), msg.dt_ns * 1e-9, msg.seq)
        if msg.seq % self.config.output_every:
            return []
        ins_nav = self._ins_nav
        if ins_nav is None:  # no IMU step on the horizon yet: the initial state
            ins_nav = self._ins_nav = self._sd.LazyNavState(self._ins, self._origin)
        self._step_estimators()  # (the free INS's output does not depend on the estimators)
        # every stream's horizon state: (name, position, velocity, attitude, biases, sigmas)
        streams: list[_Stream] = [(FREE_INS, *ins_nav.floats(), None, None)]
        for est in self._ests:
            if est.name in self._failed:
                continue
            try:
                nav = est.solution()
                sig = (nav.pos_sigma_m, nav.vel_sigma_mps, nav.att_sigma_rad)
                streams.append((est.name, *nav_floats(nav), imu_bias_floats_of(est), sig))
            except ArithmeticError:
                self._inc(f"errors.nonfinite.{est.name}")
        return self._carried(streams, pred.motion(), msg)

    def _carried(self, streams: list[_Stream], motion: Motion, msg: ImuSample) -> list[NavSolution]:
        """Each stream carried to the newest sample and published: their arithmetic in one call
        (``carry_rows``, compiled), or one by one as ``predict_floats`` and ``_publish`` where a
        stream's numbers make it raise (a state gone non-finite: that one counted)."""
        pred = self.predictor
        assert pred is not None
        rows = [(*p, *v, *q, 0.0 if b is None else 1.0, *(b or NO_BIAS)) for _, p, v, q, b, _ in streams]
        dt, dq, dv, dp = motion
        (o0, o1, o2), c = _origin_floats(*self._origin)
        table: list[list[float]] | None
        try:
            table = carry_rows(
                np.array(rows), dt, *dq, *dv, *dp, pred.g, o0, o1, o2, *c[0], *c[1], *c[2]
            ).tolist()
        except ArithmeticError:
            table = None
        out: list[NavSolution] = []
        for i, (name, pos, vel, q, bias, sig) in enumerate(streams):
            try:
                if table is None:
                    pos, vel, q = pred.predict_floats(pos, vel, q, motion, bias)
                    out.append(self._publish(name, pos, vel, q, *(sig or _NO_SIGMA), msg.stamp_ns, msg.seq))
                    continue
                t = table[i]
                if t[13] == 0.0:
                    raise ArithmeticError(f"{name}: non-finite solution")
                ps, vs, at = self._sigma_lists(name, *(sig or _NO_SIGMA))
                out.append(
                    self._message(name, t[0:3], t[3:6], t[6:10], t[10:13], ps, vs, at, msg.stamp_ns, msg.seq)
                )
            except ArithmeticError:
                self._inc(f"errors.nonfinite.{name}")
        return out

    def _too_soon(self, stamp_ns: int, source: str) -> bool:
        """A fix of this publisher within the rate rule's gap of its last one taken in."""
        last = self._last_fix_ns.get(source)
        if last is not None and abs(stamp_ns - last) < self._gnss_min_gap_ns:
            return True
        if last is not None or len(self._last_fix_ns) < 1024:  # bounded whatever a flood names
            self._last_fix_ns[source] = stamp_ns
        return False

    def _hold_aiding(self, key: tuple[int, int, int], arrival: int, msg: Measurement, source: str) -> None:
        """Bound the aiding inputs held: past ``max_buffered_aiding`` the one furthest ahead in
        the total order (junk stamped into the future first) is evicted and journaled."""
        self._aiding_live.add(arrival)
        heapq.heappush(self._aiding_max, (-key[0], -key[1], -key[2], -arrival, msg, source))
        while len(self._aiding_live) > self.config.max_buffered_aiding:
            *_, neg_arrival, old, old_source = heapq.heappop(self._aiding_max)
            if -neg_arrival in self._aiding_live:
                self._aiding_live.discard(-neg_arrival)
                self._evicted.add(-neg_arrival)
                self._inc(f"dropped_overflow.{old.sensor}")
                self._dropped.append("overflow:" + input_id(old, old_source))
        if len(self._aiding_max) > 2 * len(self._aiding_live) + 1024:  # drop released entries
            self._aiding_max = [e for e in self._aiding_max if -e[3] in self._aiding_live]
            heapq.heapify(self._aiding_max)

    def note_dropped(self, msg: Measurement, source: str = "", why: str = "inbox") -> None:
        """An input the service dropped before it reached the core (``inbox``: its bounded inbox;
        ``held``: a restarted fusion's full list of inputs held for its re-alignment): journaled,
        so ``hil rerun`` leaves out what the live core never saw."""
        self._inc(f"dropped_{why}.{msg.sensor}")
        self._dropped.append(f"{why}:" + input_id(msg, source))

    def flush(self) -> list[NavSolution]:
        """End of input: release everything still buffered."""
        out = self._release(2**62)
        self._step_estimators()
        return out

    def journal(self, seq: int, stamp_ns: int) -> FusionJournal:
        """What was decided since the last journal: the live service and hil sim publish this."""
        return FusionJournal(
            seq=seq,
            stamp_ns=stamp_ns,
            watermark_ns=self.watermark_ns,
            consumed=self.consumed,
            dropped=self.take_dropped(),
            gated=self.take_gated(),
            unpredicted=self.take_unpredicted(),
        )

    def journals(self, seqs: Callable[[], int], stamp_ns: int) -> list[FusionJournal]:
        """``journal`` cut into messages of at most ``JOURNAL_MAX_ENTRIES`` names each (a flood
        is thousands a second; one message stays far below the bus's payload limit)."""
        dropped, gated, unpredicted = self.take_dropped(), self.take_gated(), self.take_unpredicted()
        n = JOURNAL_MAX_ENTRIES
        out: list[FusionJournal] = []
        while True:
            take_d, dropped = dropped[:n], dropped[n:]
            room = n - len(take_d)
            take_u, unpredicted = unpredicted[:room], unpredicted[room:]
            room -= len(take_u)
            take_g, gated = gated[:room], gated[room:]
            out.append(
                FusionJournal(
                    seq=seqs(),
                    stamp_ns=stamp_ns,
                    watermark_ns=self.watermark_ns,
                    consumed=self.consumed,
                    dropped=take_d,
                    gated=take_g,
                    unpredicted=take_u,
                )
            )
            if not dropped and not gated and not unpredicted:
                return out

    def take_dropped(self) -> list[str]:
        out, self._dropped = self._dropped, []
        return out

    def take_gated(self) -> list[str]:
        out, self._gated = self._gated, []
        return out

    def take_unpredicted(self) -> list[str]:
        out, self._unpredicted = self._unpredicted, []
        return out

    @property
    def watermark_ns(self) -> int:
        return self._last_key[0]

    def _release(self, watermark_ns: int) -> list[NavSolution]:
        out: list[NavSolution] = []
        # everything at or before the watermark has now been taken: a later arrival stamped
        # there is late (outputs already went out without it, so it must not be fused after)
        self._horizon_ns = max(self._horizon_ns, watermark_ns)
        while self._heap and self._heap[0][0][0] <= watermark_ns:
            key, arrival, msg, source = heapq.heappop(self._heap)
            if arrival in self._evicted:
                self._evicted.discard(arrival)
                continue
            self._aiding_live.discard(arrival)
            if key == self._last_key:  # a duplicate that was buffered twice
                self._inc(f"dropped_duplicate.{msg.sensor}")
                self._dropped.append("dup:" + input_id(msg, source))
                continue
            self._last_key = key
            out.extend(self.process(msg, source))
        return out

    # -- processing side (live after release, and rerun) -----------------------------------
    def process(self, msg: Measurement, source: str = "") -> list[NavSolution]:
        """Consume one input in total order; return the solutions it produced."""
        self.consumed += 1
        if isinstance(msg, ImuSample):
            return self._on_imu(msg)
        self._on_measurement(msg, source)
        return []

    def _on_imu(self, msg: ImuSample) -> list[NavSolution]:
        if self.predictor is not None:
            self.predictor.horizon_at(msg.stamp_ns)
        dt_s = msg.dt_ns * 1e-9
        d, v = msg.dtheta_b_rad, msg.dvel_b_mps
        row = (dt_s, float(d[0]), float(d[1]), float(d[2]), float(v[0]), float(v[1]), float(v[2]))
        self._ins = self._sd.strapdown_step_f(self._ins, *row[1:], dt_s)
        self._last_row = row
        self._last_imu_ns = msg.stamp_ns
        if msg.status & IMU_FAULT_STATUS:
            self._clean_rows.clear()
            if self.gate is not None:
                self.gate.note_imu_fault(msg.stamp_ns)
        else:
            self._clean_rows.append((msg.stamp_ns, row))
        # built lazily: most estimators read the free INS at a fix or an output only
        ins_nav = self._ins_nav = self._sd.LazyNavState(self._ins, self._origin)
        block = self._block
        block.append(msg.stamp_ns, row, ins_nav)
        if len(block) >= IMU_BLOCK_MAX:
            self._step_estimators()
        self._last_imu_seq = msg.seq
        if self.predictor is not None or msg.seq % self.config.output_every:
            return []
        self._step_estimators()
        out: list[NavSolution] = []
        for name, get in [(FREE_INS, lambda: ins_nav)] + [
            (e.name, e.solution) for e in self._ests if e.name not in self._failed
        ]:
            try:
                out.append(self._solution(name, get(), msg.stamp_ns))
            except ArithmeticError:
                # NaN never reaches a published solution: counted, not published
                self._inc(f"errors.nonfinite.{name}")
        return out

    def _on_measurement(self, msg: Measurement, source: str = "") -> None:
        """An aiding measurement at its time of validity, to every estimator that takes its kind
        (a GNSS fix: with its σ floored, to those the integrity gate lets have it)."""
        convert = INPUTS.get(msg.sensor)
        data = convert(msg) if convert is not None else msg
        if data is None:
            self._inc(f"{msg.sensor}.unusable")
            return
        self._step_estimators()
        handlers = [(n, h) for n, h in self._handlers.get(msg.sensor, ()) if n not in self._failed]
        allowed: dict[str, bool] = {}
        if msg.sensor == "gnss" and self.gate is not None and handlers:
            data, allowed = self._gate(data, [n for n, _ in handlers], msg, source)
        if handlers:
            ins_nav = self._ins_nav
            if ins_nav is None:  # no IMU step yet: the initial state
                ins_nav = self._ins_nav = self._sd.LazyNavState(self._ins, self._origin)
            reset = self.gate.reset if self.gate is not None and msg.sensor == "gnss" else ()
            accel = self._gnss_accel(data, source) if reset and self.config.gnss_reset_accel else None
            if reset and self.config.gnss_reset_free_ins:
                self._reset_free_ins(data, accel)
                ins_nav = self._ins_nav
            for name, handle in handlers:
                if name in self._failed or not allowed.get(name, True):
                    continue
                try:
                    if name in reset and self._resets.get(name) is not None:
                        if accel is not None and name in self._resets_accel:
                            self._resets[name](data, accel_ned=accel)
                        else:
                            self._resets[name](data)
                        self._inc(f"gnss_gate.reset.{name}")
                        continue
                    handle(data, ins_nav)
                except Exception as err:
                    self._fail(name, err)
        if msg.sensor == "gnss":
            self._last_gnss_seq = msg.seq
            self._recent_fixes.append((data.stamp_ns, data.vel_ned_mps, source))

    def _gnss_accel(self, fix: Any, source: str = "") -> tuple[float, float, float] | None:
        """The acceleration the GNSS velocity shows at ``fix`` and over the ``RESET_ACCEL_SPAN_NS``
        before it, or one and a half receiver periods where that is longer (``velocity_rate``;
        None: levelled on a = 0). The receiver's velocity is not the
        IMU's to doubt after an IMU fault."""
        # at least the fix before it: a 1 Hz receiver's last second holds one fix
        period = self.receiver.period_ns if self.receiver is not None else 0
        since = fix.stamp_ns - max(RESET_ACCEL_SPAN_NS, 3 * period // 2)
        # the reset fix's publisher's alone: a stranger's velocities beside it are no witness
        fixes = [(t, v) for t, v, src in self._recent_fixes if since <= t < fix.stamp_ns and src == source]
        fixes.append((fix.stamp_ns, fix.vel_ned_mps))
        # at the middle of the samples the free INS levels on
        return velocity_rate(fixes, fix.vel_sigma_mps, self._last_imu_ns - RESET_LEVEL_WINDOW_NS // 2)

    def _gate(
        self, data: Any, names: list[str], msg: Measurement, source: str
    ) -> tuple[Any, dict[str, bool]]:
        """The integrity gate's σ floor and verdicts; rejections counted and journaled."""
        gate = self.gate
        assert gate is not None
        floored = gate.floor(data)
        if floored is not data:
            self._inc("gnss.sigma_floored")
        if not gate.enabled:
            return floored, {}
        by_name = {e.name: e for e in self._ests}

        def solution(name: str) -> NavState | None:
            try:
                return by_name[name].solution()
            except Exception as err:  # a solution that cannot be had is a failed estimator
                self._fail(name, err)
                return None

        n_transitions = len(gate.transitions)
        relay, kept = self.gate_relay, self.gate_verdicts
        key = "" if relay is None and kept is None else input_id(msg, source)
        # none relayed for this fix: the reference core had no estimator left to take it, so
        # the reference had failed, and each decides on its own (as it did there)
        relayed = None if relay is None else (relay.pop(key, None), bool(relay.pop(key + _RESET_MARK, False)))
        allowed = gate.verdicts(floored, names, solution, self._last_imu_ns, source, relayed)
        if kept is not None:
            kept[key] = gate.reference_ok
            if gate.reset and gate.reference_ok is not None:  # the reference re-initialised on it
                kept[key + _RESET_MARK] = True
        for t in gate.transitions[n_transitions:]:
            self._inc(f"gnss_gate.{t.kind.removeprefix('gnss_integrity_')}")
        refused = [n for n in names if not allowed.get(n, True)]
        for n in refused:
            self._inc(f"gnss_gate.rejected.{n}")
        if refused:
            name_in_journal = input_id(msg, source)
            whole = len(refused) == len(names)
            self._gated.extend([name_in_journal] if whole else [f"{name_in_journal}>{n}" for n in refused])
        return floored, allowed

    def _fail(self, name: str, err: Exception) -> None:
        """An estimator that raises is taken out (and says so); the others go on."""
        self._failed.add(name)
        self._inc(f"errors.estimator_failed.{name}")
        self.last_error = f"estimator {name} failed: {type(err).__name__}: {err}"

    def _solution(self, name: str, nav: NavState, stamp_ns: int, imu_seq: int | None = None) -> NavSolution:
        pos, vel, q = nav_floats(nav)
        sig = (nav.pos_sigma_m, nav.vel_sigma_mps, nav.att_sigma_rad)
        return self._publish(name, pos, vel, q, *sig, stamp_ns, imu_seq)

    def _publish(
        self,
        name: str,
        pos: Sequence[float],
        vel: Sequence[float],
        q: Sequence[float],
        pos_sigma: Any,
        vel_sigma: Any,
        att_sigma: Any,
        stamp_ns: int,
        imu_seq: int | None = None,
    ) -> NavSolution:
        """The solution message of ``name``'s state (Python floats; sigmas arrays or None)."""
        for part in (pos, vel, q):
            for v in part:
                if not isfinite(v):
                    raise ArithmeticError(f"{name}: non-finite solution")
        ps, vs, at = self._sigma_lists(name, pos_sigma, vel_sigma, att_sigma)
        lla = ned_to_lla_one(pos[0], pos[1], pos[2], *self._origin)
        return self._message(name, list(pos), list(vel), list(q), lla, ps, vs, at, stamp_ns, imu_seq)

    @staticmethod
    def _sigma_lists(name: str, *sigmas: Any) -> tuple[list[float], list[float], list[float]]:
        """The σ of a solution as lists of floats ([] for None), all finite (else ArithmeticError)."""
        ps, vs, at = [[] if s is None else _floats(s) for s in sigmas]
        for part in (ps, vs, at):
            for v in part:
                if not isfinite(v):
                    raise ArithmeticError(f"{name}: non-finite solution")
        return ps, vs, at

    def _message(
        self,
        name: str,
        pos: list[float],
        vel: list[float],
        q: list[float],
        lla: Sequence[float],
        ps: list[float],
        vs: list[float],
        at: list[float],
        stamp_ns: int,
        imu_seq: int | None,
    ) -> NavSolution:
        """A finite solution as the message, numbered in ``name``'s stream."""
        seq = self._out_seq.get(name, 0)
        self._out_seq[name] = seq + 1
        return NavSolution(
            seq=seq,
            stamp_ns=stamp_ns,
            estimator=name,
            pos_ned_m=pos,
            vel_ned_mps=vel,
            q_nb=q,
            lat_deg=degrees(lla[0]),  # numpy's degrees is the same product by 180/π
            lon_deg=degrees(lla[1]),
            alt_m=lla[2],
            pos_sigma_m=ps,
            vel_sigma_mps=vs,
            att_sigma_rad=at,
            imu_seq=self._last_imu_seq if imu_seq is None else imu_seq,
            gnss_seq=self._last_gnss_seq,
        )

    def status_counters(self) -> dict[str, int]:
        """What the status topic counts: rejections, drops, the buffer, inputs consumed."""
        self._step_estimators()  # an estimator that fails on a deferred interval is counted now
        out = dict(self.counters)
        out["buffered"] = len(self._heap) - len(self._evicted)
        out["buffered_aiding"] = len(self._aiding_live)
        out["consumed"] = self.consumed
        out["horizon_lag_ms"] = round(self.config.lag_ns / 1e6)  # the latency bound
        for sensor, late in self._latency_max_ns.items():
            out[f"latency_max_ms.{sensor}"] = round(late / 1e6)
        return out

    def take_gate_events(self) -> list[Transition]:
        """Integrity alarms raised or cleared since the last call (the node publishes them)."""
        return self.gate.take_transitions() if self.gate is not None else []

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
                continue
            if self.gate is not None and self.gate.enabled:
                out[est.name].update(self.gate.health(est.name))
        return out

    def _inc(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1
