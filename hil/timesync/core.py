"""Time-tag synchronisation core: device clock -> rig clock, per sensor. Pure: no I/O, no clock.

The mapping is ``rig = device + offset + drift * (device - ref)`` (``ClockMapping``). Each sensor
has one of three sources (``SyncConfig.source``):

``timetag``  a 2-state Kalman filter (offset, drift) on time-tag pairs (edge on the device clock,
             rig latch minus the calibrated tag latency), with an innovation gate. Until the
             first tag the arrival estimate stands in.
``arrival``  no tags: a one-way-delay lower bound (TICSync's convex hull). Arrival minus device
             stamp is ``offset + delay``, delay >= its minimum, so the lower convex hull of those
             points over a sliding window is the mapping plus the minimum delay; the hull edge
             that spans the window's middle gives offset and drift, and the known minimum delay
             (``min_delay_ns``, like PX4's ``EKF2_GPS_DELAY``) is taken off.
``off``      no synchronisation: a measurement keeps its raw arrival stamp (the "sync off"
             baseline of the navigation comparison).

The arrival hull runs for every sensor, also with tags. Without tags (and before the first tag,
or while a step is being recovered) its residuals watch for clock steps:
A device step of Δ moves every later point by -Δ: a forward step puts points *below* the lower
bound (impossible for a one-way delay: declared after ``step_confirm`` such points in a row), a
backward step lifts the floor (declared when every residual over ``step_window_ns`` -- longer
than any plausible transport stall -- is above what jitter of the observed scale explains).
Measurements whose residual is suspicious are *held* (FIFO) until the question is settled, so
samples around a step are re-stamped with the mapping that fits them, never with the stale one.
After a step the hull restarts on the new points, the Kalman filter re-initialises on the next
tag (its drift kept), and the state reads ``step_recovering`` until then.

With tags ruling (source ``timetag``, filter initialised, not recovering) arrivals alone never
declare a step: arrival minus device time is offset *plus transport delay*, so a lifted or lowered
delay floor (a slow gateway, a congested bus: the ``can_latency`` fault) reads exactly like a
device step, while a tag measures the device clock itself. There the arrival residual is taken
against the tag mapping plus the learned minimum delay, and a run of suspicious residuals (the
same tests as above) is only a *suspicion*: a step is declared when a tag innovation outside the
gate agrees with it (whichever comes first), or by the filter's own two consistent outliers.
A tag that fits dismisses the suspicion. Nothing is held: the stamp comes from the tag mapping,
which added transport delay does not move, and holding until the next tag (1 s for the IMU) would
outlast what the fusion accepts (its 0.5 s horizon). The price of a real step is the samples
between it and the confirming tag (at most one tag period), stamped with the old mapping.

Start-up hold (``hold_until_locked_ns``, set for the IMU): before the tag filter has locked (three
tags) the clock's rate is not known, and an IMU sample's interval on the rig clock needs it (a
20 ppm crystal integrated at rate 1 for the first two seconds leaves 40 µs of time in the INS for
good, a 100 ppm one 200 µs: 2e-6 of a minute's run). So at start the sensor's measurements are
held until lock, at most that long of device time, and released together under the locked
mapping: the fusion, paced by the IMU, starts ~2 s later and every interval it integrates has the
rate. Only at start: after a clock step the stamps come from the tag mapping at once (above).
The step watch runs during the hold as after it; a step it declares closes a clock *epoch*, and at
the release each held measurement is stamped with the mapping of its own epoch (the one taken
before the step: that epoch's last mapping; the run of arrivals that proved the step: the new
one), never the new clock's mapping applied to the old clock's samples (100 s into the future
for a -100 s step: the fusion, paced by them, then refused every correct input). The bound is
held device time summed over the epochs, suspicious arrivals not counted (device time jumps at a
step), with twice that in rig arrival time as the backstop. Intervals keep the current rate: a
step resets the counter, not the oscillator.

Why a hull and a Kalman filter, not one filter: tags carry a small, symmetric latch noise, for
which least squares (the KF) is optimal; arrivals carry a one-sided, heavy-tailed delay, for
which the minimum (the hull) is the efficient estimator and a mean would be biased by the mean
delay.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Generic, TypeVar

T = TypeVar("T")

SOURCES = ("timetag", "arrival", "off")

# A held measurement waits for the step watch's verdict, but not while its sensor is silent: once
# an input of the sensor comes stamped more than this after the last measurement's arrival, what
# is held goes out first, under the mapping of then (``SensorSync.idle_release_due``). A rule on
# the sensor's own inputs, so a rerun that feeds them in order releases at the same place as the
# live service did; the service releases sooner, on its clock, once the rule is sure to hold
# (``hil.nodes.timesync``), for the fusion's sake (a held 1 Hz fix would wait a second).
IDLE_RELEASE_NS = 150_000_000


@dataclass(frozen=True)
class SyncConfig:
    """Per-sensor synchronisation settings (ns unless named otherwise)."""

    source: str = "timetag"  # "timetag" | "arrival" | "off"
    tag_latency_ns: int = 0  # calibrated mean edge -> latch delay of a time tag
    min_delay_ns: int = 0  # known minimum capture -> arrival delay of a measurement
    tag_sigma_ns: float = 10_000.0  # 1σ latch noise of a tag (KF measurement noise)
    drift_rw_ppb_per_sqrt_s: float = 50.0  # KF process noise: frequency random walk
    phase_noise_ns_per_sqrt_s: float = 200.0  # KF process noise: white frequency (phase walk)
    tag_gate_ns: int = 1_000_000  # a tag innovation beyond max(6σ, this) is an outlier
    hull_window_ns: int = 20_000_000_000  # arrival points kept for the hull
    hull_block_ns: int = 100_000_000  # one point (the minimum) per block of device time
    min_span_ns: int = 2_000_000_000  # hull drift is trusted once the window spans this
    step_window_ns: int = 500_000_000  # backward-step test: every residual this long is high
    step_confirm: int = 3  # forward-step test: this many impossible arrivals in a row
    step_floor_ns: int = 500_000  # smallest residual treated as a step indication
    max_drift_ppm: float = 500.0  # a hull slope beyond this is not a clock
    # > 0: at start, hold measurements until the tag filter is locked (3 tags), at most this long
    # (device time); for interval measurements, whose interval needs the clock's rate (see below)
    hold_until_locked_ns: int = 0

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"sync source {self.source!r} is not one of {SOURCES}")


@dataclass
class ClockMapping:
    """The published estimate: ``rig = device + offset + drift * (device - ref)``."""

    sensor: str
    source: str = "passthrough"
    offset_ns: int = 0
    drift_ppb: float = 0.0
    ref_device_ns: int = 0
    residual_rms_ns: float = 0.0
    n_samples: int = 0
    state: str = "converging"
    steps_detected: int = 0

    def to_rig(self, device_ns: int) -> int:
        return device_ns + self.offset_ns + round(self.drift_ppb * 1e-9 * (device_ns - self.ref_device_ns))

    def interval(self, device_ns: int, dt_ns: int) -> int:
        """The device interval ``dt_ns`` ending at ``device_ns``, on the rig clock: the mapping's
        rate applied (the offset cancels). Both ends through the one rounding ``to_rig`` uses, so
        consecutive intervals telescope: their sum is the rig span of the whole stream, with no
        rounding error that accumulates (a per-interval ``round(dt·rate)`` would carry up to
        0.5 ns per sample, 2e-7 of a 2.5 ms interval, all of one sign under a steady drift)."""
        return self.to_rig(device_ns) - self.to_rig(device_ns - dt_ns)


# ---------------------------------------------------------------------------------------------
# time tags: offset + drift Kalman filter


@dataclass
class TagFilter:
    """x = [θ (rig - device at ``ref``, ns), f (drift, ppb = ns/s)]; P its covariance.

    Predict over Δ s (device):  θ += f Δ;  Q = q_f [[Δ³/3, Δ²/2], [Δ²/2, Δ]] + q_θ [[Δ, 0], [0, 0]]
    Update with z = latch - tag_latency - device:  ν = z - θ;  S = P00 + R;  K = P[:,0] / S
    """

    cfg: SyncConfig
    ref_ns: int = 0
    theta_ns: float = 0.0
    f_ppb: float = 0.0
    p: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # P00, P01, P11
    n: int = 0
    outliers_in_row: int = 0
    last_outlier_nu: float = 0.0
    res_sq: deque[float] = field(default_factory=lambda: deque(maxlen=30))
    version: int = 0  # counts resets and updates: the mapping drawn from it is the same until it moves

    @property
    def initialised(self) -> bool:
        return self.n > 0

    def reset(self, f_ppb: float, f_sigma_ppb: float) -> None:
        self.version += 1
        self.n = 0
        self.f_ppb = f_ppb
        self.p = [0.0, 0.0, f_sigma_ppb**2]
        self.outliers_in_row = 0

    def _predict(self, device_ns: int) -> None:
        d = (device_ns - self.ref_ns) * 1e-9
        self.theta_ns += self.f_ppb * d
        self.ref_ns = device_ns
        ad = abs(d)
        qf = self.cfg.drift_rw_ppb_per_sqrt_s**2
        qt = self.cfg.phase_noise_ns_per_sqrt_s**2
        p00, p01, p11 = self.p
        p00 = p00 + 2 * d * p01 + d * d * p11 + qf * ad**3 / 3 + qt * ad
        p01 = p01 + d * p11 + qf * ad * ad / 2
        p11 = p11 + qf * ad
        self.p = [p00, p01, p11]

    def update(self, device_ns: int, z_ns: float) -> str:
        """One tag; returns ``"init"``, ``"ok"``, ``"outlier"`` or ``"step"``."""
        self.version += 1
        r = self.cfg.tag_sigma_ns**2
        if not self.initialised:
            self.ref_ns, self.theta_ns = device_ns, z_ns
            self.p = [r, 0.0, self.p[2]]
            self.n = 1
            return "init"
        self._predict(device_ns)
        p00, p01, p11 = self.p
        nu = z_ns - self.theta_ns
        s = p00 + r
        gate = max(6.0 * math.sqrt(s), float(self.cfg.tag_gate_ns))
        if abs(nu) > gate:
            # Two outliers in a row that agree with each other: the clock stepped.
            consistent = self.outliers_in_row > 0 and abs(nu - self.last_outlier_nu) < gate
            self.outliers_in_row += 1
            self.last_outlier_nu = nu
            if consistent:
                self.reset(self.f_ppb, math.sqrt(p11))
                self.update(device_ns, z_ns)
                return "step"
            return "outlier"
        self.outliers_in_row = 0
        k0, k1 = p00 / s, p01 / s
        self.theta_ns += k0 * nu
        self.f_ppb += k1 * nu
        # P = (I - K H) P
        self.p = [p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01]
        self.n += 1
        self.res_sq.append(nu * nu)
        return "ok"

    def mapping_terms(self) -> tuple[int, float, int]:
        return round(self.theta_ns), self.f_ppb, self.ref_ns


# ---------------------------------------------------------------------------------------------
# arrivals: one-way-delay lower bound


def _chain_push(hull: list[tuple[int, int]], p: tuple[int, int]) -> None:
    """One step of Andrew's monotone chain: ``p``, right of every point in ``hull``, joins the
    lower hull. The turn test (cross product of hull[-2] -> hull[-1] and hull[-2] -> p) is
    written out: it runs for every arrival block."""
    px, py = p
    while len(hull) >= 2:
        ox, oy = hull[-2]
        ax, ay = hull[-1]
        if (ax - ox) * (py - oy) - (ay - oy) * (px - ox) > 0:
            break
        hull.pop()
    hull.append(p)


def lower_hull(points: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Lower convex hull (Andrew's monotone chain) of points sorted by x."""
    hull: list[tuple[int, int]] = []
    for p in points:
        _chain_push(hull, p)
    return hull


