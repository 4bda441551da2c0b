"""Who published a sample: the rig's own processes, or someone else on the bus.

Zenoh names every sample's publisher in its source info (``hil.bus.pubsub.source_id``:
``"<zid>:<eid>"``, the session's Zenoh id and the publisher entity's). For the recorder to tell
the rig's traffic from a stranger's it must know the rig's session ids, so ``hil up`` chooses
them: it makes a secret per run (``RIG_KEY_ENV``, handed to its children only) and opens every
session of the rig (its own, each service's, each restart's) with an id that carries its own
proof, ``rig_zid(key)``: 8 random bytes and 8 bytes of their keyed hash. Whoever holds the key
checks any id without a list; without it, an id of the rig cannot be made up, and one in use
cannot be joined under (Zenoh refuses a second session with a live session's id).

What this does not stop: a process that can read the rig's samples can copy a source info onto
its own samples (zenoh-python's ``put(source_info=...)``). Closing the bus to strangers
(authentication, issue 18 item 3) is what makes the identity trustworthy; this makes it visible.

Without a key (a compose deployment, ``hil service`` by hand) every publisher counts as the rig's,
as before, and the recording says the rig's identity was unknown.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets

RIG_KEY_ENV = "HIL_RIG_KEY"  # hex; the per-run secret hil up hands to its children
ZENOH_ID_ENV = "HIL_ZENOH_ID"  # this process's Zenoh session id (hex, as Zenoh's config takes it)

RIG = "rig"
FOREIGN = "foreign"
UNKNOWN = "unknown"  # no key: the rig's identity cannot be checked


def new_rig_key() -> str:
    return secrets.token_hex(16)


def rig_key_from_env() -> str | None:
    """A rig key given to ``hil up`` (``HIL_RIG_KEY``): a rig whose processes or test clients
    start elsewhere (another machine, a test's own session) shares it to be the rig's. Unset: None."""
    key = os.environ.get(RIG_KEY_ENV, "").strip()
    if not key:
        return None
    try:
        ok = len(bytes.fromhex(key)) >= 16
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(
            f"{RIG_KEY_ENV} must be at least 32 hex digits (python -c 'import secrets; "
            f"print(secrets.token_hex(16))'), got {len(key)} characters that are not"
        )
    return key


def rig_zid(key: str) -> str:
    """A fresh Zenoh id of the rig's: 16 random hex digits (the first never 0: Zenoh refuses
    leading zeros) and 16 of their hash keyed with ``key``."""
    while True:
        nonce = secrets.token_hex(8)
        if nonce[0] != "0":
            return nonce + _mac(key, nonce)


def _mac(key: str, nonce: str) -> str:
    return hashlib.blake2b(nonce.encode(), key=bytes.fromhex(key), digest_size=8).hexdigest()


def is_rig_zid(key: str, zid: str) -> bool:
    return len(zid) == 32 and hmac.compare_digest(_mac(key, zid[:16]), zid[16:])


class RigIdentity:
    """Classifies publishers (``"<zid>:<eid>"``) as the rig's, foreign or unknown; cached."""

    def __init__(self, key: str | None) -> None:
        self.key = key or None
        self._cache: dict[str, str] = {}

    @classmethod
    def from_env(cls) -> RigIdentity:
        key = os.environ.get(RIG_KEY_ENV, "").strip()
        try:
            bytes.fromhex(key)
        except ValueError:
            key = ""
        return cls(key or None)

    @property
    def known(self) -> bool:
        return self.key is not None

    def classify(self, source: str) -> str:
        """``rig``, ``foreign`` or (without a key) ``unknown``."""
        hit = self._cache.get(source)
        if hit is not None:
            return hit
        if self.key is None:
            return UNKNOWN
        out = RIG if is_rig_zid(self.key, source.partition(":")[0]) else FOREIGN
        if len(self._cache) < 4096:  # a flood of made-up ids must not grow it without bound
            self._cache[source] = out
        return out
