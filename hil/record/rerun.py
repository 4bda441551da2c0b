"""``hil rerun FILE --core fusion [--verify]``: recompute a core's outputs from recorded inputs.

Fusion: the recorded synchronised inputs, minus those the live fusion journaled as dropped, in
the total order, through the fusion node's core built from the recording's own configuration
(``fusion/config``, ``hil.FusionSettings``; recordings made before it existed carry it as a
``fusion_config`` event) -- then every recomputed ``NavSolution`` is compared byte for byte with
the recorded one. The first difference is named (topic, seq, field, both values).

An input is named by its sensor, seq *and publisher* (the Zenoh source id the recorder kept, as
the live fusion journals it): a stranger's forged copy of ``gnss:42`` is another input than the
rig's, dropped or used as the live fusion decided. The fusion's own records -- its outputs, its
journal, its configuration, the run -- are taken from the rig's publishers only; a stranger's
``nav/ekf15`` is not the fusion's output, nor its journal the fusion's decisions.
"""

from __future__ import annotations

import bisect
import heapq
import json
from array import array
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from hil.fusion.core import FREE_INS, FusionConfig, before_alignment, input_id, input_key, parse_journal_id
from hil.messages import (
    Event,
    FusionJournal,
    FusionSettings,
    Measurement,
    NavSolution,
    RunInfo,
    decode,
    encoded_today,
)
from hil.nodes.fusion import FusionNode, realign_point, realigned_first_received, realigned_imu_seq
from hil.record.matching import TAIL_NS, Matcher, SeqSet, truncation_notes, verdict
from hil.record.mcapio import (
    PayloadError,
    Record,
    RecordingError,
    Session,
    SessionStream,
    cut_notes,
    first_of_its_session,
    no_run_message,
    session_note,
)
from hil.runners.sim_worker import (
    EncodedInput,
    LocalNode,
    RemoteNode,
    Replayed,
    replay_encoded,
    worker_pays,
    worker_possible,
)
from hil.runtime import jit
from hil.runtime.heap import freeze_command_startup

FUSION_CONFIG_EVENT = "fusion_config"  # how recordings before hil.FusionSettings said it


def config_of_record(r: Record) -> FusionConfig | None:
    """The fusion's configuration if ``r`` says it: ``fusion/config``, or the legacy event."""
    if r.topic.endswith("/fusion/config"):
        return FusionConfig.from_settings(decode(FusionSettings, r.payload))
    if "/event/" in r.topic:
        ev = r.decode()
        if isinstance(ev, Event) and ev.kind == FUSION_CONFIG_EVENT:
            d = json.loads(ev.detail)
            return FusionConfig(
                estimators=tuple(d["estimators"]),
                lag_ns=int(d["lag_ns"]),
                output_every=int(d["output_every"]),
            )
    return None


def fusion_config_from(session: Session) -> FusionConfig:
    for r in session.records:
        cfg = config_of_record(r)
        if cfg is not None:
            return cfg
    raise RecordingError(f"{session.path}: no fusion configuration (fusion/config): the fusion did not run")


def run_info_from(session: Session) -> RunInfo:
    for r in session.records:
        if r.topic.endswith("/run"):
            m = r.decode()
            assert isinstance(m, RunInfo)
            return m
    raise RecordingError(f"{session.path}: no RunInfo (hil/<rig>/run): not a rig session")


@dataclass
class RerunResult:
    recomputed: list[NavSolution]  # every recomputed output, only when asked for (``keep_outputs``)
    n_recorded: int  # recorded outputs of the fusion's estimators
    n_recomputed: int
    inputs_used: int
    inputs_dropped: int
    live_consumed: int = -1  # the last journal's count of inputs the live fusion consumed
    difference: str | None = None
    # a truncated file: the difference leaving out what the cut made unverifiable (below)
    difference_if_cut: str | None = None
    unverified: int = 0  # recorded outputs near the cut whose inputs the cut took
    restarts: int = 0  # fusion restarts: each later life rerun from its re-alignment
    # the recording lacks inputs the live fusion took (its journals count them): the outputs in
    # each (from, to) span of rig time are not verifiable (``after_loss`` of them differ)
    lost_spans: list[tuple[int, int]] = field(default_factory=list)
    after_loss: int = 0

    def first_difference(self, truncated: bool = False) -> str | None:
        return self.difference_if_cut if truncated else self.difference

    @property
    def excused(self) -> int:
        return self.after_loss


class OutOfWindow(Exception):
    """The file's order defeats the streaming window: rerun it with the whole file instead."""


def _nav_difference(key: tuple[str, int], recorded: bytes, mine: bytes) -> str:
    est, seq = key
    theirs = msgspec.json.decode(recorded)
    ours = msgspec.json.decode(mine)
    for k in ours:
        if ours.get(k) != theirs.get(k):
            return (
                f"nav/{est} seq {seq}: field {k!r} differs: "
                f"recorded {theirs.get(k)!r}, recomputed {ours.get(k)!r}"
            )
    return f"nav/{est} seq {seq}: payload bytes differ"


def _nav_current_form(payload: bytes) -> bytes:
    """A recorded solution in the form today's encoder writes: the same values, the same bytes."""
    return encoded_today(NavSolution, payload)


def _stream(sensor: str, publisher: str) -> str:
    """One publisher's stream of one sensor's inputs (what a seq is unique within)."""
    return f"{sensor}@{publisher}"


