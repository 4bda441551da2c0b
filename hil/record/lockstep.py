"""Lockstep between a replayer and the fusion it feeds: the consumer says how far it has got.

The fusion publishes, on ``hilack/<rig>/fusion``, the number of inputs it has taken from its inbox
and pushed through its core (ASCII decimal), after every input and every journal period. A
replayer in lockstep mode sends fusion input ``n`` only once the ack says ``n - window`` inputs
were consumed, so ``--afap`` never outruns the consumer (the PX4 #28783 failure: samples dropped
or shifted on a loaded machine) and the fresh fusion sees exactly the recorded sequence.

The key lives outside ``hil/<rig>/`` on purpose: it is flow control, not rig data, so the
recorder neither records it nor counts it as an unknown key.
"""

from __future__ import annotations

ACK_PREFIX = "hilack"


def ack_key(rig: str) -> str:
    """The key the fusion of ``rig`` acknowledges consumed inputs on."""
    return f"{ACK_PREFIX}/{rig}/fusion"


def encode_ack(consumed: int) -> bytes:
    return str(int(consumed)).encode()


def decode_ack(payload: bytes) -> int | None:
    """The count in an ack, or None for anything that is not a small non-negative integer."""
    if not payload or len(payload) > 20 or not payload.isdigit():
        return None
    return int(payload)
