"""One line on stderr before and after each case of a benchmark, with the time left estimated
from the cases done so far (cases of one study cost alike only roughly, hence "about")."""
from __future__ import annotations

import sys
import time
from typing import Callable

__all__ = ["Cases"]


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class Cases:
    """``before(what)`` / ``after(result)`` around each of ``total`` cases of ``study``:
    ``"bench fit: lambda 2/3: lambda 1e-05, about 40 s left"`` ... ``"... E 0.0013 in 20.1 s"``."""

    def __init__(self, study: str, total: int, say: Callable[[str], None] | None = None) -> None:
        self.study, self.total, self.done, self.seconds = study, max(int(total), 1), 0, 0.0
        self.say = say or _stderr
        self._what, self._t0 = "", time.perf_counter()

    def before(self, what: str) -> None:
        self._what, self._t0 = what, time.perf_counter()
        left = (f", about {self.seconds / self.done * (self.total - self.done):.0f} s left"
                if self.done else "")
        self.say(f"{self.study} {self.done + 1}/{self.total}: {what}{left}")

    def after(self, result: str = "done") -> float:
        """Close the case; returns its seconds."""
        seconds = time.perf_counter() - self._t0
        self.done += 1
        self.seconds += seconds
        self.say(f"{self.study} {self.done}/{self.total}: {self._what}: {result} in {seconds:.1f} s")
        return seconds
