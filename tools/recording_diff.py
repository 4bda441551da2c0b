"""Compare two recordings topic by topic: ``python tools/recording_diff.py OLD.mcap NEW.mcap``.

How a refactor that must not change ``hil sim``'s output is checked: for every topic, the list
of (log time, publish time, sequence, payload) in file order must be the same in both files. The
interleaving of topics (which message of two at one log time comes first) is not compared; a
summary per topic says what differs, and the first difference is shown.
"""

from __future__ import annotations

import sys
from collections import defaultdict

from mcap.reader import make_reader


def streams(path: str) -> dict[str, list[tuple[int, int, int, bytes]]]:
    out: dict[str, list[tuple[int, int, int, bytes]]] = defaultdict(list)
    with open(path, "rb") as fh:
        for _schema, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            out[channel.topic].append((msg.log_time, msg.publish_time, msg.sequence, bytes(msg.data)))
    return out


def say(line: str) -> None:
    sys.stdout.write(line + "\n")


def main(argv: list[str]) -> int:
    old, new = streams(argv[0]), streams(argv[1])
    same = differ = 0
    for topic in sorted(set(old) | set(new)):
        a, b = old.get(topic, []), new.get(topic, [])
        if a == b:
            same += 1
            continue
        differ += 1
        if not a or not b:
            say(f"{topic}: only in {'new' if b else 'old'} ({len(a or b)} messages)")
            continue
        first = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))
        what = ""
        if first < min(len(a), len(b)):
            x, y = a[first], b[first]
            names = ("log_time", "publish_time", "sequence", "payload")
            parts = [n for n, u, v in zip(names, x, y, strict=True) if u != v]
            what = f"; first at #{first}: {', '.join(parts)} differ"
            if "payload" in parts:
                what += f"\n    old {x[3][:300]!r}\n    new {y[3][:300]!r}"
            elif parts:
                what += f" (old {x[:3]}, new {y[:3]})"
        say(f"{topic}: {len(a)} vs {len(b)} messages{what}")
    say(f"{same} topics identical, {differ} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