RERUN_WINDOW_S = 30.0  # rig time held while streaming: inputs arrive within fractions of a second of order
# inputs a worker recomputes per message (~10 s of a 400 Hz IMU): while it runs them, this
# process reads, decodes and orders the next ones and compares the last ones' solutions
REPLAY_BATCH = 4096
# with a share of the estimators in this process: it runs a batch's share only once the worker has
# run that batch (for the gate's verdicts), so the worker idles on the first batch and this process
# runs the last alone; half the batch halves both (uav_survey 120 s: 2.99-3.12 s against
# 3.08-3.34 s, three runs each, 2026-12-06)
REPLAY_BATCH_HERE = 2048
# the first batch a worker is sent: the sizes double from there, so the pipeline fills in a few
# milliseconds instead of a whole batch's work (uav_survey 120 s: the first batch held this process
# ~0.1 s)
REPLAY_BATCH_FIRST = 128
# two workers share the estimators when there are at least twice this many, by default on this
# many CPUs (see ``split_estimators``)
SPLIT_MIN_EACH = 2
SPLIT_MIN_CPUS = 3
# an estimator's share of the work per IMU sample, to balance the shares: in-process reruns of
# 40 s of uav_survey with one estimator each, less the free INS alone (2026-12-05): ekf15
# 0.35-0.47 s, a compensation filter with its feedback INS 0.28-0.38 s, kfvel 0.19-0.27 s
_WEIGHTS = {"ekf15": 4, "kfvel": 2}
_WEIGHT = 3


def split_estimators(cfg: FusionConfig, here: bool = False) -> tuple[tuple[str, ...], tuple[str, ...]] | None:
    """Two shares of the configuration's estimators for two workers that each run the whole core
    on every input (the free INS, the output predictor, the reorder buffer: the same in both).
    ``here``: the second share is run by the process that also reads the file and compares the
    solutions (``hil rerun`` on two CPUs), so it takes the least it can, the ``SPLIT_MIN_EACH``
    lightest (2026-12-06, wall time: uav_survey 120 s with kfvel and comp1 here 2.98-3.01 s, with
    cf3 too 2.86-3.19 s; straight_level 300 s 4.97-5.09 s against 5.35-5.37 s with three here).

    Each estimator's state depends on the inputs and on the GNSS gate's verdicts only, and a
    verdict depends on the gate's reference estimator (whose prediction decides for all) or, when
    it has none, on each estimator's own. So the reference runs in the first share only, which
    keeps its verdicts; the second takes them (``hil.runners.sim_worker.replay_split``) one
    batch behind, and each share computes every one of its estimators exactly as one core does.
    Only with the output predictor (one solution per estimator per output, in the
    configuration's order; the merge relies on it). None: nothing worth sharing."""
    if not cfg.output_predictor or len(cfg.estimators) < 2 * SPLIT_MIN_EACH:
        return None
    ref = cfg.gnss_gate_reference if cfg.gnss_gate_reference in cfg.estimators else ""
    order = {name: i for i, name in enumerate(cfg.estimators)}
    if here:
        rest = sorted(
            (e for e in cfg.estimators if e != ref), key=lambda e: (_WEIGHTS.get(e, _WEIGHT), order[e])
        )
        light = set(rest[:SPLIT_MIN_EACH])
        a = tuple(e for e in cfg.estimators if e not in light)
        return a, tuple(e for e in cfg.estimators if e in light)
    shares: tuple[list[str], list[str]] = ([ref] if ref else [], [])
    load = [1 + (_WEIGHTS.get(ref, _WEIGHT) if ref else 0), 0]  # the first publishes the free INS too
    for e in sorted((e for e in cfg.estimators if e != ref), key=lambda e: -_WEIGHTS.get(e, _WEIGHT)):
        i = 0 if load[0] < load[1] else 1
        shares[i].append(e)
        load[i] += _WEIGHTS.get(e, _WEIGHT)
    if len(shares[1]) < SPLIT_MIN_EACH:
        return None
    a, b = (tuple(sorted(share, key=order.__getitem__)) for share in shares)
    return a, b


def share_here_pays(cfg: FusionConfig) -> bool:
    """Whether this process should take a share of the estimators beside its reading (on two
    CPUs): when the estimators' work outweighs the reading it then competes with. The second
    share repeats the core's common part (the free INS, the predictor), so the worker's share
    must be worth more than this process's reading for it to pay: with a consumer IMU's
    configuration (the filters in feedback form, each with its own INS and corrector, and ekf15's
    33 states) it is; with a tactical one (open-loop filters, 15 states) it is not, or barely.
    Against one worker, 2026-12-06, medians of the wall time (four alternating pairs, or three):
    uav_survey 120 s 0.91x, car_drive 120 s 0.92x; static 90 s 1.15x, long_flight 90 s 1.08x,
    straight_level 90 s 0.98x, straight_level 300 s 0.91x."""
    return bool(cfg.feedback) or bool(cfg.ekf_calibration)


#: each input's solutions, as a core replays a batch
_Solutions = list[list[Replayed]]
#: an input on its way to a worker: message, publisher, predicted, and its payload as recorded
_Pending = tuple[Measurement, str, bool, bytes]


