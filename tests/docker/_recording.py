"""Checks on a recording made by a deployed rig (compose, multi-host): shared by both tiers."""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import jsonschema
from mcap.reader import make_reader

REPO = Path(__file__).resolve().parents[2]

CONTRACT_TYPES = (
    "hil.Truth",
    "hil.ImuSample",
    "hil.GnssFix",
    "hil.CanFrame",
    "hil.TimeTag",
    "hil.ClockModel",
    "hil.NavSolution",
    "hil.ServiceStatus",
    "hil.CaptureTruth",
)


@dataclass
class Audit:
    counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))  # type -> messages
    topics: dict[str, int] = field(default_factory=lambda: defaultdict(int))  # topic -> messages
    gaps: dict[str, list[tuple[int, int]]] = field(default_factory=lambda: defaultdict(list))
    invalid: list[str] = field(default_factory=list)
    has_summary: bool = False
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    total: int = 0

    def gap_lines(self) -> list[str]:
        return [f"{t}: {len(g)} gap(s), first {g[:3]}" for t, g in sorted(self.gaps.items()) if g]


def audit(path: Path, *, schemas_dir: Path = REPO / "schemas", validate_max: int | None = None) -> Audit:
    """Count types and topics, find seq gaps per topic (one publisher per topic), validate JSON.

    A seq gap is a pair (previous seq, next seq) with next != previous + 1.
    """
    a = Audit()
    validators: dict[str, jsonschema.protocols.Validator] = {}
    last: dict[str, int] = {}
    validated: dict[str, int] = defaultdict(int)
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        a.has_summary = summary is not None and summary.statistics is not None
        for rec in reader.iter_metadata():
            a.metadata[rec.name] = dict(rec.metadata)
        fh.seek(0)
        reader = make_reader(fh)
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            name = schema.name if schema else "?"
            a.total += 1
            a.counts[name] += 1
            a.topics[channel.topic] += 1
            if not name.startswith("hil."):
                continue  # Foxglove's well-known types (protobuf), derived from the hil.* messages
            doc = json.loads(msg.data)
            if validate_max is None or validated[name] < validate_max:
                if name not in validators:
                    spec = json.loads((schemas_dir / f"{name}.json").read_text())
                    validators[name] = jsonschema.Draft202012Validator(spec)
                err = next(iter(validators[name].iter_errors(doc)), None)
                if err is not None and len(a.invalid) < 20:
                    a.invalid.append(f"{channel.topic} seq={doc.get('seq')}: {err.message[:200]}")
                validated[name] += 1
            seq = doc.get("seq")
            if isinstance(seq, int):
                prev = last.get(channel.topic)
                if prev is not None and seq != prev + 1:
                    a.gaps[channel.topic].append((prev, seq))
                last[channel.topic] = seq
    return a
