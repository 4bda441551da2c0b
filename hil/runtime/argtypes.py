"""argparse value types shared by the CLI and the services' own entry points."""

from __future__ import annotations

import argparse


def positive_float(text: str) -> float:
    """A number > 0, or a one-line argparse error naming the value."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return v