def _decoded(batch: list[_Pending]) -> list[tuple[Measurement, str, bool]]:
    """A batch as this process's share runs it (``LocalNode``): the messages already decoded."""
    return [item[:3] for item in batch]


def _encoded(batch: list[_Pending]) -> list[EncodedInput]:
    """A batch as a worker is sent it (``EncodedInput``): the recorded bytes, decoded there."""
    return [(payload, type(m), source, predicted) for m, source, predicted, payload in batch]


@dataclass
class _FusionRerun:
    """The state of one fusion rerun over a stream of records (see ``rerun_fusion_records``)."""

    window_ns: int | None
    keep_outputs: bool
    worker: bool | None = None  # the fusion in a forked worker; None: when it pays (``_start``)
    # with a worker: two, the estimators shared between them (``split_estimators``); None: on
    # SPLIT_MIN_CPUS CPUs, when the configuration has enough to share
    split: bool | None = None
    run: RunInfo | None = None
    cfg: FusionConfig | None = None
    node: FusionNode | None = None
    produced: set[str] = field(default_factory=set)
    early_nav: list[Record] = field(default_factory=list)  # outputs before the config said whose
    # (total-order key, push count, message, publisher, payload as recorded: what a worker is sent)
    heap: list[tuple[tuple[int, int, int], int, Measurement, str, bytes]] = field(default_factory=list)
    present: Counter[str] = field(default_factory=Counter)  # copies of each input still in the heap
    dropped: Counter[str] = field(default_factory=Counter)
    unpredicted: set[str] = field(default_factory=set)  # IMU samples the live predictor did not take
    rerun_ids: SeqSet = field(default_factory=SeqSet)
    last_key: tuple[int, int, int] | None = None
    newest_ns: int = -(2**63)
    pushed: int = 0
    used: int = 0
    n_out: int = 0
    outputs: list[NavSolution] = field(default_factory=list)
    last_log_ns: int = 0
    last_journal_log_ns: int = -1  # log time of the last journal record read
    matcher: Matcher = field(init=False)
    remote: RemoteNode | None = None
    # ``split`` with the second share in this process (``LocalNode``); None: on two CPUs, for
    # a heavy configuration (``share_here_pays``)
    here: bool | None = None
    batch_size: int = 0  # inputs a worker is sent at a time (``_start``)
    # the next batch's size: from REPLAY_BATCH_FIRST, doubled up to ``batch_size`` (a worker's
    # first batch, or this process's share of the last, is run while the other side waits)
    sending: int = 0
    # with two workers: the second (or this process's share), each one's estimators (``only``),
    # and every solution's place in one core's output of an input (the free INS, then the
    # configuration's order)
    remote2: RemoteNode | LocalNode | None = None
    shares: tuple[frozenset[str], frozenset[str]] | None = None
    rank: dict[str, int] = field(default_factory=dict)
    # for the worker: (message, publisher, predicted, payload as recorded)
    batch: list[_Pending] = field(default_factory=list)
    # the batches sent to the (first) worker whose solutions are not read yet: the next one is sent
    # before the last one's are read, so the worker never waits for this process between two
    ahead: deque[list[_Pending]] = field(default_factory=deque)
    # split: the batch the second worker runs, with the first's solutions of it
    in_flight_b: tuple[list[_Pending], list[list[Replayed]]] | None = None
    # a restarted fusion (its ``realigned`` event): the current life's re-alignment (align_ns,
    # first output seq), and the IMU seq of one whose sample is not read yet (``_try_realign``)
    realigned: tuple[int, int] | None = None
    realign_pending: int | None = None
    # its event's first input received per stream before that sample (None: an older recording)
    realign_firsts: dict[tuple[str, str], int] | None = None
    restarts: int = 0
    pushed_released: int = -1  # the push count of the last input rerun
    # for ``_lost_spans``: each journal as (its fusion's session, watermark, consumed); the
    # sessions of the restarted fusions, in order; each life's start and the stamps it was fed
    journal_marks: list[tuple[str, int, int]] = field(default_factory=list)
    realigned_sessions: list[str] = field(default_factory=list)
    life_starts_ns: dict[int, int] = field(default_factory=dict)
    fed_stamps: dict[int, array[int]] = field(default_factory=dict)  # 8 bytes an input

    def __post_init__(self) -> None:
        self.matcher = Matcher(self._difference, "recomputed", self.window_ns, _nav_current_form)
        self.nav_topics: dict[str, str] = {}  # estimator -> its recorded topic

    def _difference(self, key: tuple[str, int], recorded: bytes, mine: bytes) -> str:
        """``_nav_difference``; a recorded payload that does not decode is a damaged file, not a
        difference: ``PayloadError`` naming the message (its topic, seq, log time)."""
        try:
            return _nav_difference(key, recorded, mine)
        except (msgspec.DecodeError, msgspec.ValidationError) as err:
            est, seq = key
            topic = self.nav_topics.get(est, f"nav/{est}")
            rec = Record(topic, "hil.NavSolution", recorded, self.matcher.describing_log_ns, 0, seq)
            raise PayloadError(rec, str(err)) from None

    def feed(self, r: Record) -> None:
        t = r.topic
        if r.skipped_log_ns > self.last_log_ns:  # the rig's messages a filtering reader left out
            self.last_log_ns = r.skipped_log_ns
        if r.foreign:  # the live fusion refused a stranger's inputs (``refuses_foreign``), and
            return  # they are not its outputs, journal or configuration, nor the rig's run
        self.last_log_ns = max(self.last_log_ns, r.log_time_ns)
        if "/synced/" in t:
            self._synced(r)
        elif "/nav/" in t:
            if self.cfg is None:
                self.early_nav.append(r)
            else:
                self._recorded_nav(r)
        elif t.endswith("/fusion/journal"):
            self._journal(r)
        elif self.run is None and t.endswith("/run"):
            m = r.decode()
            assert isinstance(m, RunInfo)
            self.run = m
        elif self.cfg is None and (cfg := config_of_record(r)) is not None:
            self.cfg = cfg
            self.produced = {FREE_INS, *cfg.estimators}
            for early in self.early_nav:
                self._recorded_nav(early)
            self.early_nav.clear()
        elif t.endswith("/event/fusion"):  # (the legacy configuration event: the branch above)
            self._realigned_event(r)
        if self.node is None and self.run is not None and self.cfg is not None:
            self._start(FusionNode.for_rerun(self.run, self.cfg))
        if self.realign_pending is not None and self.node is not None:
            self._try_realign()

    def _realigned_event(self, r: Record) -> None:
        """A restarted fusion's ``realigned`` event: a new life of the fusion from the IMU sample
        it names (``_try_realign``, once that sample is read)."""
        ev = r.decode()
        if not isinstance(ev, Event) or ev.kind != "realigned":
            return
        seq = realigned_imu_seq(ev.detail)
        if seq is None:
            raise RecordingError(
                f"{r.topic} seq {ev.seq}: a realigned event that names no IMU sample "
                f"({ev.detail!r}): the restarted fusion's inputs cannot be told"
            )
        self.realign_pending = seq
        self.realign_firsts = realigned_first_received(ev.detail)
        self.realigned_sessions.append(r.publisher.partition(":")[0])

    def _try_realign(self) -> None:
        """The life before the re-alignment ended: its inputs through the old core, then a new core
        aligned where the event says (``FusionNode.for_rerun``) for the restarted fusion's.

        Which inputs those are follows from how it took them: it held what it received until
        the first IMU sample (``first``), kept of that what is stamped at or after the alignment,
        and took everything after that is (less what it journaled as dropped; ``release`` leaves
        out the rest: refused if it came, and whether it came is chance). Its event names the
        first input of each stream it received before ``first``: it received every later one of
        that stream (one publisher, one link: in seq order), none published before ``first`` of
        a stream it does not name, and everything published after ``first`` (the aiding
        streams' subscriptions are declared before the IMU's on its one session) -- the file
        holds the time sync's messages in the order they were published, and the heap's push
        count is that order. A recording made before the event named them is read by inference:
        what was published after the IMU sample before ``first``, which it did not receive
        (wrong for a fix published just before the subscription to the fixes took effect)."""
        seq = self.realign_pending
        heap = self.heap
        found = [e for e in heap if e[2].sensor == "imu" and e[2].seq == seq]
        if not found or self.cfg is None or self.run is None:
            return  # its sample is not read yet
        self.realign_pending = None
        first = min(found, key=lambda e: e[1])
        point = realign_point(first[2], self.cfg.output_every)  # type: ignore[arg-type]
        firsts = self.realign_firsts
        before = [e[1] for e in heap if e[2].sensor == "imu" and e[1] < first[1]]
        # no sample before it held: the last one rerun, or none at all (it took everything)
        received_after = max(before) if before else (-1 if self.last_key is None else self.pushed_released)

        def received(e: tuple[Any, int, Measurement, str, bytes]) -> bool:
            if firsts is None:
                return e[1] > received_after
            from_seq = firsts.get((e[2].sensor, e[3]))
            return from_seq is not None and e[2].seq >= from_seq

        def taken(e: tuple[Any, int, Measurement, str, bytes]) -> bool:
            if e[1] >= first[1]:
                return True
            return received(e) and not before_alignment(e[2].stamp_ns, point[0])

        later: list[tuple[Any, int, Measurement, str, bytes]] = []
        earlier: list[tuple[Any, int, Measurement, str, bytes]] = []
        for e in heap:
            (later if taken(e) else earlier).append(e)
        self.heap = earlier
        heapq.heapify(self.heap)
        self.release(None)  # the old life's inputs, and every worker drained
        self.close()
        self.remote = self.remote2 = None
        self.heap = later
        heapq.heapify(self.heap)
        self.last_key, self.realigned = None, point
        self.restarts += 1
        self.life_starts_ns[self.restarts] = point[0]
        self._start(FusionNode.for_rerun(self.run, self.cfg, point))

    def _start(self, node: FusionNode) -> None:
        """The core, here or in a worker (``worker_pays``, as ``hil sim`` decides), or in two
        that share its estimators: the kernels are compiled where it runs, with the same bits."""
        self.node = node
        self.batch_size = REPLAY_BATCH
        self.sending = REPLAY_BATCH_FIRST
        if not (self.worker if self.worker is not None else worker_pays(node)):
            jit.enable()
            freeze_command_startup()
            return
        cfg, run = self.cfg, self.run
        many = worker_possible(SPLIT_MIN_CPUS)
        here = self.here
        if here is None:
            here = self.split is None and not many and cfg is not None and share_here_pays(cfg)
        split = here or (self.split if self.split is not None else many)
        shares = split_estimators(cfg, here) if cfg is not None and split else None
        if shares is None or cfg is None or run is None:
            self.remote = RemoteNode(node, setup=jit.enable_for_run)
            freeze_command_startup()
            return
        from dataclasses import replace

        a, b = shares
        self.shares = frozenset({FREE_INS, *a}), frozenset(b)
        self.rank = {name: i for i, name in enumerate((FREE_INS, *cfg.estimators))}
        setup = jit.enable_for_run
        if here:  # the kernels loaded once, before the fork: the worker has them too
            jit.enable()
            self.batch_size = REPLAY_BATCH_HERE
            self.remote2 = LocalNode(FusionNode.for_rerun(run, replace(cfg, estimators=b), self.realigned))
        self.remote = RemoteNode(
            FusionNode.for_rerun(run, replace(cfg, estimators=a), self.realigned), setup=setup
        )
        if not here:
            self.remote2 = RemoteNode(
                FusionNode.for_rerun(run, replace(cfg, estimators=b), self.realigned), setup=setup
            )
        freeze_command_startup()

    def _synced(self, r: Record) -> None:
        m = r.decode()
        key = input_key(m)  # type: ignore[arg-type]
        seen = (_stream(m.sensor, r.publisher), m.seq) in self.rerun_ids  # type: ignore[attr-defined]
        if self.last_key is not None and (key < self.last_key or seen):
            raise OutOfWindow(f"{r.topic} seq {m.seq} comes after later inputs were rerun")  # type: ignore[attr-defined]
        self.present[input_id(m, r.publisher)] += 1  # type: ignore[arg-type]
        heapq.heappush(self.heap, (key, self.pushed, m, r.publisher, r.payload))  # type: ignore[arg-type]
        self.pushed += 1
        self.newest_ns = max(self.newest_ns, m.stamp_ns)
        if self.realign_pending == m.seq and m.sensor == "imu" and self.node is not None:  # type: ignore[attr-defined]
            self._try_realign()
        if self.node is not None and self.window_ns is not None:
            self.release(self.newest_ns - self.window_ns)

    def _recorded_nav(self, r: Record) -> None:
        est = r.topic.rsplit("/", 1)[1]
        if est not in self.produced:
            return  # nav/<dut> and other non-fusion solutions are not the core's
        w = self.window_ns
        if self.last_key is not None and w is not None and r.publish_time_ns < self.last_key[0] - w:
            raise OutOfWindow(f"{r.topic} seq {r.sequence} is recorded long after its inputs")
        # a recording made before the current form of NavSolution (``null`` for an absent sigma)
        # is compared in the current form (the matcher's ``normalise``, where the bytes differ)
        self.nav_topics[est] = r.topic
        self.matcher.recorded((est, r.sequence), r.payload, -1, r.log_time_ns)

    def _journal(self, r: Record) -> None:
        j = r.decode()
        assert isinstance(j, FusionJournal)
        self.last_journal_log_ns = max(self.last_journal_log_ns, r.log_time_ns)
        # each life of the fusion (a process, a Zenoh session) counts its own
        self.journal_marks.append((r.publisher.partition(":")[0], j.watermark_ns, j.consumed))
        for d in j.dropped:
            _why, name, source = parse_journal_id(d)
            sensor, _, seq = name.partition(":")
            if seq.isdigit() and (_stream(sensor, source), int(seq)) in self.rerun_ids:
                raise OutOfWindow(f"the journal drops {d} after it was rerun")
            self.dropped[f"{name}@{source}" if source else name] += 1
        for u in j.unpredicted:
            name, _, source = u.partition("@")
            sensor, _, seq = name.partition(":")
            if seq.isdigit() and (_stream(sensor, source), int(seq)) in self.rerun_ids:
                raise OutOfWindow(f"the journal names {u} unpredicted after it was rerun")
            self.unpredicted.add(u)

    def release(self, upto_ns: int | None) -> None:
        """Inputs older than ``upto_ns`` (all: None), in the total order, through the core."""
        node = self.node
        assert node is not None
        heap = self.heap
        fed = self.fed_stamps.setdefault(self.restarts, array("q"))
        while heap and (upto_ns is None or heap[0][0][0] < upto_ns):
            key, n, msg, source, payload = heapq.heappop(heap)
            self.last_key, self.pushed_released = key, n
            stream = _stream(msg.sensor, source)
            if (stream, msg.seq) in self.rerun_ids:
                continue  # a second copy of an input already decided
            i = input_id(msg, source)
            if self.realigned is not None and before_alignment(msg.stamp_ns, self.realigned[0]):
                # valid before this life's re-alignment: refused if it reached the restarted
                # fusion (journaled ``prealign``), or never received -- its subscription to that
                # stream took effect later than the IMU's -- and not taken either way
                self.present.pop(i, None)
                continue
            self.rerun_ids.add(stream, msg.seq)
            if self.present.pop(i) - self.dropped[i] <= 0:
                continue
            self.used += 1
            fed.append(key[0])
            predicted = i not in self.unpredicted
            if self.remote is None:
                self._compare(msg, replay_encoded(node, [(msg, source, predicted)], self.keep_outputs)[0])
                continue
            self.batch.append((msg, source, predicted, payload))
            if len(self.batch) >= self.sending:
                self._send_batch()
                self.sending = min(2 * self.sending, self.batch_size)
        if upto_ns is None:  # the end: what the worker still holds
            self.drain()

    def _compare(self, msg: Measurement, sols: list[Replayed]) -> None:
        """One input's recomputed solutions against the recorded ones."""
        m = self.matcher
        for est, seq, payload, stamp_ns, sol in sols:
            if sol is not None:
                self.outputs.append(sol)
            if est in self.produced:
                m.recomputed((est, seq), payload, self.n_out, stamp_ns)
            self.n_out += 1
        m.release_before(msg.stamp_ns)  # the total order's first key

    def _send_batch(self) -> None:
        """The batch to the worker, then the solutions of the one before it compared (all of them
        once there is nothing more to send: the end)."""
        assert self.remote is not None
        if self.remote2 is not None:
            self._send_split()
            return
        keep = 0
        if self.batch:
            self.remote.replay(_encoded(self.batch), self.keep_outputs)
            self.ahead.append(self.batch)
            self.batch, keep = [], 1
        while len(self.ahead) > keep:
            for (msg, *_), sols in zip(self.ahead.popleft(), self.remote.replayed(), strict=True):
                self._compare(msg, sols)

    def _send_split(self) -> None:
        """Two cores: the first (with the gate's reference) a batch or two ahead of the second,
        which takes a batch with the first's gate verdicts on it. The first is sent batch N + 1
        before its solutions of N are read, so it goes from one to the next without waiting; the
        second runs N (a worker; ``LocalNode``: this process, at once) once they are, while
        this process reads N + 2 and compares N - 1. (Neither side waits for ever on the other:
        one waiting for room in its ring takes in what the other says, ``_Link``.)"""
        a, b, shares = self.remote, self.remote2, self.shares
        assert a is not None and b is not None and shares is not None
        keep = 0
        if self.batch:
            a.replay(_encoded(self.batch), self.keep_outputs, shares[0], verdicts=True)
            self.ahead.append(self.batch)
            self.batch, keep = [], 1
        done_a = (self.ahead.popleft(), *a.replayed_split()) if len(self.ahead) > keep else None
        if self.in_flight_b is not None:
            self._merge(*self.in_flight_b, b.replayed())
            self.in_flight_b = None
        if done_a is not None:
            batch, sols_a, verdicts = done_a
            inputs = _decoded(batch) if isinstance(b, LocalNode) else _encoded(batch)
            b.replay(inputs, self.keep_outputs, shares[1], relay=verdicts or {})
            self.in_flight_b = (batch, sols_a)

    def _merge(self, batch: list[_Pending], sols_a: _Solutions, sols_b: _Solutions) -> None:
        """The two shares' solutions of each input, in one core's order, compared."""
        rank = self.rank.__getitem__
        for (msg, *_), x, y in zip(batch, sols_a, sols_b, strict=True):
            self._compare(msg, sorted(x + y, key=lambda sol: rank(sol[0])))

    def drain(self) -> None:
        """Every input handed to the worker(s) recomputed and compared."""
        if self.remote is not None:
            while self.batch or self.ahead or self.in_flight_b is not None:
                self._send_batch()

    def close(self) -> None:
        for remote in (self.remote, self.remote2):
            if remote is not None:
                remote.close()

    def result(self) -> RerunResult:
        m = self.matcher
        unannounced = self._unannounced_lives()
        spans = self._lost_spans() if self.realign_pending is None and not unannounced else []
        diff, after_loss = (m.first[1] if m.first else None), 0
        missing = sorted(m.recorded_pending)
        if spans:
            diff, after_loss, missing = self._before_loss(spans, missing)
        if self.realign_pending is not None:  # its outputs were rerun as the life before's: no verdict
            diff = (
                f"the fusion restarted at imu seq {self.realign_pending} (its realigned event), which the "
                "recording lacks: the restarted fusion's inputs and alignment cannot be told"
            )
        elif unannounced:
            diff = (
                f"the fusion's journal comes from {len(unannounced)} restarted process(es) more than the "
                f"recording has realigned events for (Zenoh session {unannounced[0]}): a restarted "
                "fusion's inputs and alignment cannot be told without its event"
            )
        if diff is None and missing:
            est, seq = missing[0]
            diff = f"nav/{est} seq {seq}: recorded but not recomputed ({len(missing)} such outputs)"
        if diff is None and m.compared == 0:
            diff = "the recording holds no fusion outputs to compare"
        n_dropped = sum(self.dropped.values())
        if_cut, unverified = self._if_cut()
        return RerunResult(
            self.outputs,
            m.n_recorded,
            self.n_out,
            self.used,
            n_dropped,
            self._live_consumed(),
            diff,
            if_cut,
            unverified,
            self.restarts,
            spans,
            after_loss,
        )

    def _live_consumed(self) -> int:
        """What the live fusion consumed, by its journals: each life's last count, summed (-1: no
        journal)."""
        last: dict[str, int] = {}
        for session, _w, consumed in self.journal_marks:
            last[session] = max(last.get(session, -1), consumed)
        return sum(last.values()) if last else -1

    def _lost_spans(self) -> list[tuple[int, int]]:
        """Where the recording lacks inputs the live fusion took: a journal counts the inputs its
        fusion consumed up to its watermark, so the first one of a life counting more than this
        rerun fed up to there has the loss between its watermark and the one before (or the
        life's start); the outputs from there to the next life's re-alignment (a fresh start)
        are not verifiable. [] : the recording holds all it consumed."""
        lives = {session: k + 1 for k, session in enumerate(self.realigned_sessions)}
        marks: dict[int, list[tuple[int, int]]] = {}
        for session, watermark_ns, consumed in self.journal_marks:
            if watermark_ns > -(2**61):  # (a journal before anything was released: no watermark yet)
                marks.setdefault(lives.get(session, 0), []).append((watermark_ns, consumed))
        spans = []
        for life, life_marks in sorted(marks.items()):
            fed = self.fed_stamps.get(life, array("q"))
            before = self.life_starts_ns.get(life, fed[0] if fed else 0)
            for watermark_ns, consumed in sorted(life_marks):
                if consumed > bisect.bisect_right(fed, watermark_ns):
                    spans.append((before, self.life_starts_ns.get(life + 1, 2**62)))
                    break
                before = watermark_ns
        return spans

    def _unannounced_lives(self) -> list[str]:
        """Fusion processes (Zenoh sessions of its journal) after the first that announced no
        re-alignment: a restart whose ``realigned`` event the recording lacks."""
        sessions = list(dict.fromkeys(session for session, _w, _c in self.journal_marks))
        return [s for s in sessions[1:] if s not in self.realigned_sessions]

    def _before_loss(
        self, spans: list[tuple[int, int]], missing: list[tuple[str, int]]
    ) -> tuple[str | None, int, list[tuple[str, int]]]:
        """The first difference among the outputs outside the loss ``spans`` (``_lost_spans``),
        how many in them could not be verified, and the recorded outputs outside them not
        recomputed."""
        m = self.matcher

        def lost(t_ns: int) -> bool:
            return any(a < t_ns < b for a, b in spans)

        after = m.excuse(lost)
        diff = m.first[1] if m.first else None
        kept = []
        for key in missing:
            try:
                stamp = decode(NavSolution, m.recorded_pending[key][1]).stamp_ns
            except (msgspec.DecodeError, msgspec.ValidationError):
                stamp = -(2**62)
            if lost(stamp):
                after += 1
            else:
                kept.append(key)
        return diff, after, kept

    def _if_cut(self) -> tuple[str | None, int]:
        """The verdict on a file cut short, which can leave two kinds of outputs unverifiable:
        one recorded before an input that the cut took (within ``TAIL_NS`` of the end), and one
        recorded after the last journal, whose drops (inputs the live fusion skipped) the cut
        took with the next journal. Everything recorded before those is verified as usual."""
        m = self.matcher
        cut_ns = self.last_log_ns - TAIL_NS
        early = m.pending_before(cut_ns)
        unverified = len(m.recorded_pending) - len(early)
        unverified += sum(1 for t in m.diff_logs if t >= self.last_journal_log_ns)
        first = m.first_by_log
        if first is not None and first[0] < self.last_journal_log_ns:
            return first[1], unverified
        if early:
            est, seq = early[0]
            return f"nav/{est} seq {seq}: recorded but not recomputed ({len(early)} such outputs)", unverified
        if m.compared == 0:
            return "the part of the file that exists holds no fusion outputs to compare", unverified
        return None, unverified


