"""The ``--estimators`` list of the command lines (``hil sim``, ``hil up``, ``hil campaign``).

One parser, so every command refuses the same lists with the same words: an empty list quietly
ran the default set, and a repeated name ran that estimator twice, publishing each solution twice.
"""

from __future__ import annotations


def estimator_names(text: str, option: str = "--estimators") -> list[str]:
    """The names of a comma-separated list, spaces around them allowed; ValueError for an empty
    list, an empty item or a repeated name (the caller's user error, one line)."""
    names = [e.strip() for e in text.split(",")]
    if not any(names):
        raise ValueError(
            f"{option} {text!r} names no estimator: give names (a,b) or leave it out for the defaults"
        )
    if "" in names:
        raise ValueError(f"{option} {text!r} has an empty name: separate names with one comma")
    dup = sorted({e for e in names if names.count(e) > 1})
    if dup:
        raise ValueError(f"{option} {text!r} names {', '.join(dup)} more than once: name each estimator once")
    return names
