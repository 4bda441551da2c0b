"""``hil rerun FILE --core fusion [--verify]``: recompute a core's outputs from recorded inputs.

Fusion: the recorded synchronised inputs, minus those the live fusion journaled as dropped, in
the total order, through a fresh ``FusionCore.process`` -- then every recomputed ``NavSolution``
is compared byte for byte with the recorded one. The first difference is named (topic, seq,
field, both values).
"""

from __future__ import annotations

import heapq
import json
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from hil.fusion.core import FREE_INS, FusionConfig, FusionCore, input_id, input_key
from hil.messages import Event, FusionJournal, GnssFix, ImuSample, NavSolution, RunInfo, encode
from hil.record.mcapio import Record, RecordingError, Session, SessionStream

FUSION_CONFIG_EVENT = "fusion_config"


def fusion_config_detail(cfg: FusionConfig) -> str:
    return json.dumps(
        {"estimators": list(cfg.estimators), "lag_ns": cfg.lag_ns, "output_every": cfg.output_every}
    )


def fusion_config_from(session: Session) -> FusionConfig:
    for r in session.records:
        if "/event/" in r.topic:
            ev = r.decode()
            assert isinstance(ev, Event)
            if ev.kind == FUSION_CONFIG_EVENT:
                d = json.loads(ev.detail)
                return FusionConfig(
                    estimators=tuple(d["estimators"]),
                    lag_ns=int(d["lag_ns"]),
                    output_every=int(d["output_every"]),
                )
    raise RecordingError(
        f"{session.path}: no '{FUSION_CONFIG_EVENT}' event: the fusion did not run in this session"
    )


def run_info_from(session: Session) -> RunInfo:
    for r in session.records:
        if r.topic.endswith("/run"):
            m = r.decode()
            assert isinstance(m, RunInfo)
            return m
    raise RecordingError(f"{session.path}: no RunInfo (hil/<rig>/run): not a rig session")


class SeqSet:
    """Which (source, seq) pairs were seen: a bit per seq per source, not a Python object each.

    An hour at 400 Hz is 1.4 million IMU seqs: 180 kB here, ~100 MB as a set of tuples. Seqs
    outside the dense range (negative, absurd) go to a small overflow set.
    """

    DENSE_MAX = 1 << 28

    def __init__(self) -> None:
        self._bits: dict[str, bytearray] = {}
        self._other: set[tuple[str, int]] = set()

    def add(self, source: str, seq: int) -> None:
        if 0 <= seq < self.DENSE_MAX:
            bits = self._bits.setdefault(source, bytearray())
            i = seq >> 3
            if i >= len(bits):
                bits.extend(bytes(max(i + 1 - len(bits), len(bits))))
            bits[i] |= 1 << (seq & 7)
        else:
            self._other.add((source, seq))

    def __contains__(self, item: tuple[str, int]) -> bool:
        source, seq = item
        if 0 <= seq < self.DENSE_MAX:
            bits = self._bits.get(source)
            i = seq >> 3
            return bits is not None and i < len(bits) and bool(bits[i] & (1 << (seq & 7)))
        return item in self._other


class Matcher:
    """Pairs recorded outputs with recomputed ones by key while both streams go by.

    Neither side is kept whole: an output is held only until its counterpart shows up, so a
    one-hour rerun holds seconds of outputs, not the hour. Each side gives an ``order`` (file
    position, recompute position); the first difference is the one first in the order of the
    side named by ``by``, as a comparison of two complete lists would name it.

    ``release_before(t)`` lets go of recomputed outputs still unmatched whose ``t_ns`` is older
    than ``t - horizon_ns`` (a recording lacks a few: the recorder stopped first); their keys
    stay in ``released``, so the caller can tell a recorded copy that comes even later.
    """

    def __init__(
        self,
        describe: Callable[[tuple[str, int], bytes, bytes], str],
        by: str,
        horizon_ns: int | None,
    ) -> None:
        self.describe = describe  # (key, recorded, recomputed) -> text of a difference
        self.by_recorded = by == "recorded"
        self.horizon_ns = horizon_ns
        self.recorded_pending: dict[tuple[str, int], tuple[int, bytes]] = {}
        self.recomputed_pending: OrderedDict[tuple[str, int], tuple[int, bytes, int]] = OrderedDict()
        self.released = SeqSet()
        self.n_recorded = 0
        self.compared = 0
        self.first: tuple[int, str] | None = None  # (order, text) of the first difference

    def _compare(self, key: tuple[str, int], rec: tuple[int, bytes], mine: tuple[int, bytes]) -> None:
        self.compared += 1
        if mine[1] != rec[1]:
            order = rec[0] if self.by_recorded else mine[0]
            if self.first is None or order < self.first[0]:
                self.first = (order, self.describe(key, rec[1], mine[1]))

    def recorded(self, key: tuple[str, int], payload: bytes, order: int) -> None:
        if key in self.recorded_pending:
            return  # a recorded duplicate: the first copy counts
        self.n_recorded += 1
        mine = self.recomputed_pending.pop(key, None)
        if mine is not None:
            self._compare(key, (order, payload), (mine[0], mine[1]))
        else:
            self.recorded_pending[key] = (order, payload)

    def recomputed(self, key: tuple[str, int], payload: bytes, order: int, t_ns: int) -> None:
        rec = self.recorded_pending.pop(key, None)
        if rec is not None:
            self._compare(key, rec, (order, payload))
        else:
            self.recomputed_pending[key] = (order, payload, t_ns)

    def release_before(self, t_ns: int) -> None:
        if self.horizon_ns is None:
            return
        limit = t_ns - self.horizon_ns
        while self.recomputed_pending:
            key, (_o, _p, t) = next(iter(self.recomputed_pending.items()))
            if t >= limit:
                break
            del self.recomputed_pending[key]
            self.released.add(*key)


