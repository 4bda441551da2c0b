"""replayer: ``hil replay FILE`` as a process -- argument parsing and resources, nothing else.

The work is ``hil.record.replay.replay``; this module builds what it is handed (the Zenoh
session, the CAN bus, the stop event wired to SIGINT/SIGTERM) and turns its errors into one line
and an exit code: 0 done, 1 the replay could not go on, 2 bad input (file, option), 130 stopped.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import Any

from hil.runtime.argtypes import OneLineParser, bounded_float, bounded_int, seconds
from hil.runtime.signals import EventSetter

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_STOPPED = 130


def add_args(p: argparse.ArgumentParser) -> None:
    """The replay options (shared by ``hil replay`` and ``python -m services.replayer``)."""
    p.add_argument("file", help="an MCAP recording")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument(
        "--rate",
        type=bounded_float(0.0, 1e6, lo_open=True),
        default=1.0,
        help="K times the recorded speed (default 1)",
    )
    timing.add_argument("--afap", action="store_true", help="as fast as possible (no timing)")
    timing.add_argument("--step", action="store_true", help="send one message per Enter (canplayer -i)")
    p.add_argument("--start", type=seconds, default=None, help="seconds after the first message")
    p.add_argument("--end", type=seconds, default=None, help="seconds after the first message")
    p.add_argument(
        "--topics", action="append", default=[], metavar="REGEX", help="replay only matching topics (repeat)"
    )
    p.add_argument(
        "--exclude-topics", action="append", default=[], metavar="REGEX", help="skip matching topics (repeat)"
    )
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    p.add_argument("--rig", default=None, help="republish under hil/<RIG>/... (beside a live rig)")
    p.add_argument("--can", default=None, metavar="CHANNEL", help="play recorded CAN frames onto this bus")
    p.add_argument("--can-interface", default=None, help="python-can interface (default: auto)")
    p.add_argument(
        "--gnss-serial",
        default=None,
        metavar="PATH",
        help="play the recorded GNSS line (serial/<port> bytes) onto a pseudo-terminal linked at PATH",
    )
    p.add_argument(
        "--gnss-baud",
        type=bounded_int(1, 10_000_000),
        default=115200,
        help="the line's baud rate (pacing of each read)",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="gate fusion inputs on the target fusion's ack (bit-exact replay through a live fusion)",
    )
    p.add_argument(
        "--lockstep-window",
        type=bounded_int(0, 1_000_000),
        default=0,
        help="fusion inputs in flight beyond the ack",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(a: argparse.Namespace) -> int:
    """Build the resources, replay, print one summary line."""
    from hil.bus.keys import check_name
    from hil.bus.session import open_session
    from hil.record.mcapio import RecordingError
    from hil.record.replay import ReplayError, ReplayOptions, check_readable, check_selected, replay

    try:
        if a.rig:
            check_name("rig", a.rig)
        if a.start is not None and a.end is not None and a.end < a.start:
            raise ValueError(f"--end {a.end} is before --start {a.start}")
        check_readable(a.file)
        opts = ReplayOptions(
            rate=a.rate,
            afap=a.afap,
            start_s=a.start,
            end_s=a.end,
            topics=list(a.topics),
            exclude_topics=list(a.exclude_topics),
            loop=a.loop,
            step=a.step,
            rig=a.rig,
            can_channel=a.can,
            can_interface=a.can_interface,
            lockstep=a.lockstep,
            lockstep_window=a.lockstep_window,
            progress=not a.no_progress and sys.stderr.isatty(),
        )
        # a bad --topics/--exclude-topics pattern, or a selection that takes nothing (--loop would
        # reread the file for ever): one line and exit 2, before any bus
        check_selected(a.file, opts)
    except ValueError as err:  # RecordingError is a ValueError
        sys.stderr.write(f"hil replay: {err}" + "\n")
        return EXIT_USAGE
    stop = threading.Event()
    # Ctrl-C sets the stop event (checked between messages and while pacing); in --step mode it
    # must also interrupt the blocking read of the Enter key, so there it stays KeyboardInterrupt.
    sigs = (signal.SIGTERM,) if a.step else (signal.SIGINT, signal.SIGTERM)
    prev = {s: signal.getsignal(s) for s in sigs}
    setter = EventSetter(stop)  # not stop.set() in the handler: hil.runtime.signals says why
    for s in prev:
        signal.signal(s, setter)
    session = open_session()
    bus: Any = None
    line: Any = None
    try:
        if a.gnss_serial:
            from hil.runners.serial import LineWriter

            line = LineWriter(a.gnss_baud, [a.gnss_serial])
            sys.stderr.write(f"hil replay: the GNSS line -> {a.gnss_serial}" + "\n")
        if a.can:
            from hil.can.bus import open_can_bus

            bus, desc = open_can_bus(
                a.can, a.can_interface, rig=a.rig or "default", session=session, receive=False
            )
            sys.stderr.write(f"hil replay: CAN frames -> {desc}" + "\n")
        stats = replay(a.file, opts, session, can_bus=bus, line=line, stop=stop)
    except KeyboardInterrupt:
        sys.stderr.write("hil replay: stopped\n")
        return EXIT_STOPPED
    except (ReplayError, RecordingError) as err:
        sys.stderr.write(f"hil replay: {err}" + "\n")
        return EXIT_FAILED if isinstance(err, ReplayError) else EXIT_USAGE
    except Exception as err:  # a CAN transport refusing to open, and similar boundary errors
        sys.stderr.write(f"hil replay: {type(err).__name__}: {err}" + "\n")
        return EXIT_FAILED
    finally:
        for s, h in prev.items():
            signal.signal(s, h)
        setter.close()  # a signal just before: its stop is set by now
        if bus is not None:
            bus.shutdown()
        if line is not None:
            line.close()
        session.close()
    sys.stdout.write(stats.summary() + "\n")
    return EXIT_STOPPED if stop.is_set() and not a.step else 0


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="hil replay", description="republish a recording onto Zenoh")
    add_args(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