def rerun_fusion_records(
    records: Iterable[Record],
    *,
    window_ns: int | None,
    keep_outputs: bool = False,
    name: str = "recording",
    worker: bool | None = None,
    split: bool | None = None,
    here: bool | None = None,
) -> RerunResult:
    """The fusion rerun over records in file order, holding ``window_ns`` of rig time at most.

    The recorded synchronised inputs go to a fresh fusion core (``FusionNode.replay``) in the
    total order ``input_key``, each once the newest input seen is ``window_ns`` ahead of it
    (``None``: after the last record, i.e. a sort of the whole file), minus those the live
    fusion journaled as dropped: an input recorded n times and journaled as dropped d times was
    consumed max(n - d, 0) times (0 or 1). Streaming gives what sorting the whole file gives as
    long as no input comes more than the window behind a newer one, no journal drops an input
    already rerun, no second copy of a rerun input comes, and no recorded output comes more than
    the window after its inputs; each is checked and raises ``OutOfWindow``. Live inputs are out
    of order by the fusion's lag (0.2 s) and journals follow within a second, so the default 30 s
    never trips on a rig session.

    ``worker``: the core in a forked worker (``hil.runners.sim_worker``), fed ``REPLAY_BATCH``
    inputs at a time, while this process reads and orders the next ones and compares the
    solutions back; the same inputs in the same order through the same code, so the same bits.
    None: when it pays (``_FusionRerun._start``); False: in this process. ``split``: with a
    worker, two that share the estimators (``split_estimators``), their solutions merged into
    one core's order; None: on ``SPLIT_MIN_CPUS`` CPUs, if the configuration has enough to share.
    ``here``: the second share in this process instead of a second worker (``LocalNode``), run on
    each batch while the worker runs the next; None: when ``split`` is None, fewer than
    ``SPLIT_MIN_CPUS`` CPUs are there (two: a second worker would share them with this process)
    and the configuration's estimators are heavy enough (``share_here_pays``).
    """
    state = _FusionRerun(window_ns, keep_outputs, worker, split, here=here)
    try:
        for r in records:
            state.feed(r)
        if state.run is None:
            raise RecordingError(no_run_message(name, records))
        if state.node is None:
            raise RecordingError(f"{name}: no fusion configuration (fusion/config): the fusion did not run")
        if state.pushed == 0 and state.matcher.n_recorded:  # outputs but none of their inputs
            raise RecordingError(
                f"{name}: it holds the fusion's outputs but none of its inputs (synced/*): its recorder's "
                "--record-include/--record-exclude left them out, or they were all lost; nothing to rerun"
            )
        tail = getattr(records, "skipped_tail", None)
        if tail is not None:  # the file's last messages were left out by the reader
            state.last_log_ns = max(state.last_log_ns, tail[0])
        state.release(None)
        return state.result()
    finally:
        state.close()


