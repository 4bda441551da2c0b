"""The fusion: every estimator on the same synchronised inputs, each on ``nav/<estimator>``.

Inputs go to the pure ``hil.fusion.core.FusionCore`` in arrival order; its estimators take them
in the total order on a delayed horizon (``lag_s`` behind the newest IMU sample, which is also
the bound on a source's latency), and at each IMU sample's arrival the output predictor publishes
every estimator's state at that sample (docs/concepts.md, "Fusion"). It journals what it dropped;
a source whose latency crosses the bound raises a ``latency_over_bound`` event. Every half second of rig time
the node publishes that journal on ``fusion/journal`` -- with the recorded inputs, all
``hil rerun`` needs -- and every second each estimator's health as real numbers
(``health/<estimator>``, ``hil.EstimatorHealth``). Its configuration goes out once at start as
``fusion/config`` (``hil.FusionSettings``), so a recording says how to rebuild the core.

A fusion restarted mid-run (option ``resume``) re-aligns: it holds its inputs until the first
IMU sample and builds every estimator from the run's truth where that sample's interval starts
(an in-flight re-alignment; the rig knows truth, a real unit would use its last good solution),
then numbers its outputs after ``imu_seq // output_every + 1`` so no seq repeats one from before the death,
and says so in a ``realigned`` event naming that sample and the first input of each stream it
received before it. ``hil rerun`` reruns each life of the fusion on its own: the first on the
inputs before the re-alignment, each later one from a core re-aligned where the event says
(``realign_point``, ``realigned_imu_seq``), on the inputs that process received
(``realigned_first_received``), less what it journaled as dropped.
"""

from __future__ import annotations

import collections
import math
import re
from typing import Any

import msgspec

from hil.estimators.registry import (
    DEFAULT_ESTIMATORS,
    EKF_CALIBRATIONS,
    ESTIMATORS,
    FEEDBACK_CAPABLE,
    default_ekf_calibration,
    default_feedback,
)
from hil.estimators.tuning import BIAS_MODELS
from hil.fusion.core import (
    FREE_INS,
    FusionConfig,
    FusionCore,
    before_alignment,
    input_id,
)
from hil.messages import EstimatorHealth, ImuSample, Measurement, NavSolution
from hil.nav import kernels
from hil.nav.scenario import scenario_for_run
from hil.nav.sensor_specs import imu_grade
from hil.nodes.base import BatchedInputOptions, Input, Node, Out
from hil.sensor_table import SENSOR_NAMES, SENSORS

JOURNAL_PERIOD_NS = 500_000_000
HEALTH_PERIOD_NS = 1_000_000_000
_DEFAULT = FusionConfig()
DEFAULT_LAG_S = _DEFAULT.lag_s  # one default, FusionConfig's, for every caller
DEFAULT_OUTPUT_EVERY = _DEFAULT.output_every


def realign_point(first_imu: ImuSample, output_every: int) -> tuple[int, int]:
    """Where a restarted fusion re-aligns, and the seq its outputs start from, given the first IMU
    sample it takes: the start of that sample's interval, as a run is at 0 before its first one
    (the truth at its stamp already holds the motion the sample measured: stepped on top of it,
    every stream ran one interval ahead, 12 cm at 50 m/s and 400 Hz). The live fusion and
    ``hil rerun`` both take it from here."""
    stamp = first_imu.stamp_ns
    align_ns = stamp - min(max(first_imu.dt_ns, 0), max(stamp, 0))
    return align_ns, first_imu.seq // output_every + 1


_REALIGNED_SEQ = re.compile(r"\(the start of imu seq (\d+)\)")


MAX_FIRST_RECEIVED = 64  # streams a restarted fusion's realigned event names (the rig has a handful)
# inputs a restarted fusion received but did not hold, kept to journal at its re-alignment: past
# this the oldest are forgotten, which were received long before its first IMU sample and so are
# valid before its alignment (refused either way, nothing to journal)
MAX_HELD_DROPPED = 1_000
_FIRST_RECEIVED = re.compile(r"; first received: ([^;]*)$")