class _SlidingLowerHull:
    """The lower hull of a window of points that come in increasing x and leave oldest first.

    A queue of two stacks: the newer points (``back``) keep Andrew's chain, built left to right
    as they come; the older ones (``front``) a chain built right to left when ``back`` is handed
    over, with a log of what each point's arrival popped, so the leftmost point leaves by undoing
    its arrival. Each point is pushed and handed over once: O(1) amortised per point, where a
    refit from scratch is O(window) (200 blocks). Every vertex of the window's lower hull is a
    vertex of one of the two chains, so ``lower_hull`` of the chains' vertices is the window's
    ``lower_hull``, the same list (the points have distinct x: vertices are determined).
    """

    __slots__ = ("back", "back_hull", "front_hull", "front_log")

    def __init__(self) -> None:
        self.back: list[tuple[int, int]] = []  # the newer points, in x order
        self.back_hull: list[tuple[int, int]] = []  # their lower hull, left to right
        self.front_hull: list[tuple[int, int]] = []  # the older points' lower hull, right to left
        self.front_log: list[list[tuple[int, int]]] = []  # per older point: what its arrival popped

    def clear(self) -> None:
        self.back.clear()
        self.back_hull.clear()
        self.front_hull.clear()
        self.front_log.clear()

    def push(self, p: tuple[int, int]) -> None:
        """A point right of all others (``lower_hull``'s step)."""
        self.back.append(p)
        _chain_push(self.back_hull, p)

    def pop_oldest(self) -> None:
        """The leftmost point leaves."""
        if not self.front_log:
            self._hand_over()
        self.front_hull.pop()  # the leftmost point is always on the hull: the last pushed there
        self.front_hull.extend(reversed(self.front_log.pop()))

    def _hand_over(self) -> None:
        """``back`` becomes the front: its chain built right to left, each point's pops logged."""
        hull, log = self.front_hull, self.front_log
        for p in reversed(self.back):
            px, py = p
            popped: list[tuple[int, int]] = []
            while len(hull) >= 2:
                ox, oy = hull[-2]  # p < a < o in x: keep a if it is strictly below p -> o
                ax, ay = hull[-1]
                if (ax - px) * (oy - py) - (ay - py) * (ox - px) > 0:
                    break
                popped.append(hull.pop())
            hull.append(p)
            log.append(popped)
        self.back.clear()
        self.back_hull.clear()

    def vertices(self) -> list[tuple[int, int]]:
        """Left to right: a superset of the window's lower hull vertices, in x order."""
        return [*reversed(self.front_hull), *self.back_hull]


