"""The stop signal's handler never waits for the stop event's lock (hil.runtime.signals)."""

from __future__ import annotations

import signal
import threading

from hil.runtime.signals import EventSetter


def test_a_signal_while_the_main_thread_holds_the_events_lock_stops_once_it_lets_go() -> None:
    """Where a timed ``stop.wait()`` holds the event's lock as it returns, the handler runs: a
    handler calling ``stop.set()`` waited there for ever (the recorder that never stopped after
    SIGSTOP, SIGCONT, SIGTERM). This one returns at once; the event is set once the lock is free."""
    stop = threading.Event()
    setter = EventSetter(stop)
    try:
        with stop._cond:  # type: ignore[attr-defined]  # the lock Event.wait holds as it returns
            setter(signal.SIGTERM, None)  # returns: nothing here waits for the lock
            assert not stop.is_set()  # the setter's thread waits for it instead
        assert stop.wait(timeout=60)
    finally:
        setter.close()


def test_a_signal_just_before_close_has_set_the_event_when_close_returns() -> None:
    """``hil replay`` reads the event after it takes its handlers down: a signal that came in just
    before must show (its exit code says it was stopped)."""
    stop = threading.Event()
    setter = EventSetter(stop)
    setter(signal.SIGINT, None)
    setter.close()
    assert stop.is_set()
    setter(signal.SIGINT, None)  # after close: ignored, no error
    setter.close()  # twice: nothing


def test_a_real_signal_sets_the_event_through_the_handler() -> None:
    stop = threading.Event()
    setter = EventSetter(stop)
    previous = signal.signal(signal.SIGUSR2, setter)
    try:
        signal.raise_signal(signal.SIGUSR2)
        assert stop.wait(timeout=60)
    finally:
        signal.signal(signal.SIGUSR2, previous)
        setter.close()
