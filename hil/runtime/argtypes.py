"""argparse value types shared by the CLI, the benches and the services' own entry points.

Every number a user types is checked here, before any process starts: a finite value in a
stated range, or one line naming the value and the range (exit 2). Why bounds and not only
"> 0": ``inf`` and ``1e300`` parse as floats and used to start seven processes and then die, or
end in an ``OverflowError`` or a 14 TiB allocation in ``hil sim``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import NoReturn

from hil.nav.limits import MAX_DURATION_S, MAX_SPEED, MIN_SPEED

MAX_RESTARTS = 100  # restarts per service; more is a crash loop, not supervision
MAX_SECONDS = 1e7  # any other span of seconds (monitor, fault, replay window): ~116 days


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr and exit code 2.

    argparse prints the whole usage (many lines for ``hil up``) before the error; a script or a
    test reading stderr wants the one line that says what was wrong and where to look.
    """

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def finite_float(text: str) -> float:
    """Any finite number (a node's own flag; its options check the range)."""
    return _number(text)


def bounded_float(lo: float, hi: float, *, lo_open: bool = False, unit: str = "") -> Callable[[str], float]:
    """A type accepting finite numbers in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``)."""
    left = "(" if lo_open else "["
    span = f"{left}{lo:g}, {hi:g}]{(' ' + unit) if unit else ''}"

    def parse(text: str) -> float:
        v = _number(text)
        if v < lo or v > hi or (lo_open and v == lo):
            raise argparse.ArgumentTypeError(f"{text!r} is out of range: use a number in {span}")
        return v

    parse.__name__ = f"number in {span}"
    return parse


def bounded_int(lo: int, hi: int) -> Callable[[str], int]:
    """A type accepting whole numbers in ``[lo, hi]``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{text!r} is out of range: use a whole number in [{lo}, {hi}]")
        return v

    parse.__name__ = f"whole number in [{lo}, {hi}]"
    return parse


def positive_float(text: str) -> float:
    """A finite number > 0 (and at most 1e9: larger is a typo for any setting here)."""
    v = _number(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    if v > 1e9:
        raise argparse.ArgumentTypeError(f"{text!r} is out of range: use a number in (0, 1e9]")
    return v


duration_s = bounded_float(0.0, MAX_DURATION_S, lo_open=True, unit="s")
speed = bounded_float(MIN_SPEED, MAX_SPEED)
seconds = bounded_float(0.0, MAX_SECONDS, unit="s")  # a span that may be 0
restart_count = bounded_int(0, MAX_RESTARTS)


def fail(prog: str, message: str) -> NoReturn:
    """One line on stderr and exit code 2, for checks argparse cannot make (one value vs another)."""
    sys.stderr.write(f"{prog}: error: {message}\n")
    raise SystemExit(2)
