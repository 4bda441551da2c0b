"""Which keys a recording keeps: Zenoh key expressions to include and to exclude.

``include`` empty means every key; a key is kept when some include pattern contains it and no
exclude pattern does (``zenoh.KeyExpr.includes``: ``*`` one chunk, ``**`` any number). A pattern
not starting with ``hil/`` is relative to the rig (``can/**`` -> ``hil/<rig>/can/**``). The
answer is cached per key: a rig has tens of keys, the recorder sees thousands of messages a second.
"""

from __future__ import annotations

import zenoh


class KeyFilterError(ValueError):
    """A pattern that is not a valid Zenoh key expression; the message names it."""


class KeyFilter:
    def __init__(
        self, rig: str, include: list[str] | tuple[str, ...], exclude: list[str] | tuple[str, ...]
    ) -> None:
        self.include = [self._expr(rig, p, "include") for p in include]
        self.exclude = [self._expr(rig, p, "exclude") for p in exclude]
        self._cache: dict[str, bool] = {}

    @staticmethod
    def _expr(rig: str, pattern: str, what: str) -> zenoh.KeyExpr:
        full = pattern if pattern.startswith("hil/") else f"hil/{rig}/{pattern.lstrip('/')}"
        try:
            return zenoh.KeyExpr.autocanonize(full)
        except Exception as err:
            raise KeyFilterError(f"{what} pattern {pattern!r} is not a Zenoh key expression: {err}") from None

    @property
    def active(self) -> bool:
        return bool(self.include or self.exclude)

    def keeps(self, key: str) -> bool:
        ok = self._cache.get(key)
        if ok is None:
            try:
                k = zenoh.KeyExpr(key)
            except Exception:
                ok = not self.include
            else:
                ok = (not self.include or any(p.includes(k) for p in self.include)) and not any(
                    p.includes(k) for p in self.exclude
                )
            self._cache[key] = ok
        return ok
