"""A recording in today's Foxglove-ready form: ``python -m hil.record.foxglove IN.mcap [OUT.mcap]``.

Recordings made now need no export: the recorder and ``hil sim`` write every schema in a form
Foxglove decodes, the well-known types beside the messages (``hil.wellknown``) and wall-clock
times. This brings a recording made before up to that form, so it opens the same way:

- every ``hil.*`` message in the current form of its type (``hil.messages.current_form``: an
  absent sigma ``[]`` instead of ``null``, a map as ``[{key, value}]``) under the current schema;
- MCAP log and publish times moved onto the wall clock (+ the run's start epoch) where they were
  rig time;
- the well-known channels (``/foxglove/...``: ``foxglove.LocationFix``, ``foxglove.FrameTransform``,
  ``foxglove.Log``) derived by the same conversion the recorder runs, where the file has none;
- every other channel, metadata record and attachment copied as it is.

A recording already in today's form comes out with the same messages.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from hil import __version__
from hil.messages import TYPES_BY_NAME, current_form, decode, json_schema
from hil.record.mcapio import (
    PROFILE,
    RecordingError,
    check_hil_recording,
    is_derived,
    iter_records,
    run_start,
)
from hil.wellknown import MESSAGE_ENCODING, SCHEMAS, WellKnown


class _Out:
    """The export's writer: one schema and one channel per name, registered on first use."""

    def __init__(self, w: Writer) -> None:
        self.w = w
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.seq: dict[str, int] = {}

    def channel(self, topic: str, schema: tuple[str, str, bytes], message_encoding: str) -> int:
        cid = self.channels.get(topic)
        if cid is None:
            sid = self.schemas.get(schema[0])
            if sid is None:
                sid = self.schemas[schema[0]] = self.w.register_schema(*schema)
            cid = self.channels[topic] = self.w.register_channel(topic, message_encoding, sid)
        return cid


def export_foxglove(src: str | Path, dst: str | Path) -> dict[str, int]:
    """Write the Foxglove-ready copy of ``src`` to ``dst``; returns messages per derived topic."""
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise RecordingError(f"{dst}: the export must not overwrite its source")
    try:
        return _export(src, dst)
    except BaseException:
        dst.unlink(missing_ok=True)  # never leave a half-written export behind
        raise


def _export(src: Path, dst: Path) -> dict[str, int]:
    start, on_wall_clock = run_start(src)
    shift = 0 if on_wall_clock or start is None else start
    has_derived = any(
        kind == "message" and is_derived(rec.topic) for kind, rec in iter_records(src, derived=True)
    )
    wellknown = None if has_derived else WellKnown(start_epoch_ns=start)
    derived: dict[str, int] = {}
    with open(dst, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile=PROFILE, library=f"hil {__version__} foxglove export")
        out = _Out(w)
        seen_message = False
        for kind, rec in iter_records(src, derived=True):
            if kind == "truncated":
                if not seen_message:
                    raise RecordingError(f"{src} is not a readable MCAP recording ({rec})")
                break
            if kind == "metadata":
                w.add_metadata(rec.name, dict(rec.metadata))
            elif kind == "attachment":
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            elif kind == "message":
                seen_message = True
                _message(out, rec, shift, wellknown, derived)
        w.finish()
    return derived


def _message(out: _Out, rec: Any, shift: int, wellknown: WellKnown | None, derived: dict[str, int]) -> None:
    log_ns, pub_ns = rec.log_time_ns + shift, rec.publish_time_ns + shift
    cls = TYPES_BY_NAME.get(rec.schema)
    if cls is None:  # a derived channel of a recent file, or one hil does not know: as it is
        schema = SCHEMAS.get(rec.schema)
        body = (schema.name, schema.encoding, schema.data) if schema else (rec.schema, "", b"")
        enc = MESSAGE_ENCODING if schema else "json"
        out.w.add_message(out.channel(rec.topic, body, enc), log_ns, rec.payload, pub_ns, rec.sequence)
        if is_derived(rec.topic):
            derived[rec.topic] = derived.get(rec.topic, 0) + 1
        return
    data = json.dumps(json_schema(cls), sort_keys=True).encode()
    cid = out.channel(rec.topic, (rec.schema, "jsonschema", data), "json")
    out.w.add_message(cid, log_ns, current_form(cls, rec.payload), pub_ns, rec.sequence)
    if wellknown is None:
        return
    try:
        msg = decode(cls, rec.payload)
    except ValueError:
        return  # a payload the recorder should not have taken: copied, nothing derived
    for d in wellknown.convert(rec.topic, msg, log_ns):
        schema = SCHEMAS[d.schema]
        n = derived.get(d.topic, 0)
        cid = out.channel(d.topic, (schema.name, schema.encoding, schema.data), MESSAGE_ENCODING)
        out.w.add_message(cid, log_ns, d.data, max(d.stamp_ns, 0), n & 0xFFFFFFFF)
        derived[d.topic] = n + 1


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.record.foxglove IN.mcap [OUT.mcap]`` (default OUT: IN with ``.foxglove.mcap``)."""
    args = sys.argv[1:] if argv is None else argv
    if not 1 <= len(args) <= 2 or args[0].startswith("-"):
        sys.stderr.write("usage: python -m hil.record.foxglove IN.mcap [OUT.mcap]\n")
        return 2
    src = Path(args[0])
    dst = Path(args[1]) if len(args) > 1 else src.with_suffix(".foxglove.mcap")
    try:
        check_hil_recording(src)
        derived = export_foxglove(src, dst)
    except (RecordingError, OSError) as err:
        sys.stderr.write(f"hil foxglove export: {err}\n")
        return 2
    topics = ", ".join(f"{t} ({n})" for t, n in sorted(derived.items()))
    sys.stdout.write(f"wrote {dst}: Foxglove channels {topics}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
