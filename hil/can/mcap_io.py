"""python-can reads a rig recording: ``can.LogReader("session.mcap")`` yields its CAN frames.

Registered under python-can's ``can.io.message_reader`` entry point for the ``.mcap`` suffix, so
python-can's own tools work on a recording unchanged, e.g. ``python -m can.player -i virtual
session.mcap`` plays the recorded frames onto any bus with their recorded spacing, and
``python -m can.logconvert session.mcap out.asc`` converts them.

Which frames: every ``hil.CanFrame`` message (the bridge's ``hil/<rig>/can/<channel>`` topics),
in file order. ``timestamp`` is the frame's receive time on the wall-clock timeline: the run's
start epoch (``RunInfo.start_epoch_ns``, from the file's ``hil`` metadata or its ``run`` message)
+ the frame's receive stamp on the rig clock (``stamp_ns``), in seconds since 1970 -- what a
SocketCAN log of the same bus would say, so ``.asc``/``.blf``/``.trc`` exports line up with other
logs of the bench. Old recordings (rig-time log times) get the same, as their frames' stamps are
rig time too. A file with no start epoch at all (a recorder killed before the run started) keeps
rig seconds. ``channel`` is the recorded channel name. A crashed recording is read up to its last
complete chunk, like every other reader of the rig's files.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
from can.io.generic import MessageReader

from hil.messages import CanFrame, decode
from hil.record.mcapio import RecordingError, iter_records, run_start

CAN_SCHEMA = "hil.CanFrame"


def can_message(frame: CanFrame, start_epoch_ns: int = 0) -> can.Message:
    """The python-can view of one recorded frame (``start_epoch_ns``: the run's time zero)."""
    return can.Message(
        timestamp=(start_epoch_ns + frame.stamp_ns) * 1e-9,
        arbitration_id=frame.arbitration_id,
        is_extended_id=frame.is_extended_id,
        is_fd=frame.is_fd,
        bitrate_switch=frame.bitrate_switch,
        is_error_frame=frame.is_error_frame,
        is_rx=True,
        channel=frame.channel,
        data=bytes.fromhex(frame.data_hex),
    )


class McapReader(MessageReader):
    """Iterates the ``hil.CanFrame`` messages of an MCAP recording as ``can.Message``.

    ``channel``: only frames recorded from this CAN channel (default: all).
    Raises ``RecordingError`` (a ``ValueError``) when the file is not a readable recording.
    """

    def __init__(self, file: Any, channel: str | None = None, **kwargs: Any) -> None:
        if not isinstance(file, str | Path):
            raise TypeError("McapReader reads a file path (MCAP needs random access to its chunks)")
        self.path = Path(file)
        if not self.path.is_file():
            raise RecordingError(f"no recording at {self.path}")
        self.channel = channel
        self.truncated = ""
        self._stopped = False
        self.start_epoch_ns: int | None = None  # known once iteration has begun

    def __iter__(self) -> Iterator[can.Message]:
        seen_any = False
        start = self.start_epoch_ns = run_start(self.path)[0] or 0
        for kind, rec in iter_records(self.path):
            if self._stopped:
                return
            if kind == "truncated":
                if not seen_any:
                    raise RecordingError(f"{self.path} is not a readable MCAP recording ({rec})")
                self.truncated = str(rec)
                return
            seen_any = True
            if kind != "message" or rec.schema != CAN_SCHEMA:
                continue
            frame = decode(CanFrame, rec.payload)
            if self.channel is not None and frame.channel != self.channel:
                continue
            yield can_message(frame, start)

    def stop(self) -> None:
        self._stopped = True
