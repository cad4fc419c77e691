"""Command-line option types: every number checked when it is parsed, one line on error.

Each type names what it wants (``must be a positive integer, got '0'``); :class:`Parser`
prints argparse's errors as one line and exits with code 2.
"""

from __future__ import annotations

import argparse

import numpy as np

__all__ = ["Parser", "finite_float", "fraction", "nonnegative_float", "positive_float",
           "positive_int", "unit_fraction"]


class Parser(argparse.ArgumentParser):
    """Bad options: one line naming the option and exit code 2 (not argparse's usage block)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(kind, test, what):
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            v = None
        if v is None or not np.isfinite(v) or not test(v):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return v
    parse.__name__ = what  # argparse names the type in its messages
    return parse


positive_int = _number(int, lambda v: v > 0, "a positive integer")
positive_float = _number(float, lambda v: v > 0, "a positive number")
nonnegative_float = _number(float, lambda v: v >= 0, "a number >= 0")
fraction = _number(float, lambda v: 0 < v < 1, "a number in (0, 1)")
unit_fraction = _number(float, lambda v: 0 < v <= 1, "a number in (0, 1]")
finite_float = _number(float, lambda v: True, "a finite number")
