"""Command-line parsing shared by ``glsldiff`` and the calibration commands: a parser whose
usage errors are one line, and argument types that check each value while the arguments are
parsed, so a bad number fails before any work (``--seed -1``, ``--size -4 8 8``,
``--max-seconds 0``, ``--noise nan``). Lengths in mm."""
from __future__ import annotations

import argparse
import math
from typing import Callable, NoReturn

from glsldiff.core.errors import InputError


class CommandParser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors raise InputError: the command prints them as one error
    line with status 2, like every other bad input (``glsldiff`` and the calibration commands)."""

    def error(self, message: str) -> NoReturn:
        raise InputError(f"{self.prog}: {message} (see --help)")


def integer(lo: int, hi: float = math.inf) -> Callable[[str], int]:
    """An integer in [lo, hi]."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if not lo <= v <= hi:
            rng = f">= {lo}" if hi == math.inf else f"in [{lo}, {int(hi)}]"
            raise argparse.ArgumentTypeError(f"must be an integer {rng}, got {v}")
        return v
    parse.__name__ = "integer"
    return parse


def number(lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False,
           allow_inf: bool = False) -> Callable[[str], float]:
    """A real number in [lo, hi] ((lo, hi] with ``lo_open``); NaN never, inf only with ``allow_inf``."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        bad = math.isnan(v) or (math.isinf(v) and not allow_inf) or (v <= lo if lo_open else v < lo) or v > hi
        if bad:
            left = "(" if lo_open else "["
            right = "]" if math.isfinite(hi) else ")"
            raise argparse.ArgumentTypeError(f"must be a number in {left}{lo:g}, {hi:g}{right}, got {text}")
        return v
    parse.__name__ = "number"
    return parse


seed = integer(0, 2**32 - 1)
positive = number(0.0, lo_open=True)
nonnegative = number(0.0)