def realigned_detail(align_ns: int, imu_seq: int, first_seq: int, first_received: list[str]) -> str:
    """``first_received``: the first input of each stream the new life received before its first
    IMU sample (``input_id``), so that rerun takes exactly what it did (``realigned_first_received``)."""
    return (
        f"fusion restarted: estimators re-aligned from truth at t={align_ns / 1e9:.4f} s "
        f"(the start of imu seq {imu_seq}); outputs numbered from {first_seq}; "
        f"first received: {', '.join(first_received) or 'nothing else'}"
    )


def realigned_imu_seq(detail: str) -> int | None:
    """The first IMU sample a restarted fusion took, from its ``realigned`` event's detail
    (``realigned_detail``); None if the detail does not say."""
    m = _REALIGNED_SEQ.search(detail)
    return int(m.group(1)) if m else None


def realigned_first_received(detail: str) -> dict[tuple[str, str], int] | None:
    """Per stream (sensor, publisher), the seq of the first input a restarted fusion received
    before its first IMU sample (``realigned_detail``): it received every later one of that
    stream, and none of a stream not named before that sample. None: a recording made before
    the event said so (rerun infers it from the publish order)."""
    m = _FIRST_RECEIVED.search(detail)
    if m is None:
        return None
    firsts: dict[tuple[str, str], int] = {}
    for entry in m.group(1).split(", "):
        name, _, source = entry.partition("@")
        sensor, _, seq = name.partition(":")
        if seq.isdigit():
            firsts[(sensor, source)] = int(seq)
    return firsts


