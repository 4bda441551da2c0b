"""Per-publisher sequence accounting: what arrived, what is missing, what came twice or late.

A restarted service numbers its own counters in a new *restart generation*
(``hil.messages.SEQ_GENERATION_SHIFT``): its seqs jump forward to ``generation * 2**32`` and
count from there. The tracker treats each generation as a new stream of the same publisher: the
jump is reported as a restart (``restarts``, ``generations``), not as four billion missing
messages, and the new stream's first seq is its baseline, as for any stream the recorder joins.
Data lost while the process was dead shows where it can be measured: as gaps in the streams
whose seq is a time or device index (truth, IMU samples, GNSS epochs, fusion outputs), which a
restart does not renumber.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hil.messages import seq_generation, seq_in_generation

MAX_GAP_RANGES = 100


@dataclass
class _Generation:
    """One restart generation of one publisher."""

    generation: int
    first: int
    last: int
    count: int = 1
    missing: int = 0
    gap_ranges: list[tuple[int, int]] = field(default_factory=list)


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
    gap_ranges: list[tuple[int, int]] = field(default_factory=list)
    generations: dict[int, _Generation] = field(default_factory=dict)

    def see(self, seq: int) -> None:
        self.count += 1
        g = seq_generation(seq)
        gen = self.generations.get(g)
        if gen is None:
            self.generations[g] = _Generation(g, seq, seq)
            if self.first < 0:
                self.first = self.last = seq
            elif seq > self.last:  # the publisher was restarted: a new stream, not a gap
                self.restarts += 1
                self.last = seq
            else:  # a late message of an older generation we had not seen at all
                self.out_of_order += 1
            return
        gen.count += 1
        if seq == gen.last + 1:
            gen.last = seq
        elif seq > gen.last + 1:
            self.gaps += 1
            n = seq - gen.last - 1
            self.missing += n
            gen.missing += n
            if len(gen.gap_ranges) < MAX_GAP_RANGES:
                gen.gap_ranges.append((gen.last + 1, seq - 1))
            if len(self.gap_ranges) < MAX_GAP_RANGES:
                self.gap_ranges.append((gen.last + 1, seq - 1))
            gen.last = seq
        elif seq == gen.last:
            self.duplicates += 1
        else:
            # An old seq: either a late arrival filling a gap, or a duplicate of an older one.
            self.out_of_order += 1
            if any(a <= seq <= b for a, b in gen.gap_ranges):
                self.missing -= 1
                gen.missing -= 1
        if g == seq_generation(self.last):
            self.last = max(self.last, gen.last)

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


class Completeness:
    """All publishers of a session."""

    def __init__(self) -> None:
        self.topics: dict[str, SeqTracker] = {}

    def see(self, topic: str, seq: int) -> None:
        tr = self.topics.get(topic)
        if tr is None:
            tr = self.topics[topic] = SeqTracker()
        tr.see(seq)

    def total_missing(self) -> int:
        return sum(t.missing for t in self.topics.values())

    def restarts(self) -> dict[str, int]:
        """Publishers seen restarting during the recording: topic -> restarts."""
        return {k: t.restarts for k, t in sorted(self.topics.items()) if t.restarts}

    def report(self) -> dict[str, dict[str, int | list[list[int]] | list[dict[str, int]]]]:
        return {k: v.summary() for k, v in sorted(self.topics.items())}
