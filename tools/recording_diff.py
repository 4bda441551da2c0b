"""Compare two recordings topic by topic: ``python tools/recording_diff.py OLD.mcap NEW.mcap``.

How a refactor that must not change ``hil sim``'s output is checked: for every topic, the
sequence of (log time, publish time, sequence, payload) in file order must be the same in both
files. The interleaving of topics (which of two messages at one log time comes first) is not
compared. It streams: one pass hashes every topic's sequence in each file, a second pass finds
the first difference of each topic that differs, so hour-long sessions need no memory.
"""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Iterator

from mcap.reader import make_reader

Item = tuple[int, int, int, bytes]


def _items(path: str, topics: list[str] | None = None) -> Iterator[tuple[str, Item]]:
    with open(path, "rb") as fh:
        for _schema, channel, msg in make_reader(fh).iter_messages(topics=topics, log_time_order=False):
            yield channel.topic, (msg.log_time, msg.publish_time, msg.sequence, bytes(msg.data))


def digests(path: str) -> dict[str, tuple[int, str]]:
    """Per topic: (message count, SHA-256 of its (log, publish, sequence, payload) sequence)."""
    hashes: dict[str, tuple[int, object]] = {}
    for topic, (log, pub, seq, data) in _items(path):
        n, h = hashes.get(topic, (0, hashlib.sha256()))
        h.update(f"{log} {pub} {seq} {len(data)}\n".encode())  # type: ignore[attr-defined]
        h.update(data)  # type: ignore[attr-defined]
        hashes[topic] = (n + 1, h)
    return {t: (n, h.hexdigest()) for t, (n, h) in hashes.items()}  # type: ignore[attr-defined]


def first_difference(old: str, new: str, topic: str) -> str:
    a, b = _items(old, [topic]), _items(new, [topic])
    i = 0
    for (_, x), (_, y) in zip(a, b, strict=False):
        if x != y:
            names = ("log_time", "publish_time", "sequence", "payload")
            parts = [n for n, u, v in zip(names, x, y, strict=True) if u != v]
            what = f"first at #{i}: {', '.join(parts)} differ"
            if "payload" in parts:
                return what + f"\n    old {x[3][:300]!r}\n    new {y[3][:300]!r}"
            return what + f" (old {x[:3]}, new {y[:3]})"
        i += 1
    return f"the first {i} are the same"


def say(line: str) -> None:
    sys.stdout.write(line + "\n")


def main(argv: list[str]) -> int:
    old, new = digests(argv[0]), digests(argv[1])
    same = differ = 0
    for topic in sorted(set(old) | set(new)):
        a, b = old.get(topic), new.get(topic)
        if a == b:
            same += 1
            continue
        differ += 1
        if a is None or b is None:
            say(f"{topic}: only in {'new' if b else 'old'} ({(a or b)[0]} messages)")  # type: ignore[index]
            continue
        say(f"{topic}: {a[0]} vs {b[0]} messages; {first_difference(argv[0], argv[1], topic)}")
    say(f"{same} topics identical, {differ} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