@dataclass
class ArrivalHull:
    """Points (x = device ns, y = arrival - device ns), one minimum per block, in a window.

    ``line()`` -> (x0, y0, slope): y(x) = y0 + slope (x - x0) is the lower bound of offset+delay.
    While blocks come in device-time order (always, short of a clock going backwards, which
    resets the hull once declared) a sliding hull (``_SlidingLowerHull``) gives the refit at each
    new block in O(1) amortised; otherwise the window is sorted and refitted whole, as before.
    """

    cfg: SyncConfig
    prior_slope: float = 0.0
    blocks: deque[tuple[int, int]] = field(default_factory=deque)  # closed blocks' minima
    cur_block: int | None = None
    cur_min: tuple[int, int] | None = None
    _line: tuple[int, float, float] | None = None
    n: int = 0
    _unordered: bool = False  # a block went back in device time since the last reset
    _sliding: _SlidingLowerHull = field(default_factory=_SlidingLowerHull, repr=False, compare=False)

    def reset(self, prior_slope: float) -> None:
        self.prior_slope = prior_slope
        self.blocks.clear()
        self._sliding.clear()
        self._unordered = False
        self.cur_block = None
        self.cur_min = None
        self._line = None

    def add(self, x: int, y: int) -> None:
        self.n += 1
        b = x // self.cfg.hull_block_ns
        if self.cur_block is None or b != self.cur_block:
            if self.cur_min is not None:
                blocks = self.blocks
                if blocks and self.cur_min[0] < blocks[-1][0]:
                    self._unordered = True
                blocks.append(self.cur_min)
                if not self._unordered:
                    self._sliding.push(self.cur_min)
                oldest = x - self.cfg.hull_window_ns
                while blocks and blocks[0][0] < oldest:
                    blocks.popleft()
                    if not self._unordered:
                        self._sliding.pop_oldest()
            self.cur_block, self.cur_min = b, (x, y)
            self._fit()
        elif self.cur_min is None or y < self.cur_min[1]:
            self.cur_min = (x, y)
            if not self.blocks:  # the first block: keep the offset current while it fills
                self._fit()

    def _fit(self) -> None:
        blocks, cur = self.blocks, self.cur_min
        if (
            cur is not None
            and len(blocks) >= 1
            and not self._unordered
            and cur[0] > blocks[-1][0]
            and cur[0] - blocks[0][0] >= self.cfg.min_span_ns
        ):
            # the window in x order, blocks then the open one: its hull from the sliding one's
            # vertices (the same list as lower_hull of every point, see _SlidingLowerHull)
            self._fit_hull(lower_hull([*self._sliding.vertices(), cur]), blocks[0][0], cur[0])
            return
        self._fit_all()

    def _fit_all(self) -> None:
        """The fit from every point of the window, sorted: the reference the fast path equals."""
        pts = sorted([*self.blocks, *([self.cur_min] if self.cur_min is not None else [])])
        if not pts:
            self._line = None
            return
        span = pts[-1][0] - pts[0][0]
        if span < self.cfg.min_span_ns or len(pts) < 2:
            # too short to trust a slope: the prior slope through the lowest point
            s = self.prior_slope
            x0, y0 = min(pts, key=lambda p: p[1] - s * (p[0] - pts[0][0]))
            self._line = (x0, float(y0), s)
            return
        self._fit_hull(lower_hull(pts), pts[0][0], pts[-1][0])

    def _fit_hull(self, hull: list[tuple[int, int]], x_first: int, x_last: int) -> None:
        """The hull edge that spans the window's middle, its slope clamped to a clock's."""
        xm = (x_first + x_last) // 2
        for a, b in itertools.pairwise(hull):
            if a[0] <= xm <= b[0]:
                break
        else:
            a, b = hull[0], hull[-1]
        s = (b[1] - a[1]) / (b[0] - a[0]) if b[0] != a[0] else self.prior_slope
        lim = self.cfg.max_drift_ppm * 1e-6
        s = min(max(s, -lim), lim)
        self._line = (a[0], float(a[1]), s)

    def line(self) -> tuple[int, float, float] | None:
        return self._line

    def at(self, x: int) -> float | None:
        if self._line is None:
            return None
        x0, y0, s = self._line
        return y0 + s * (x - x0)

    @property
    def span_ns(self) -> int:
        # Asked for on every arrival: blocks normally arrive in device-time order (a clock step
        # resets the hull), so the extremes are the two ends; a full scan only when they did not.
        if self.blocks and self._unordered:
            xs = [p[0] for p in self.blocks]
        else:
            xs = [p[0] for p in (self.blocks[0], self.blocks[-1])] if self.blocks else []
        if self.cur_min is not None:
            xs.append(self.cur_min[0])
        return (max(xs) - min(xs)) if xs else 0