def fusion_topic(topic: str) -> bool:
    """The topics ``rerun_fusion_records`` does more with than read their log time: what a
    filtering reader must give it (``SessionStream(keep=...)``)."""
    return (
        "/synced/" in topic
        or "/nav/" in topic
        or "/event/" in topic
        or topic.endswith(("/run", "/fusion/journal", "/fusion/config"))
    )


def rerun_fusion(session: Session) -> RerunResult:
    """The fusion rerun of a recording already in memory (every recomputed output kept)."""
    return rerun_fusion_records(session.records, window_ns=None, keep_outputs=True, name=str(session.path))


def rerun_fusion_file(
    path: str | Path,
    *,
    window_s: float | None = RERUN_WINDOW_S,
    on_progress: Any = None,
    worker: bool | None = None,
    split: bool | None = None,
    here: bool | None = None,
) -> tuple[RerunResult, SessionStream, str]:
    """Stream a recording through the fusion rerun; if its order defeats the window, read it whole.

    Returns the result, the stream (truncation, metadata) and a note ("" or why the whole file
    was needed).
    """
    stream = SessionStream(path, on_progress, follow_parts=True, keep=fusion_topic)
    window_ns = None if window_s is None else round(window_s * 1e9)
    cores = {"worker": worker, "split": split, "here": here}
    try:
        res = rerun_fusion_records(stream, window_ns=window_ns, name=str(path), **cores)
        return res, stream, ""
    except OutOfWindow as why:
        stream = SessionStream(path, on_progress, follow_parts=True, keep=fusion_topic)
        res = rerun_fusion_records(stream, window_ns=None, name=str(path), **cores)
        note = f"{why} (out of order by more than {window_s:g} s): reran with the whole file in memory"
        return res, stream, note


