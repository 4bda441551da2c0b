"""The IMU's device sample index and interval, recovered at the receiver.

Capture truth pairs with a measurement by ``seq``; the emulator's is the device sample index k.
So the bridge must publish ``seq = k`` even when frames are lost -- a lost sample then shows as a
seq gap and every sample still pairs exactly with its true capture time. The DBC status frame
carries ``SampleCount`` (the index of the sample that follows it, modulo 2^32, sent every 40th
sample and on a status change); between status frames the index advances by one per sample, or,
after the assembler reported lost frames, by the device-time gap in nominal periods.

A receiver that joins a running stream (a restarted ``can_bridge``) does not know the index until
the next status frame: numbering from 0 would reuse the seqs of samples published before its
restart and pair them with the wrong capture truth. With ``wait_for_count`` it returns None for
those samples (at most ``status_every`` - 1 of them, 0.1 s at 400 Hz), which the caller counts and
drops.
"""

from __future__ import annotations

from dataclasses import dataclass

SAMPLE_COUNT_MODULO = 1 << 32


@dataclass
class ImuSampleIndexer:
    """Feed each reassembled sample in order; get (device sample index, interval ns)."""

    nominal_dt_ns: int
    index: int | None = None
    prev_device_ns: int | None = None
    wait_for_count: bool = False  # joined mid-stream: no index before the first SampleCount

    def next(self, device_ns: int, sample_count: int | None, lost: bool) -> tuple[int, int] | None:
        """``sample_count``: SampleCount of a status frame received since the previous sample
        (it names this sample), else None; ``lost``: frames were lost since the previous one.
        None: the index is not known yet (``wait_for_count`` and no SampleCount seen)."""
        prev_i, prev_d = self.index, self.prev_device_ns
        if prev_i is None and sample_count is None and self.wait_for_count:
            return None
        if sample_count is not None:
            if prev_i is None:
                idx = sample_count
            else:  # unwrap the 32-bit count next to the prediction
                pred = prev_i + 1
                idx = sample_count + (
                    (pred - sample_count + SAMPLE_COUNT_MODULO // 2) // SAMPLE_COUNT_MODULO
                ) * (SAMPLE_COUNT_MODULO)
        elif prev_i is None:
            idx = 0
        elif lost and prev_d is not None and 0 < device_ns - prev_d <= 1_000_000_000:
            idx = prev_i + max(1, round((device_ns - prev_d) / self.nominal_dt_ns))
        else:
            idx = prev_i + 1
        gap = idx - prev_i if prev_i is not None else 1
        dt = self.nominal_dt_ns
        if prev_d is not None and gap >= 1:
            per = (device_ns - prev_d) / gap
            # a clock step or a wrong gap: the nominal period, not a nonsense interval
            if abs(per - self.nominal_dt_ns) <= 0.1 * self.nominal_dt_ns:
                dt = round(per)
        self.index, self.prev_device_ns = idx, device_ns
        return idx, dt
