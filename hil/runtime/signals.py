"""A signal handler that sets a ``threading.Event`` without ever waiting for its lock.

Python runs a signal handler in the main thread between two bytecodes, and those may be of that
thread's own ``event.wait(timeout)``: ``threading`` is Python code, and right after a timed wait
returns the event's lock (a plain, non-reentrant ``Lock``) is held. ``event.set()`` in the
handler then waits for ever for a lock its own thread holds. Seen: a recorder paused (SIGSTOP),
resumed (SIGCONT) and told to stop (SIGTERM) at once never stopped -- its run loop's 0.5 s wait
had run out while it was stopped, so the pending SIGTERM's handler ran with the lock held. Every
service, ``hil up`` and ``hil replay`` wait on their stop event that way.

:class:`EventSetter` is the handler: it writes a byte to a pipe (no lock) and a thread of its own
reads it and sets the event, a few microseconds later, from outside the main thread.
"""

from __future__ import annotations

import contextlib
import os
import threading


class EventSetter:
    """``signal.signal(sig, EventSetter(stop))``: the signal sets ``stop`` (through a thread of
    this object's, never in the handler). :meth:`close` ends the thread; a process that keeps the
    handler for its life need not call it."""

    def __init__(self, event: threading.Event) -> None:
        self.event = event
        self._r, self._w = os.pipe()
        os.set_blocking(self._w, False)
        self._thread = threading.Thread(target=self._watch, name="signal-event-setter", daemon=True)
        self._thread.start()

    def __call__(self, _signum: int = 0, _frame: object = None) -> None:
        # a full pipe (signals faster than the thread reads) already holds a byte that sets it;
        # a closed one belongs to a handler that was taken down
        with contextlib.suppress(OSError):
            os.write(self._w, b"\x00")

    def _watch(self) -> None:
        while True:
            try:
                data = os.read(self._r, 64)
            except OSError:
                return
            if not data:  # the write end closed: close()
                return
            self.event.set()

    def close(self) -> None:
        """End the thread (after setting the event if a signal came in just before)."""
        if self._w < 0:
            return
        os.close(self._w)
        self._w = -1
        self._thread.join()
        os.close(self._r)