class FusionOptions(BatchedInputOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # empty: the registry's defaults (hil.estimators.registry)
    estimators: list[str] = msgspec.field(default_factory=list)
    # the fusion horizon's lag behind the newest IMU stamp: the bound on a source's latency
    lag_s: float = DEFAULT_LAG_S
    # publish at each IMU sample (the horizon's state carried forward by the IMU); False: the
    # horizon's state, lag_s late (the fusion before the predictor)
    output_predictor: bool = True
    output_every: int = DEFAULT_OUTPUT_EVERY  # publish every N-th IMU step
    # seed estimators in feedback form: "auto" (by the IMU grade), "none", or names (a,b)
    feedback: str = "auto"
    # ekf15's calibration states: "auto" (by the IMU grade), "none", "gyro", "gyro+accel"
    ekf_calibration: str = "auto"
    # how ekf15 and the feedback INS are told the IMU's bias wander (hil.estimators.tuning):
    # "instability" is what recordings made before the Gauss-Markov tuning ran, for replaying
    # one into a fresh fusion configured as it was
    imu_bias_model: str = _DEFAULT.imu_bias_model

    def __post_init__(self) -> None:
        unknown = [e for e in self.estimators if e not in ESTIMATORS and e != FREE_INS]
        if unknown:
            raise ValueError(
                f"unknown estimator(s) {unknown}; known: {', '.join(sorted(ESTIMATORS))} "
                f"(and {FREE_INS}, the free inertial solution, which always runs: name it alone for it alone)"
            )
        dup = sorted({e for e in self.estimators if self.estimators.count(e) > 1})
        if dup:  # each would run twice and publish every solution twice
            raise ValueError(f"estimators: {dup} named more than once; name each estimator once")
        if self.feedback not in ("auto", "none"):
            bad = [e for e in self.feedback.split(",") if e not in FEEDBACK_CAPABLE]
            if bad:
                raise ValueError(
                    f"feedback: {bad} have no feedback form; give auto, none or names of "
                    f"{', '.join(FEEDBACK_CAPABLE)}"
                )
        if self.ekf_calibration not in ("auto", "none", *EKF_CALIBRATIONS[1:]):
            raise ValueError(
                f"ekf_calibration must be auto, none, {' or '.join(EKF_CALIBRATIONS[1:])}; "
                f"got {self.ekf_calibration!r}"
            )
        if self.imu_bias_model not in BIAS_MODELS:
            raise ValueError(
                f"imu_bias_model must be {' or '.join(BIAS_MODELS)}; got {self.imu_bias_model!r}"
            )
        if not 0.0 <= self.lag_s <= 60.0:
            raise ValueError(f"lag_s must be in [0, 60] s, got {self.lag_s}")
        if self.output_every < 1:
            raise ValueError(f"output_every must be >= 1, got {self.output_every}")

    def run_estimators(self) -> tuple[str, ...]:
        """The estimators the fusion runs beside the free INS: none named, the registry's
        defaults; the free INS named alone, none."""
        named = tuple(e for e in self.estimators if e != FREE_INS)
        return named if self.estimators else DEFAULT_ESTIMATORS

    def unused_choice(self) -> str:
        """A feedback or calibration choice for an estimator the fusion does not run ("" if
        none): ``config`` leaves it out, so a command line that asked for it is told instead."""
        run = self.run_estimators()
        which = f"the fusion runs {', '.join(run)}" if run else "the fusion runs the free INS alone"
        if self.feedback not in ("auto", "none"):
            idle = [e for e in self.feedback.split(",") if e not in run]
            if idle:
                return (
                    f"feedback {self.feedback}: {', '.join(idle)} not run ({which}); add "
                    f"{'it' if len(idle) == 1 else 'them'} to the estimators or leave {', '.join(idle)} out"
                )
        if self.ekf_calibration not in ("auto", "none") and "ekf15" not in run:
            return (
                f"ekf_calibration {self.ekf_calibration}: ekf15, whose states they are, is not run "
                f"({which}); add ekf15 to the estimators, or choose auto or none"
            )
        return ""

    def config(self, grade: str = "tactical") -> FusionConfig:
        """The core's configuration; ``auto`` choices resolved for an IMU of ``grade``
        (``hil.nav.sensor_specs.imu_grade``: the fusion passes its scenario's)."""
        # none named: the registry's defaults; the free INS named alone: it alone (it always runs)
        estimators = self.run_estimators()
        if self.feedback == "auto":
            feedback = default_feedback(grade, estimators)
        elif self.feedback == "none":
            feedback = ()
        else:
            feedback = tuple(e for e in FEEDBACK_CAPABLE if e in self.feedback.split(",") and e in estimators)
        cal = self.ekf_calibration
        cal = default_ekf_calibration(grade) if cal == "auto" else "" if cal == "none" else cal
        return FusionConfig(
            estimators=estimators,
            lag_ns=round(self.lag_s * 1e9),
            output_every=self.output_every,
            feedback=feedback,
            ekf_calibration=cal,
            output_predictor=self.output_predictor,
            imu_bias_model=self.imu_bias_model,
        )


class FusionNode(Node):
    inputs_move_timers = False  # its timers are its own: periodic, or none
    journals_drops = True  # an input the live inbox dropped is journaled: rerun leaves it out
    # a stranger's fixes never reach an estimator (nor the journal): Zenoh may drop a stranger's
    # messages to the recorder but not to the fusion, so what it took could not be rerun
    refuses_foreign = True
    name = "fusion"
    Options = FusionOptions
    # The aiding streams' subscriptions are declared before the IMU's: a restarted fusion takes
    # what was published after the IMU sample before the first one it received (``hil rerun``
    # infers the same from the publish order), and declared first on the one session, an aiding
    # stream's subscription has taken effect at the hub by the time the IMU's has.
    inputs = tuple(
        Input(f"synced/{s}", {"synced": SENSORS[s].message})
        for s in sorted(SENSOR_NAMES, key=lambda n: SENSORS[n].paces_fusion)
    )

    def __init__(self, run: Any, options: FusionOptions | None = None) -> None:
        super().__init__(run, options)
        opts: FusionOptions = self.options  # type: ignore[assignment]
        self.scenario = scenario_for_run(run)
        self.config = opts.config(imu_grade(self.scenario.imu.params))
        self.end_ns = int(run.duration_s * 1e9)
        self.outputs = tuple(f"nav/{n}" for n in (FREE_INS, *self.config.estimators))  # type: ignore[misc]
        # restarted: hold inputs until the first IMU sample, then re-align there
        self.core: FusionCore | None = None
        if not opts.resume:
            self.core = FusionCore.for_scenario(self.scenario, self.config)
        self._held: list[tuple[Measurement, str]] = []
        # a restarted fusion, until its first IMU sample: each stream's first input received
        # (``realigned_detail``), and what it received but did not hold (its inbox dropped it,
        # or the held list was full): journaled once the core exists, as rerun takes every
        # input of a stream from its first on
        self._first_received: dict[tuple[str, str], str] = {}
        self._held_dropped: collections.deque[tuple[Measurement, str, str]] = collections.deque(
            maxlen=MAX_HELD_DROPPED
        )
        self.pushed = 0  # inputs handed to the core (lockstep replay counts them)
        self._next_journal = JOURNAL_PERIOD_NS
        self._next_health = HEALTH_PERIOD_NS

    @classmethod
    def for_rerun(
        cls, run: Any, config: FusionConfig, realigned: tuple[int, int] | None = None
    ) -> FusionNode:
        """The node as a recording says it ran: its configuration field for field (``hil rerun``);
        ``realigned``: a restarted fusion's ``realign_point``."""
        node = cls(run, FusionOptions(estimators=list(config.estimators)))
        node.config = config
        align_ns, first_seq = realigned or (0, 0)
        node.core = FusionCore.for_scenario(node.scenario, config, align_ns=align_ns)
        if realigned is not None:
            node.core.start_output_seq(first_seq)
        return node

    def replay(self, msg: Measurement, source: str = "", predicted: bool = True) -> list[NavSolution]:
        """One input the live fusion accepted, in the total order (``hil rerun``); ``predicted``
        False for an IMU sample its journal names ``unpredicted``."""
        assert self.core is not None
        return self.core.replay(msg, source, predicted)

    def start(self, now_ns: int) -> list[Out]:
        return [("fusion/config", self.config.settings(self.next_seq("fusion/config"), now_ns))]

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        return self.on_message_from(key, msg, now_ns, "")

    def on_message_from(self, key: str, msg: Any, now_ns: int, source: str) -> list[Out]:
        if self.core is None:
            return self._realign(msg, source, now_ns)
        return self._push(msg, source)

    def on_dropped(self, key: str, msg: Any, source: str) -> None:
        """An input the live inbox dropped: journaled, so rerun leaves it out too."""
        if self.core is not None:
            self.core.note_dropped(msg, source)
        else:  # received while the restarted fusion holds: journaled at its re-alignment
            self._note_received(msg, source)
            self._held_dropped.append((msg, source, "inbox"))

    def _push(self, msg: Measurement, source: str = "") -> list[Out]:
        core = self.core
        assert core is not None
        sols = core.push(msg, source)
        self.pushed += 1
        # per source, taken or refused: what its refusals (dropped_late.<sensor>) are a share of
        self.inc("inputs." + msg.sensor)
        if core.last_error:
            self.error("errors.estimator", core.last_error)
            core.last_error = ""
        outs = _nav(sols)
        for t in core.take_gate_events():  # an integrity alarm raised or cleared
            outs.append(self.event(t.kind, t.detail, t.stamp_ns))
        for t in core.take_latency_events():  # a source crossed the latency bound
            outs.append(self.event(t.kind, t.detail, t.stamp_ns))
        return outs

    def _note_received(self, msg: Measurement, source: str) -> None:
        stream = (msg.sensor, source)
        # bounded: a flood of made-up publishers (a bus without the rig's key) names no more
        if stream not in self._first_received and len(self._first_received) < MAX_FIRST_RECEIVED:
            self._first_received[stream] = input_id(msg, source)

    def _realign(self, msg: Measurement, source: str, now_ns: int) -> list[Out]:
        self._note_received(msg, source)
        self._held.append((msg, source))
        if not isinstance(msg, ImuSample):
            if 0 < self.config.max_buffered_aiding < len(self._held):  # bounded through an IMU outage
                old, old_source = self._held.pop(0)
                self.inc(f"dropped_held.{old.sensor}")
                self._held_dropped.append((old, old_source, "held"))
            return []
        align_ns, first_seq = realign_point(msg, self.config.output_every)
        self.core = FusionCore.for_scenario(self.scenario, self.config, align_ns=align_ns)
        self.core.start_output_seq(first_seq)
        firsts = list(self._first_received.values())
        self._first_received.clear()  # said once: later inputs go to the core
        outs = [self.event("realigned", realigned_detail(align_ns, msg.seq, first_seq, firsts), now_ns)]
        for m, src, why in self._held_dropped:  # rerun would take them: journaled as dropped
            if not before_alignment(m.stamp_ns, align_ns):
                self.core.note_dropped(m, src, why)
        self._held_dropped.clear()
        held, self._held = self._held, []
        held = [(m, src) for m, src in held if not before_alignment(m.stamp_ns, align_ns)]
        for m, src in held:  # nothing from before the alignment
            outs.extend(self._push(m, src))
        return outs

    def next_tick_ns(self) -> int | None:
        t = min(self._next_journal, self._next_health)
        return t if t <= self.end_ns else None

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = []
        if now_ns >= self._next_journal:
            self._next_journal = (now_ns // JOURNAL_PERIOD_NS + 1) * JOURNAL_PERIOD_NS
            outs.extend(self._journal(now_ns))
        if now_ns >= self._next_health:
            self._next_health = (now_ns // HEALTH_PERIOD_NS + 1) * HEALTH_PERIOD_NS
            outs.extend(self.health(now_ns))
        return outs

    def _journal(self, now_ns: int) -> list[Out]:
        if self.core is None:
            return []
        journals = self.core.journals(lambda: self.next_seq("fusion/journal"), now_ns)
        return [("fusion/journal", j) for j in journals]

    def health(self, now_ns: int) -> list[Out]:
        """Each estimator's health as real numbers (``health/<estimator>``)."""
        if self.core is None:
            return []
        outs: list[Out] = []
        for name, values in self.core.estimator_health().items():
            key = f"health/{name}"
            finite = {k: v for k, v in values.items() if math.isfinite(v)}
            if len(finite) != len(values):  # JSON has no NaN: said, not sent
                self.inc(f"health.nonfinite.{name}", len(values) - len(finite))
            msg = EstimatorHealth(
                seq=self.next_seq(key),
                stamp_ns=now_ns,
                estimator=name,
                names=list(finite),
                values=list(finite.values()),
            )
            outs.append((key, msg))
        return outs

    def finish(self, now_ns: int) -> list[Out]:
        """End of input: release the buffered tail and journal it."""
        if self.core is None:
            return []
        return _nav(self.core.flush()) + self._journal(now_ns)

    def counters(self) -> dict[str, int]:
        core = self.core
        out = core.status_counters() if core is not None else {"held_for_alignment": len(self._held)}
        out["kernels.compiled"] = int(kernels.compiled)  # hil.runtime.jit: 0 runs at Python's speed
        out["kernels.ahead_of_time"] = int(kernels.ahead_of_time)  # hil.runtime.aot's module
        out.update(self.counts)
        return out


def _nav(sols: list[NavSolution]) -> list[Out]:
    return [(f"nav/{s.estimator}", s) for s in sols]
