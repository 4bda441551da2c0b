"""Per-publisher sequence accounting: what arrived, what is missing, what came twice or late."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class SeqTracker:
    """Tracks one publisher's ``seq`` stream (a Zenoh key has exactly one publisher)."""

    first: int = -1
    last: int = -1
    count: int = 0
    gaps: int = 0  # number of gap events
    missing: int = 0  # sequence numbers never seen (so far)
    duplicates: int = 0
    out_of_order: int = 0
    gap_ranges: list[tuple[int, int]] = field(default_factory=list)

    def see(self, seq: int) -> None:
        self.count += 1
        if self.first < 0:
            self.first = self.last = seq
            return
        if seq == self.last + 1:
            self.last = seq
        elif seq > self.last + 1:
            self.gaps += 1
            self.missing += seq - self.last - 1
            if len(self.gap_ranges) < 100:
                self.gap_ranges.append((self.last + 1, seq - 1))
            self.last = seq
        elif seq == self.last:
            self.duplicates += 1
        else:
            # An old seq: either a late arrival filling a gap, or a duplicate of an older one.
            self.out_of_order += 1
            if any(a <= seq <= b for a, b in self.gap_ranges):
                self.missing -= 1

    def summary(self) -> dict[str, int | list[list[int]]]:
        return {
            "first": self.first,
            "last": self.last,
            "count": self.count,
            "gaps": self.gaps,
            "missing": self.missing,
            "duplicates": self.duplicates,
            "out_of_order": self.out_of_order,
            "gap_ranges": [list(r) for r in self.gap_ranges[:20]],
        }


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

    def report(self) -> dict[str, dict[str, int | list[list[int]]]]:
        return {k: v.summary() for k, v in sorted(self.topics.items())}
