"""Per-publisher sequence accounting: what arrived, what is missing, what came twice or late.

A restarted service numbers its own counters in a new *restart generation*
(``hil.messages.SEQ_GENERATION_SHIFT``): its seqs jump forward to ``generation * 2**32`` and
count from there. The tracker treats each generation as a new stream of the same publisher: the
jump is reported as a restart (``restarts``, ``generations``), not as four billion missing
messages, and the new stream's first seq is its baseline, as for any stream the recorder joins.
Data lost while the process was dead shows where it can be measured: as gaps in the streams
whose seq is a time or device index (truth, IMU samples, GNSS epochs, fusion outputs), which a
restart does not renumber.

Sane under forged numbers: a seq more than ``MAX_SEQ_JUMP`` ahead of its stream (a forged
``seq`` of 10⁹ among the rig's hundreds) is not a gap of a billion messages but an ``outlier``,
counted and otherwise ignored; so is a "new generation" that does not start near 0 as a
restarted publisher's does. A late message fills its gap once (a repeated one is a duplicate),
so no count goes negative. Messages of publishers that are not the rig's are accounted apart
(``ForeignTraffic``): never the rig's loss.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hil.messages import SEQ_GENERATION_SHIFT, seq_generation, seq_in_generation

MAX_GAP_RANGES = 100
MAX_SEQ_JUMP = 100_000  # further ahead than this is no gap (4 min of 400 Hz): an outlier
MAX_GENERATIONS = 1_024


@dataclass
class _Generation:
    """One restart generation of one publisher."""

    generation: int
    first: int
    last: int
    count: int = 1
    missing: int = 0
    gap_ranges: list[tuple[int, int]] = field(default_factory=list)
    untracked_gaps: int = 0  # gaps past MAX_GAP_RANGES: where they are is not known

    def holds(self, seq: int) -> bool:
        """Whether ``seq`` was seen in this generation; False when that cannot be known."""
        if not self.first <= seq <= self.last or self.untracked_gaps:
            return False
        return not any(a <= seq <= b for a, b in self.gap_ranges)


@dataclass
class SeqTracker:
    """Tracks one publisher's ``seq`` stream (a Zenoh key has exactly one publisher).

    ``first``/``last`` are whole seqs (generation included); the counts add up over generations.
    """

    first: int = -1
    last: int = -1
    count: int = 0
    gaps: int = 0  # number of gap events
    missing: int = 0  # sequence numbers never seen (so far)
    duplicates: int = 0
    out_of_order: int = 0
    restarts: int = 0  # new generations seen after the first
    outliers: int = 0  # seqs no stream of the rig's could have sent (see the module docstring)
    gap_ranges: list[tuple[int, int]] = field(default_factory=list)
    generations: dict[int, _Generation] = field(default_factory=dict)

    def see(self, seq: int) -> None:
        self.count += 1
        g = seq >> SEQ_GENERATION_SHIFT  # seq_generation, inline: once per message recorded
        gen = self.generations.get(g)
        if gen is not None and seq == gen.last + 1:  # the next one, as nearly every message is
            gen.count += 1
            gen.last = seq
            if seq > self.last and g == self.last >> SEQ_GENERATION_SHIFT:
                self.last = seq
            return
        if gen is None:
            self._new_generation(g, seq)
            return
        gen.count += 1
        if seq == gen.last + 1:
            gen.last = seq
        elif seq > gen.last + 1 + MAX_SEQ_JUMP:
            self.outliers += 1  # forged or corrupt: no stream of the rig's skips that far
            gen.count -= 1
        elif seq > gen.last + 1:
            self.gaps += 1
            n = seq - gen.last - 1
            self.missing += n
            gen.missing += n
            if len(gen.gap_ranges) < MAX_GAP_RANGES:
                gen.gap_ranges.append((gen.last + 1, seq - 1))
            else:
                gen.untracked_gaps += 1
            if len(self.gap_ranges) < MAX_GAP_RANGES:
                self.gap_ranges.append((gen.last + 1, seq - 1))
            gen.last = seq
        elif seq == gen.last:
            self.duplicates += 1
        else:
            # An old seq: a late arrival filling a gap (once), or a duplicate of an older one.
            self.out_of_order += 1
            if _fill(gen.gap_ranges, seq):
                self.missing -= 1
                gen.missing -= 1
        if g == seq_generation(self.last):
            self.last = max(self.last, gen.last)

    def see_run(self, first: int, n: int) -> None:
        """``see`` of ``first``, ``first + 1``, ... ``first + n - 1`` in turn (one restart
        generation): a stream counted elsewhere in runs of consecutive seqs (``hil.record.info``'s
        second reader), with the same result as each seen one by one."""
        if n <= 0:
            return
        g = first >> SEQ_GENERATION_SHIFT
        last = first + n - 1
        assert last >> SEQ_GENERATION_SHIFT == g, "a run within one generation"
        seq = first
        while seq <= last:
            gen = self.generations.get(g)
            if gen is not None and gen.last == seq - 1:  # the rest all take see's first branch
                k = last - seq + 1
                self.count += k
                gen.count += k
                gen.last = last
                if last > self.last and g == self.last >> SEQ_GENERATION_SHIFT:
                    self.last = last
                return
            self.see(seq)
            seq += 1

    def _new_generation(self, g: int, seq: int) -> None:
        if self.first < 0:
            self.generations[g] = _Generation(g, seq, seq)
            self.first = self.last = seq
        elif len(self.generations) >= MAX_GENERATIONS:
            self.outliers += 1
        elif seq > self.last and seq_in_generation(seq) < MAX_SEQ_JUMP:
            # the publisher was restarted: a new stream, not a gap
            self.generations[g] = _Generation(g, seq, seq)
            self.restarts += 1
            self.last = seq
        elif seq < self.last:  # a late message of an older generation we had not seen at all
            self.generations[g] = _Generation(g, seq, seq)
            self.out_of_order += 1
        else:  # a "generation" far ahead that does not start near 0: forged, not a restart
            self.outliers += 1

    def holds(self, seq: int) -> bool:
        """Whether ``seq`` was seen (a restarted recorder's test for "already recorded"): only a
        seq inside its generation's seen span and in none of its open gaps; where gaps were too
        many to track, False (better a message twice than one lost)."""
        gen = self.generations.get(seq_generation(seq))
        return gen is not None and gen.holds(seq)

    @property
    def generation(self) -> int:
        """The newest restart generation seen (0: the publisher's first process)."""
        return seq_generation(self.last) if self.last >= 0 else 0

    def summary(self) -> dict[str, int | list[list[int]] | list[dict[str, int]]]:
        out: dict[str, int | list[list[int]] | list[dict[str, int]]] = {
            "first": self.first,
            "last": self.last,
            "count": self.count,
            "gaps": self.gaps,
            "missing": self.missing,
            "duplicates": self.duplicates,
            "out_of_order": self.out_of_order,
            "gap_ranges": [list(r) for r in self.gap_ranges[:20]],
            "restarts": self.restarts,
            "generation": self.generation,
        }
        if self.outliers:
            out["outliers"] = self.outliers
        if len(self.generations) > 1:
            # per process lifetime, numbered within it: what a reader compares across a restart
            out["generations"] = [
                {
                    "generation": gen.generation,
                    "first": seq_in_generation(gen.first),
                    "last": seq_in_generation(gen.last),
                    "count": gen.count,
                    "missing": gen.missing,
                }
                for _g, gen in sorted(self.generations.items())
            ]
        return out


def _fill(ranges: list[tuple[int, int]], seq: int) -> bool:
    """Take ``seq`` out of the open gap ``ranges`` it falls in; False if it is in none."""
    for i, (a, b) in enumerate(ranges):
        if a <= seq <= b:
            ranges[i : i + 1] = [r for r in ((a, seq - 1), (seq + 1, b)) if r[0] <= r[1]]
            return True
    return False


class Completeness:
    """All publishers of a session."""

    def __init__(self) -> None:
        self.topics: dict[str, SeqTracker] = {}

    def see(self, topic: str, seq: int) -> None:
        tr = self.topics.get(topic)
        if tr is None:
            tr = self.topics[topic] = SeqTracker()
        tr.see(seq)

    def see_run(self, topic: str, first: int, n: int) -> None:
        """``see`` of ``n`` consecutive seqs from ``first`` (``SeqTracker.see_run``)."""
        tr = self.topics.get(topic)
        if tr is None:
            tr = self.topics[topic] = SeqTracker()
        tr.see_run(first, n)

    def holds(self, topic: str, seq: int) -> bool:
        """Whether ``topic``'s ``seq`` was seen (``SeqTracker.holds``)."""
        tr = self.topics.get(topic)
        return tr is not None and tr.holds(seq)

    def total_missing(self) -> int:
        return sum(t.missing for t in self.topics.values())

    def restarts(self) -> dict[str, int]:
        """Publishers seen restarting during the recording: topic -> restarts."""
        return {k: t.restarts for k, t in sorted(self.topics.items()) if t.restarts}

    def report(self) -> dict[str, dict[str, int | list[list[int]] | list[dict[str, int]]]]:
        return {k: v.summary() for k, v in sorted(self.topics.items())}


class ForeignTraffic:
    """What publishers that are not the rig's sent: per topic and publisher, at most
    ``max_publishers`` of them tracked one by one (the rest counted together), never the rig's."""

    def __init__(self, max_publishers: int = 64) -> None:
        self.max_publishers = max_publishers
        self.messages = 0
        self.untracked = 0
        self.publishers: dict[str, Completeness] = {}

    def see(self, topic: str, publisher: str, seq: int) -> None:
        self.messages += 1
        comp = self.publishers.get(publisher)
        if comp is None:
            if len(self.publishers) >= self.max_publishers:
                self.untracked += 1
                return
            comp = self.publishers[publisher] = Completeness()
        comp.see(topic, seq)

    def report(self) -> dict[str, object]:
        topics: dict[str, int] = {}
        for comp in self.publishers.values():
            for topic, tr in comp.topics.items():
                topics[topic] = topics.get(topic, 0) + tr.count
        return {
            "messages": self.messages,
            "publishers": sorted(self.publishers),
            "untracked": self.untracked,
            "topics": dict(sorted(topics.items())),
        }