def rerun(
    path: str,
    *,
    core: str = "fusion",
    verify: bool = False,
    on_progress: Any = None,
    worker: bool | None = None,
    split: bool | None = None,
    here: bool | None = None,
) -> tuple[int, list[str]]:
    """Exit code and report lines for ``hil rerun``.

    The file is streamed (``SessionStream``): memory stays at seconds of data whatever the
    length of the recording. ``on_progress(bytes_read, file_bytes)``.
    """
    first = first_of_its_session(Path(path))
    if first is not None:  # a later file alone has no run start, configuration or first inputs
        return 2, [
            f"hil rerun: {path} is a later file of the session that begins in {first}: rerun that "
            "file, which reads the whole session in order"
        ]
    if core == "timesync":
        from hil.record.rerun_timesync import rerun_timesync_report

        return rerun_timesync_report(path, verify, on_progress, worker)
    if core != "fusion":
        return 2, [f"hil rerun: core {core!r} is not rerunnable (fusion, timesync)"]
    res, stream, note = rerun_fusion_file(
        path, on_progress=on_progress, worker=worker, split=split, here=here
    )
    lines = [
        f"rerun fusion: {res.inputs_used} inputs ({res.inputs_dropped} journaled as dropped), "
        f"{res.n_recomputed} outputs recomputed, {res.n_recorded} recorded"
    ]
    if note:
        lines.append(f"note: {note}")
    many = session_note(stream.paths, "reran")
    lines += [f"note: {n}" for n in ([many] if many else []) + cut_notes(stream.cut_files)]
    if res.restarts:
        lines.append(
            f"note: the fusion restarted {res.restarts} time(s): each restarted process reran from its "
            "re-alignment (its realigned event) on the inputs it took"
        )
    lines += truncation_notes(res, stream.truncated, "outputs", "inputs")
    if res.lost_spans:
        where = ", ".join(
            f"from t={a / 1e9:.3f} s" + (f" to the restart at t={b / 1e9:.3f} s" if b < 2**62 else " on")
            for a, b in res.lost_spans
        )
        lines.append(
            f"note: the recording lacks inputs the live fusion took (its journal counts more than the file "
            f"holds): the outputs {where} are not verifiable, and {res.after_loss} of them differ or are "
            "missing; the others are compared"
        )
    # loss is fewer held than journaled; more is expected in a file that ends (cut, then
    # recovered) after inputs the fusion consumed but had not journaled yet
    if not stream.truncated and 0 <= res.inputs_used < res.live_consumed:
        lines.append(
            f"note: the live fusion journaled {res.live_consumed} consumed inputs, the recording holds only "
            f"{res.inputs_used}: {res.live_consumed - res.inputs_used} inputs were lost between the fusion "
            "and the recorder (see hil info for seq gaps on synced/*)"
        )
    return verdict(res, stream.truncated, lines, verify, "outputs")