# ---------------------------------------------------------------------------------------------
# one sensor


@dataclass
class _Held(Generic[T]):
    item: T
    device_ns: int
    rx_ns: int
    resid: float
    count_jitter: bool = True  # False: part of a suspicious run, kept out of the jitter scale
    out: bool = False  # released already (an idle release), still part of the step watch's run


@dataclass
class SensorSync(Generic[T]):
    """Tags, arrivals, step watch and the hold queue of one sensor."""

    sensor: str
    cfg: SyncConfig
    kf: TagFilter = field(init=False)
    hull: ArrivalHull = field(init=False)
    mapping: ClockMapping = field(init=False)
    held: deque[_Held[T]] = field(default_factory=deque)
    jitter_ns: float = 0.0  # running scale of arrival residuals (mean excess delay)
    delta_ns: float = 0.0  # hull floor minus the tag mapping: the learned minimum delay
    recovering: bool = False
    n_arrivals: int = 0
    since_reset: int = 0  # arrivals since the start or the last step
    last_device_ns: int | None = None  # device time of the previous arrival (the gross-step test)
    last_rx_ns: int | None = None  # rig arrival of the previous measurement (the idle release)
    # tag-ruled step watch: the current run of same-side suspicious arrival residuals
    run_side: int = 0  # +1 above the floor (backward step?), -1 below (forward step?), 0 none
    run_first_ns: int = 0  # device time of the run's first arrival
    run_n: int = 0
    run_last_ns: int = 0  # device time of its latest
    run_min_ns: float = 0.0  # lowest residual of the run: ≈ -Δ of a step Δ (+ the least excess)
    last_tag: tuple[int, float] | None = None  # (device, z) of the last tag
    startup_hold: bool = True  # holding until the tag filter locks (cfg.hold_until_locked_ns > 0)
    # the start-up hold's queue: (item, device ns, clock epoch), in arrival order, each stamped at
    # the release with the mapping of its own epoch (a step during the hold starts a new one)
    lock_q: deque[tuple[T, int, int]] = field(default_factory=deque)
    epoch: int = 0  # clock epochs seen during the start-up hold (a declared step starts one)
    epoch_maps: dict[int, ClockMapping] = field(default_factory=dict)  # closed epochs' last mapping
    _run_lock_idx: int = 0  # where in ``lock_q`` the current suspicious run's first item is
    _hold_span_ns: int = 0  # device time held in closed epochs (their unsuspicious span)
    _epoch_first_ns: int | None = None  # device time of the current epoch's first held item
    _epoch_last_ok_ns: int | None = None  # and of its latest unsuspicious one
    _hold_first_rx_ns: int | None = None  # rig arrival of the first held item (the backstop)
    # the filter's ``version`` the mapping was last drawn from (-1: drawn from the arrivals):
    # between tags the tag mapping is refreshed for every measurement, and stays what it was
    _mapped_version: int = -1

    def __post_init__(self) -> None:
        self.kf = TagFilter(self.cfg)
        self.kf.reset(0.0, 100_000.0)
        self.hull = ArrivalHull(self.cfg)
        self.mapping = ClockMapping(self.sensor, source=self.cfg.source)
        self.delta_ns = float(self.cfg.min_delay_ns)
        self.jitter_ns = float(self.cfg.step_floor_ns) / 4

    # -- tags ---------------------------------------------------------------------------------
    def on_timetag(self, device_ns: int, rig_latch_ns: int) -> list[tuple[T, int]]:
        """A tag; what it returns is what an idle release let go before it (``idle_release_due``)."""
        if self.cfg.source != "timetag":
            return []  # not used: it moves nothing, so it releases nothing either
        released = self.release_held() if self.idle_release_due(rig_latch_ns) else []
        if not self.kf.initialised:
            line = self.hull.line()
            if line is not None and self.hull.span_ns >= self.cfg.min_span_ns:
                # the hull's drift is a better prior than none (rig-device slope, in ppb)
                self.kf.reset(line[2] * 1e9, 5_000.0)
        ruled = self._tag_ruled()
        z = float(rig_latch_ns - self.cfg.tag_latency_ns - device_ns)
        self.last_tag = (device_ns, z)
        verdict = self.kf.update(device_ns, z)
        if verdict == "outlier" and ruled and self._run_confirms(self.kf.last_outlier_nu):
            # arrivals already saw a jump of this size: tag and arrivals agree, the clock stepped
            self._tag_step()
        elif verdict == "step":
            self._tag_step()
        elif verdict == "init":
            self.recovering = False
            self._end_run()
        elif verdict == "ok" and ruled:
            self._end_run()  # the tag fits: whatever the arrivals did was the transport
        self._refresh()
        return released

    def idle_release_due(self, stamp_ns: int) -> bool:
        """Is what this sensor holds to go out before an input stamped ``stamp_ns`` (a
        measurement's arrival, a tag's latch, rig clock)? Yes when the sensor has been silent for
        more than ``IDLE_RELEASE_NS`` since its last measurement arrived (the start-up hold has
        its own bound). The live service asks it with its clock less a margin (``tick``)."""
        if not self.held or self.held[-1].out or self.startup_hold:
            return False
        return self.ends_silence(stamp_ns)

    def ends_silence(self, stamp_ns: int) -> bool:
        """Is an input stamped ``stamp_ns`` more than ``IDLE_RELEASE_NS`` after the last
        measurement's arrival (the idle release's test, held or not)?"""
        last = self.last_rx_ns
        return last is not None and stamp_ns > last + IDLE_RELEASE_NS

    def release_held(self) -> list[tuple[T, int]]:
        """An idle release: what is held goes out under the mapping of the clock as it stood
        before them, and stays in the step watch's run. A slow sensor's suspicious measurements
        (a 1 Hz receiver's, timed by arrivals) can so still add up to a declared step, which
        releasing them into the hull undid each time; from the step on the new mapping stamps."""
        held = [h for h in self.held if not h.out]
        if not held:
            return []
        self._refresh()
        to_rig = self.mapping.to_rig
        for h in held:
            h.out = True
        return [(h.item, to_rig(h.device_ns)) for h in held]

    def _tag_ruled(self) -> bool:
        """Tags decide steps and stamps: a locked-on filter that no step has invalidated."""
        return self.cfg.source == "timetag" and self.kf.initialised and not self.recovering

    def _tag_step(self) -> None:
        """A step confirmed by a tag: forget the old clock and restart the filter on that tag."""
        run_from = self._run_lock_idx if self._run_confirms(self.kf.last_outlier_nu) else None
        self._declare_step(run_from)
        if self.last_tag is not None:
            self.kf.update(*self.last_tag)  # "init": this tag is on the new clock already
        self.recovering = not self.kf.initialised

    def _end_run(self) -> None:
        self.run_side, self.run_n = 0, 0

    def _run_established(self) -> bool:
        """The arrival tests of the arrival-only watch, applied to the current run."""
        if self.run_side < 0:
            return self.run_n >= self.cfg.step_confirm
        if self.run_side > 0:
            return (
                self.run_n >= self.cfg.step_confirm
                and self.run_last_ns - self.run_first_ns >= self.cfg.step_window_ns
            )
        return False

    def _run_confirms(self, nu_ns: float) -> bool:
        """Does a tag innovation ``nu`` (≈ -Δ after a step Δ) match the arrivals' run?

        After a step Δ every arrival residual is ``excess - Δ``, so the run's lowest residual is
        -Δ plus the least excess delay seen; the tolerance covers that excess and the tag gate.
        """
        if not self._run_established() or (nu_ns > 0) != (self.run_side > 0):
            return False
        tol = max(float(self.cfg.tag_gate_ns), 2.0 * self._thresholds()[0])
        return abs(nu_ns - self.run_min_ns) < tol

    def _thresholds(self) -> tuple[float, float]:
        """(up, down): residual scale that counts as suspicious, from the excess-delay scale J.

        One residual above 6 J happens 0.25 % of the time for an exponential-like tail; a whole
        window of them, never. Below the floor any residual beyond J (and the floor) is suspect.
        """
        return (
            max(float(self.cfg.step_floor_ns), 6.0 * self.jitter_ns),
            max(float(self.cfg.step_floor_ns), self.jitter_ns),
        )

    # -- arrivals -----------------------------------------------------------------------------
    def on_measurement(self, device_ns: int, rx_ns: int, item: T) -> list[tuple[T, int]]:
        self.n_arrivals += 1
        if self.cfg.source == "off":
            self.mapping.n_samples = self.n_arrivals
            return [(item, rx_ns)]
        if self.startup_hold and not self._hold_applies():
            self.startup_hold = False
        # (``held`` first: empty but around a suspected step, and this runs for every measurement)
        released = self.release_held() if self.held and self.idle_release_due(rx_ns) else None
        self.last_rx_ns = rx_ns
        if self._hold_first_rx_ns is None:
            self._hold_first_rx_ns = rx_ns
        out = self._on_arrival(device_ns, rx_ns, item)
        if self.startup_hold and self._hold_over(rx_ns):
            out = self._end_hold()
        return out if released is None else released + out

    def _on_arrival(self, device_ns: int, rx_ns: int, item: T) -> list[tuple[T, int]]:
        """The step watch of one measurement: what it releases (into ``lock_q`` while holding)."""
        y = rx_ns - device_ns
        if self._tag_ruled():
            return self._on_tag_ruled(device_ns, rx_ns, y, item)
        floor = self.hull.at(device_ns)
        resid = 0.0 if floor is None else y - floor
        last_dev, self.last_device_ns = self.last_device_ns, device_ns
        self.held.append(_Held(item, device_ns, rx_ns, resid))
        # No step test until the floor and the jitter scale are known (after start or a step).
        warm = self.since_reset >= 4 * self.cfg.step_confirm and self.hull.span_ns >= self.cfg.step_window_ns
        if not warm and len(self.held) == 1 and self._gross_step(device_ns, last_dev, resid):
            return self._step_and_release()
        if floor is None or not warm:
            return self._release_all()
        thr_up, thr_down = self._thresholds()
        held = self.held
        if resid < -thr_down:
            # below the lower bound, impossible for a one-way delay: a forward step once
            # ``step_confirm`` arrive in a row
            if not all(h.resid < -thr_down for h in held):
                return self._release_all()
            if len(held) >= self.cfg.step_confirm:
                return self._step_and_release()
            return []
        if resid > thr_up:
            # the floor itself moved up (a backward step) once a whole window sits above it;
            # a window longer than any plausible transport stall
            if not all(h.resid > thr_up for h in held):
                return self._release_all()
            if (
                held[-1].device_ns - held[0].device_ns >= self.cfg.step_window_ns
                and len(held) >= self.cfg.step_confirm
            ):
                return self._step_and_release()
            return []
        return self._release_all()

    def _gross_step(self, device_ns: int, last_dev: int | None, resid: float) -> bool:
        """Before the step tests are warm (the first ``step_window_ns`` after start or a step), a
        step no transport can explain: device time back by more than the backward-step window
        (arrivals of one sensor come in order), or a delay below the floor by more than it (a
        one-way delay cannot shrink). A step in the first half second of a run was otherwise
        put on the new clock with the samples before it (+100 s for a -100 s step)."""
        window = self.cfg.step_window_ns
        if last_dev is not None and device_ns < last_dev - window:
            return True
        return self.hull.at(device_ns) is not None and resid < -window

    def _hold_applies(self) -> bool:
        """Does this sensor hold at start (module docstring: an interval sensor with tags)?"""
        return self.cfg.hold_until_locked_ns > 0 and self.cfg.source == "timetag"

    def _hold_over(self, rx_ns: int) -> bool:
        """Start-up hold: locked, or held long enough.

        How long is device time, summed over the hold's clock epochs and counting only
        unsuspicious items: across a step device time jumps (back by 100 s, say, which must not
        hold for ever, or ahead, which must not end the hold before the step is decided). Rig
        arrival time is the backstop, at twice the bound, should a suspicion never be settled."""
        if self.kf.n >= 3 and not self.recovering:
            return True
        first, last = self._epoch_first_ns, self._epoch_last_ok_ns
        held_ns = self._hold_span_ns + (last - first if first is not None and last is not None else 0)
        bound = self.cfg.hold_until_locked_ns
        first_rx = self._hold_first_rx_ns
        return held_ns >= bound or (first_rx is not None and rx_ns - first_rx >= 2 * bound)

    def _to_lock_q(self, held: deque[_Held[T]]) -> None:
        """Released by the step watch while the start-up hold lasts: queued with their epoch."""
        for h in held:
            self.lock_q.append((h.item, h.device_ns, self.epoch))
            if self._epoch_first_ns is None:
                self._epoch_first_ns = h.device_ns
            if h.count_jitter:
                self._epoch_last_ok_ns = h.device_ns

    def _new_epoch(self, relabel_from: int | None) -> None:
        """A step declared during the start-up hold: the epoch ends with the mapping in force, and
        the queued items from ``relabel_from`` on (the suspicious run that proved the step, taken
        after it) belong to the new one."""
        first, last = self._epoch_first_ns, self._epoch_last_ok_ns
        if first is not None and last is not None:
            self._hold_span_ns += max(0, last - first)
        self.epoch_maps[self.epoch] = replace(self.mapping)
        self.epoch += 1
        self._epoch_first_ns = self._epoch_last_ok_ns = None
        if relabel_from is None:
            return
        q = self.lock_q
        for k in range(relabel_from, len(q)):
            item, dev, _ = q[k]
            q[k] = (item, dev, self.epoch)
            if self._epoch_first_ns is None:
                self._epoch_first_ns = dev

    def _end_hold(self) -> list[tuple[T, int]]:
        """The start-up hold ends: every queued item stamped with the mapping of its own epoch
        (the current one: the locked mapping; an earlier one: its last, before the step)."""
        self.startup_hold = False
        self._refresh()
        maps = self.epoch_maps
        cur = self.epoch
        out = [(item, (self.mapping if e == cur else maps[e]).to_rig(dev)) for item, dev, e in self.lock_q]
        self.lock_q.clear()
        maps.clear()
        return out

    def _on_tag_ruled(self, device_ns: int, rx_ns: int, y: int, item: T) -> list[tuple[T, int]]:
        """Stamp from the tag mapping at once; arrivals only feed the hull and the step suspicion."""
        resid = y - (self.mapping.to_rig(device_ns) - device_ns) - self.delta_ns
        thr_up, thr_down = self._thresholds()
        side = 1 if resid > thr_up else -1 if resid < -thr_down else 0
        if side == 0:
            self._end_run()
        elif side != self.run_side:
            self.run_side, self.run_first_ns, self.run_n, self.run_min_ns = side, device_ns, 1, resid
            self._run_lock_idx = len(self.lock_q) + len(self.held)  # where this item will be queued
        else:
            self.run_n += 1
            self.run_min_ns = min(self.run_min_ns, resid)
        self.run_last_ns = device_ns
        self.held.append(_Held(item, device_ns, rx_ns, resid, count_jitter=side == 0))
        if side != 0 and self.kf.outliers_in_row > 0 and self._run_confirms(self.kf.last_outlier_nu):
            # the last tag was already off by this much: arrivals confirm the tag, the clock stepped
            self._tag_step()
            for h in self.held:
                h.resid, h.count_jitter = 0.0, False
        return self._release_all()

    def _step_and_release(self) -> list[tuple[T, int]]:
        pts = [(h.device_ns, h.rx_ns - h.device_ns) for h in self.held]
        self._declare_step()
        for x, y in pts:
            self.hull.add(x, y)
        for h in self.held:
            h.resid = 0.0
        return self._release_all()

    def _declare_step(self, run_from: int | None = None) -> None:
        """Forget what the old clock said: hull restarts (slope kept), KF waits for a tag.

        ``run_from``: where in the start-up hold's queue the run of arrivals that proved the step
        begins (those were taken after it)."""
        if self.startup_hold:
            self._new_epoch(run_from)
        line = self.hull.line()
        slope = line[2] if line is not None else 0.0
        if self.cfg.source == "timetag" and self.kf.initialised:
            self.kf.reset(self.kf.f_ppb, math.sqrt(max(self.kf.p[2], 1.0)))
            slope = self.kf.f_ppb * 1e-9
        self.hull.reset(slope)
        self.since_reset = 0
        self._end_run()
        self.mapping.steps_detected += 1
        self.recovering = True

    def _release_all(self) -> list[tuple[T, int]]:
        held, hull, cfg = self.held, self.hull, self.cfg
        learn = cfg.source == "timetag" and self.kf.n >= 3 and not self.recovering
        jitter, floor_ns = self.jitter_ns, cfg.step_floor_ns
        gain = min(256.0, float(self.n_arrivals))
        for h in held:
            hull.add(h.device_ns, h.rx_ns - h.device_ns)
            if not h.count_jitter:
                continue
            # jitter scale: a running mean of the (clipped) excess delay, cumulative at first
            r = min(max(h.resid, 0.0), 10.0 * jitter + floor_ns)
            jitter += (r - jitter) / gain
        self.jitter_ns = jitter
        self.since_reset += len(held)
        self._refresh()
        to_rig = self.mapping.to_rig
        out: list[tuple[T, int]] = [(h.item, to_rig(h.device_ns)) for h in held if not h.out]
        if learn and held:
            h = held[-1]
            floor = hull.at(h.device_ns)
            if floor is not None:
                tag_off = to_rig(h.device_ns) - h.device_ns  # the last one's rig stamp, under this mapping
                self.delta_ns += (floor - tag_off - self.delta_ns) / 64.0
        if self.startup_hold:
            self._to_lock_q(held)
            out = []
        held.clear()
        self.mapping.n_samples = self.n_arrivals
        return out

    def flush(self) -> list[tuple[T, int]]:
        out = self._release_all() if self.held else []
        return self._end_hold() if self.startup_hold and self.lock_q else out

    # -- the published mapping ------------------------------------------------------------------
    def _refresh(self) -> None:
        m = self.mapping
        if self.cfg.source == "timetag" and self.kf.initialised and not self.recovering:
            if self._mapped_version == self.kf.version:
                return  # no tag since: the same mapping
            self._mapped_version = self.kf.version
            m.offset_ns, m.drift_ppb, m.ref_device_ns = self.kf.mapping_terms()
            m.source = "timetag"
            m.residual_rms_ns = (
                math.sqrt(sum(self.kf.res_sq) / len(self.kf.res_sq)) if self.kf.res_sq else 0.0
            )
            m.state = "locked" if self.kf.n >= 3 else "converging"
            return
        self._mapped_version = -1
        line = self.hull.line()
        if line is None:
            return
        x0, y0, s = line
        delay = self.delta_ns if self.cfg.source == "timetag" else float(self.cfg.min_delay_ns)
        m.offset_ns = round(y0 - delay)
        m.drift_ppb = s * 1e9
        m.ref_device_ns = x0
        m.source = "arrival"
        m.residual_rms_ns = self.jitter_ns
        if self.recovering:
            m.state = "step_recovering"
            if self.cfg.source == "arrival" and self.hull.span_ns >= self.cfg.min_span_ns:
                self.recovering = False
                m.state = "locked"
        else:
            m.state = "locked" if self.hull.span_ns >= self.cfg.min_span_ns else "converging"


