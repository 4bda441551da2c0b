"""Pairing recomputed outputs with recorded ones while both streams go by (``hil rerun``).

Neither side is kept whole, so a one-hour rerun holds seconds of data; both the fusion rerun
(``hil.record.rerun``) and the time-sync rerun (``hil.record.rerun_timesync``) use it.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Protocol

KEEP_DIFFS = 10_000  # differences kept with their payloads (``Matcher.diffs``)
TAIL_NS = 5_000_000_000  # log time before a cut within which an output's inputs may lie beyond it


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
        normalise: Callable[[bytes], bytes] | None = None,
    ) -> None:
        self.describe = describe  # (key, recorded, recomputed) -> text of a difference
        # a recorded payload in today's form, tried only when its bytes differ (a legacy form:
        # decoding every recorded output to check its form cost more than comparing it)
        self.normalise = normalise
        self.by_recorded = by == "recorded"
        self.horizon_ns = horizon_ns
        self.recorded_pending: dict[tuple[str, int], tuple[int, bytes]] = {}
        self.recomputed_pending: OrderedDict[tuple[str, int], tuple[int, bytes, int]] = OrderedDict()
        self.released = SeqSet()
        self.n_recorded = 0
        self.compared = 0
        self.first: tuple[int, str] | None = None  # (order, text) of the first difference
        # for a truncated file: the recorded copies' log times (pending ones, and the earliest
        # recorded log time among the differences), so its tail can be told from the rest
        self.recorded_t: dict[tuple[str, int], int] = {}
        self.first_by_log: tuple[int, str] | None = None
        self.diff_logs: list[int] = []  # recorded log time of every differing output
        # every difference as (order, the recomputed output's time, key), with both payloads for
        # the first ``KEEP_DIFFS`` of them: a caller that learns only at the end which outputs it
        # can vouch for (``hil.record.rerun``: those before inputs the recording lost) names the
        # first difference among those
        self.diffs: list[tuple[int, int, tuple[str, int], bytes, bytes]] = []
        self.describing_log_ns = 0

    def _compare(
        self,
        key: tuple[str, int],
        rec: tuple[int, bytes],
        mine: tuple[int, bytes],
        log_ns: int,
        t_ns: int = 0,
    ) -> None:
        self.compared += 1
        theirs = rec[1]
        if mine[1] != theirs and self.normalise is not None:
            theirs = self.normalise(theirs)
        if mine[1] != theirs:
            self.diff_logs.append(log_ns)
            kept = len(self.diffs) < KEEP_DIFFS
            order_ = rec[0] if self.by_recorded else mine[0]
            self.diffs.append((order_, t_ns, key, theirs if kept else b"", mine[1] if kept else b""))
            self.describing_log_ns = log_ns  # the recorded copy's, for a describe that names it
            order = rec[0] if self.by_recorded else mine[0]
            text = None
            if self.first is None or order < self.first[0]:
                text = self.describe(key, theirs, mine[1])
                self.first = (order, text)
            if self.first_by_log is None or log_ns < self.first_by_log[0]:
                self.first_by_log = (log_ns, text or self.describe(key, theirs, mine[1]))

    def recorded(self, key: tuple[str, int], payload: bytes, order: int, log_ns: int = 0) -> None:
        if key in self.recorded_pending:
            return  # a recorded duplicate: the first copy counts
        self.n_recorded += 1
        mine = self.recomputed_pending.pop(key, None)
        if mine is not None:
            self._compare(key, (order, payload), (mine[0], mine[1]), log_ns, mine[2])
        else:
            self.recorded_pending[key] = (order, payload)
            self.recorded_t[key] = log_ns

    def recomputed(self, key: tuple[str, int], payload: bytes, order: int, t_ns: int) -> None:
        rec = self.recorded_pending.pop(key, None)
        if rec is not None:
            self._compare(key, rec, (order, payload), self.recorded_t.pop(key, 0), t_ns)
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

    def excuse(self, excused: Callable[[int], bool]) -> int:
        """Leave out of ``first`` the differences of outputs whose time (the recomputed one's
        ``t_ns``) ``excused`` says cannot be vouched for; how many were left out. The first
        difference is then the first among the rest, as ``first`` would have named it."""
        rest = [d for d in self.diffs if not excused(d[1])]
        n = len(self.diffs) - len(rest)
        if n:
            first = min(rest, key=lambda d: d[0]) if rest else None
            if first is None:
                self.first = None
            else:
                order, _t, key, theirs, mine = first
                self.first = (
                    order,
                    self.describe(key, theirs, mine) if theirs else f"{key[0]} seq {key[1]} differs",
                )
        return n

    def pending_before(self, log_ns: int) -> list[tuple[str, int]]:
        """Recorded outputs never recomputed that were recorded before ``log_ns``."""
        return sorted(k for k in self.recorded_pending if self.recorded_t.get(k, 0) < log_ns)


class _Verdict(Protocol):
    n_recorded: int
    unverified: int

    @property
    def excused(self) -> int:
        """Recorded outputs that differ where the recording cannot vouch for them (said in notes)."""
        ...

    def first_difference(self, truncated: bool) -> str: ...


def truncation_notes(res: _Verdict, truncated: bool, recomputed: str, inputs: str) -> list[str]:
    """What a rerun of a truncated file says: how far it went, and which recorded ``recomputed``
    (outputs, re-stamps) it could not check because their ``inputs`` lie beyond the cut."""
    if not truncated:
        return []
    lines = [
        "note: the file is truncated (its recorder did not finish it; hil recover FILE rewrites it "
        "finished); rerun covers it up to its last complete chunk"
    ]
    if res.unverified:
        lines.append(
            f"note: {res.unverified} {recomputed} recorded in the last {TAIL_NS / 1e9:g} s before the cut "
            f"have {inputs} beyond it: not verifiable"
        )
    return lines


def verdict(
    res: _Verdict, truncated: bool, lines: list[str], verify: bool, recomputed: str
) -> tuple[int, list[str]]:
    """``hil rerun``'s exit code and report: ``lines``, then ``--verify``'s outcome."""
    if not verify:
        return 0, lines
    diff = res.first_difference(truncated)
    if diff:
        return 1, [*lines, f"VERIFY FAILED: {diff}"]
    n = res.n_recorded - (res.unverified if truncated else 0) - res.excused
    return 0, [*lines, f"VERIFY OK: all {n} recorded {recomputed} are bit-identical"]