@dataclass
class RerunResult:
    recomputed: list[NavSolution]  # every recomputed output, only when asked for (``keep_outputs``)
    n_recorded: int  # recorded outputs of the fusion's estimators
    n_recomputed: int
    inputs_used: int
    inputs_dropped: int
    live_consumed: int = -1  # the last journal's count of inputs the live fusion consumed
    difference: str | None = None

    def first_difference(self) -> str | None:
        return self.difference


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


def _config_of(ev: Event) -> FusionConfig:
    d = json.loads(ev.detail)
    return FusionConfig(
        estimators=tuple(d["estimators"]), lag_ns=int(d["lag_ns"]), output_every=int(d["output_every"])
    )


def rerun_fusion_records(
    records: Iterable[Record],
    *,
    window_ns: int | None,
    keep_outputs: bool = False,
    name: str = "recording",
) -> RerunResult:
    """The fusion rerun over records in file order, holding ``window_ns`` of rig time at most.

    The recorded synchronised inputs go to a fresh ``FusionCore.process`` in the total order
    ``input_key``, each once the newest input seen is ``window_ns`` ahead of it (``None``: after
    the last record, i.e. a sort of the whole file), minus those the live fusion journaled as
    dropped: an input recorded n times and journaled as dropped d times was consumed
    max(n - d, 0) times (0 or 1). Streaming gives what sorting the whole file gives as long as no
    input comes more than the window behind a newer one, no journal drops an input already
    rerun, no second copy of a rerun input comes, and no recorded output comes more than the
    window after its inputs; each is checked and raises ``OutOfWindow``. Live inputs are out of
    order by the fusion's lag (0.2 s) and journals follow within a second, so the default 30 s
    never trips on a rig session.
    """
    run: RunInfo | None = None
    cfg: FusionConfig | None = None
    core: FusionCore | None = None
    produced: set[str] = set()
    early_nav: list[Record] = []  # outputs read before the fusion's config: whose they are is not known yet
    heap: list[tuple[tuple[int, int, int], int, ImuSample | GnssFix]] = []
    present: Counter[str] = Counter()  # copies of each input still in the heap
    dropped: Counter[str] = Counter()
    rerun_ids = SeqSet()
    last_key: tuple[int, int, int] | None = None
    newest_ns = -(2**63)
    pushed = used = n_out = 0
    live_consumed = -1
    outputs: list[NavSolution] = []
    matcher = Matcher(_nav_difference, "recomputed", window_ns)

    def release(upto_ns: int | None) -> None:
        nonlocal last_key, used, n_out
        assert core is not None
        while heap and (upto_ns is None or heap[0][0][0] < upto_ns):
            key, _n, m = heapq.heappop(heap)
            last_key = key
            if (m.sensor, m.seq) in rerun_ids:
                continue  # a second copy of an input already decided
            rerun_ids.add(m.sensor, m.seq)
            i = input_id(m)
            if present.pop(i) - dropped[i] <= 0:
                continue
            used += 1
            for sol in core.process(m):
                if keep_outputs:
                    outputs.append(sol)
                if sol.estimator in produced:
                    matcher.recomputed((sol.estimator, sol.seq), encode(sol), n_out, sol.stamp_ns)
                n_out += 1
            matcher.release_before(key[0])

    def recorded_nav(r: Record) -> None:
        est = r.topic.rsplit("/", 1)[1]
        if est not in produced:
            return  # nav/<dut> and other non-fusion solutions are not the core's
        if last_key is not None and window_ns is not None and r.publish_time_ns < last_key[0] - window_ns:
            raise OutOfWindow(f"{r.topic} seq {r.sequence} is recorded long after its inputs")
        matcher.recorded((est, r.sequence), r.payload, -1)

    for r in records:
        t = r.topic
        if "/synced/" in t:
            m = r.decode()
            assert isinstance(m, ImuSample | GnssFix)
            key = input_key(m)
            if last_key is not None and (key < last_key or (m.sensor, m.seq) in rerun_ids):
                raise OutOfWindow(f"{t} seq {m.seq} comes after later inputs were rerun")
            present[input_id(m)] += 1
            heapq.heappush(heap, (key, pushed, m))
            pushed += 1
            newest_ns = max(newest_ns, m.stamp_ns)
            if core is not None and window_ns is not None:
                release(newest_ns - window_ns)
        elif "/nav/" in t:
            if cfg is None:
                early_nav.append(r)
            else:
                recorded_nav(r)
        elif t.endswith("/fusion/journal"):
            j = r.decode()
            assert isinstance(j, FusionJournal)
            live_consumed = max(live_consumed, j.consumed)
            for d in j.dropped:
                i = d.split(":", 1)[1] if d.count(":") > 1 else d
                sensor, _, seq = i.partition(":")
                if seq.isdigit() and (sensor, int(seq)) in rerun_ids:
                    raise OutOfWindow(f"the journal drops {i} after it was rerun")
                dropped[i] += 1
        elif run is None and t.endswith("/run"):
            m = r.decode()
            assert isinstance(m, RunInfo)
            run = m
        elif cfg is None and "/event/" in t:
            ev = r.decode()
            assert isinstance(ev, Event)
            if ev.kind == FUSION_CONFIG_EVENT:
                cfg = _config_of(ev)
                produced = {FREE_INS, *cfg.estimators}
                for early in early_nav:
                    recorded_nav(early)
                early_nav.clear()
        if core is None and run is not None and cfg is not None:
            from hil.runtime.scenario_io import scenario_for_run

            core = FusionCore.for_scenario(scenario_for_run(run), cfg)
    if run is None:
        raise RecordingError(f"{name}: no RunInfo (hil/<rig>/run): not a rig session")
    if core is None:
        raise RecordingError(
            f"{name}: no '{FUSION_CONFIG_EVENT}' event: the fusion did not run in this session"
        )
    release(None)
    diff = matcher.first[1] if matcher.first else None
    if diff is None and matcher.recorded_pending:
        missing = sorted(matcher.recorded_pending)
        est, seq = missing[0]
        diff = f"nav/{est} seq {seq}: recorded but not recomputed ({len(missing)} such outputs)"
    if diff is None and matcher.compared == 0:
        diff = "the recording holds no fusion outputs to compare"
    return RerunResult(outputs, matcher.n_recorded, n_out, used, sum(dropped.values()), live_consumed, diff)