# ---------------------------------------------------------------------------------------------


class TimeSyncCore(Generic[T]):
    """One :class:`SensorSync` per sensor; fed time tags and measurements, releases re-stamps.

    ``on_measurement`` returns ``(item, rig time of validity)`` pairs in arrival order; usually the
    measurement just given, sometimes none (held while a step is being decided) or several.
    """

    def __init__(self, configs: Mapping[str, SyncConfig] | None = None, default: SyncConfig | None = None):
        self.configs = dict(configs or {})
        self.default = default or SyncConfig()
        self.sensors: dict[str, SensorSync[T]] = {}

    def sensor(self, sensor: str) -> SensorSync[T]:
        s = self.sensors.get(sensor)
        if s is None:
            s = self.sensors[sensor] = SensorSync(sensor, self.configs.get(sensor, self.default))
        return s

    @property
    def mappings(self) -> dict[str, ClockMapping]:
        return {k: s.mapping for k, s in self.sensors.items()}

    def mapping(self, sensor: str) -> ClockMapping:
        return self.sensor(sensor).mapping

    def on_timetag(self, sensor: str, device_ns: int, rig_latch_ns: int) -> list[tuple[T, int]]:
        """A time-tag edge: ``device_ns`` on the device clock, latched at ``rig_latch_ns``; returns
        what an idle release let go before it (``SensorSync.idle_release_due``)."""
        return self.sensor(sensor).on_timetag(int(device_ns), int(rig_latch_ns))

    def on_measurement(self, sensor: str, device_ns: int, rx_rig_ns: int, item: T) -> list[tuple[T, int]]:
        """A measurement stamped ``device_ns`` that arrived at ``rx_rig_ns`` (rig clock)."""
        return self.sensor(sensor).on_measurement(int(device_ns), int(rx_rig_ns), item)

    def flush(self) -> list[tuple[T, int]]:
        """Release every held measurement (end of input)."""
        out: list[tuple[T, int]] = []
        for s in self.sensors.values():
            out.extend(s.flush())
        return out

    def rig_interval(self, sensor: str, device_ns: int, dt_ns: int) -> int:
        """A measurement interval ``dt_ns`` (device clock) ending at ``device_ns`` on the rig clock,
        under the current mapping: what the fusion integrates over (``ClockMapping.interval``)."""
        return self.sensor(sensor).mapping.interval(int(device_ns), int(dt_ns))

    def restamp(self, sensor: str, device_ns: int) -> int:
        """Rig time of validity of ``device_ns`` under the current mapping (no hold, no update)."""
        return self.sensor(sensor).mapping.to_rig(int(device_ns))
