"""Recorded outputs against the emulators' capture truth (``hil.CaptureTruth``, paired by seq):
what the time-sync and pacing benches score a live recording with."""

from __future__ import annotations

import numpy as np


def restamp_errors(session: object, sensor: str) -> tuple[np.ndarray, np.ndarray]:
    """(true capture s, synced stamp - true capture ns) for every synced measurement of a
    recording, paired with the emulator's capture truth by ``seq``."""
    from hil.record.mcapio import Session

    assert isinstance(session, Session)
    truth = {}
    for r in session.records:
        if r.topic.endswith(f"/capture/{sensor}"):
            m = r.decode()
            truth[m.seq] = m.true_stamp_ns  # type: ignore[attr-defined]
    t, e = [], []
    for r in session.records:
        if r.topic.endswith(f"/synced/{sensor}"):
            m = r.decode()
            tt = truth.get(m.seq)  # type: ignore[attr-defined]
            if tt is not None:
                t.append(tt * 1e-9)
                e.append(m.stamp_ns - tt)  # type: ignore[attr-defined]
    return np.asarray(t), np.asarray(e, dtype=np.int64)
