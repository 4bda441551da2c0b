"""The Foxglove well-known channels of a recording, read by a reader nobody here wrote: mcap's
reader with mcap-protobuf-support (the MCAP project's protobuf decoder), which builds each message
class from the schema the file embeds -- as Foxglove does -- and decodes every message with it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def decode_wellknown(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """topic -> [(log_time, decoded protobuf message)] for every protobuf channel of the file."""
    out: dict[str, list[tuple[int, Any]]] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None, f"{path}: no summary"
        topics = [c.topic for c in summary.channels.values() if c.message_encoding == "protobuf"]
        if not topics:
            return out
        for schema, channel, msg, decoded in reader.iter_decoded_messages(
            topics=topics, log_time_order=False
        ):
            assert schema is not None and schema.encoding == "protobuf", channel.topic
            assert decoded.DESCRIPTOR.full_name == schema.name, channel.topic  # the type the schema names
            out.setdefault(channel.topic, []).append((msg.log_time, decoded))
    return out