def rerun_fusion(session: Session) -> RerunResult:
    """The fusion rerun of a recording already in memory (every recomputed output kept)."""
    return rerun_fusion_records(session.records, window_ns=None, keep_outputs=True, name=str(session.path))


RERUN_WINDOW_S = 30.0  # rig time held while streaming: inputs arrive within fractions of a second of order


def rerun_fusion_file(
    path: str | Path, *, window_s: float | None = RERUN_WINDOW_S, on_progress: Any = None
) -> tuple[RerunResult, SessionStream, str]:
    """Stream a recording through the fusion rerun; if its order defeats the window, read it whole.

    Returns the result, the stream (truncation, metadata) and a note ("" or why the whole file
    was needed).
    """
    stream = SessionStream(path, on_progress, follow_parts=True)
    window_ns = None if window_s is None else round(window_s * 1e9)
    try:
        return rerun_fusion_records(stream, window_ns=window_ns, name=str(path)), stream, ""
    except OutOfWindow as why:
        stream = SessionStream(path, on_progress, follow_parts=True)
        res = rerun_fusion_records(stream, window_ns=None, name=str(path))
        note = f"{why} (out of order by more than {window_s:g} s): reran with the whole file in memory"
        return res, stream, note


def rerun(
    path: str, *, core: str = "fusion", verify: bool = False, on_progress: Any = None
) -> tuple[int, list[str]]:
    """Exit code and report lines for ``hil rerun``.

    The file is streamed (``SessionStream``): memory stays at seconds of data whatever the
    length of the recording. ``on_progress(bytes_read, file_bytes)``.
    """
    if core == "timesync":
        from hil.record.rerun_timesync import rerun_timesync_report

        return rerun_timesync_report(path, verify, on_progress)
    if core != "fusion":
        return 2, [f"hil rerun: core {core!r} is not rerunnable (fusion, timesync)"]
    res, stream, note = rerun_fusion_file(path, on_progress=on_progress)
    lines = [
        f"rerun fusion: {res.inputs_used} inputs ({res.inputs_dropped} journaled as dropped), "
        f"{res.n_recomputed} outputs recomputed, {res.n_recorded} recorded"
    ]
    if note:
        lines.append(f"note: {note}")
    if len(stream.paths) > 1:
        lines.append(f"note: the recording is split: reran its {len(stream.paths)} parts in order")
    if stream.truncated:
        lines.append(
            "note: the file is truncated (its recorder did not finish it); "
            "rerun covers it up to its last complete chunk"
        )
    elif res.live_consumed >= 0 and res.live_consumed != res.inputs_used:
        lines.append(
            f"note: the live fusion journaled {res.live_consumed} consumed inputs, the recording holds "
            f"{res.inputs_used} of them: inputs were lost between the fusion and the recorder "
            "(see hil info for seq gaps on synced/*)"
        )
    if not verify:
        return 0, lines
    diff = res.first_difference()
    if diff:
        return 1, [*lines, f"VERIFY FAILED: {diff}"]
    return 0, [*lines, f"VERIFY OK: all {res.n_recorded} recorded outputs are bit-identical"]
