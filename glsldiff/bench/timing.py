"""Repeated timing, shared by every benchmark (one place: no bench times its runs its own way;
the peers' labels are in :mod:`glsldiff.bench.peers`).

Timing: :func:`repeat` runs the same work ``repeats`` times and keeps every run's seconds;
:class:`Timing` gives their minimum and median (the figure a bench prints and the README
quotes is the median; with one run it says "1 run" instead of pretending to a median) and the
last run's result. A run is timed by the wall clock around the call, or by the seconds the run
reports itself (a GPU solve timed with the GPU finished, the bench's own error measurements
left out). Which first-run costs (GL context, shader compilation, AMG or LU set-up) a timing
holds is the bench's choice, stated in its table caption; the first run's time is kept apart
(``t_first_s``) so a cold first run shows.
"""
from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence

__all__ = ["Timing", "repeat", "median_min", "runs_note", "timing_columns", "TIME_COLUMNS"]

#: The CSV columns of a repeated timing (:meth:`Timing.columns`).
TIME_COLUMNS = ("t_median_s", "t_min_s", "repeats")


@dataclass
class Timing:
    """The seconds of ``repeats`` runs of the same work and the last run's result."""

    times: list[float] = field(default_factory=list)
    result: Any = None

    @property
    def repeats(self) -> int:
        return len(self.times)

    @property
    def min(self) -> float:
        return min(self.times) if self.times else math.nan

    @property
    def median(self) -> float:
        return float(statistics.median(self.times)) if self.times else math.nan

    @property
    def first(self) -> float:
        return self.times[0] if self.times else math.nan

    def columns(self, first: bool = False) -> dict[str, object]:
        """``t_median_s``, ``t_min_s``, ``repeats`` (and ``t_first_s`` with ``first``)."""
        return timing_columns(self.times, first=first)


def repeat(run: Callable[[], Any], repeats: int, seconds: Callable[[Any], float] | None = None) -> Timing:
    """Call ``run()`` ``repeats`` (>= 1) times. Each run is timed by the wall clock around the
    call or, with ``seconds``, by ``seconds(result)`` (a run that times itself). Returns the
    times and the last run's result."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    out = Timing()
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = run()
        elapsed = time.perf_counter() - t0
        out.times.append(float(seconds(result)) if seconds is not None else elapsed)
        out.result = result
    return out


def median_min(values: Iterable[float]) -> tuple[float, float]:
    """``(median, min)`` of per-run values; NaN when any run has none (e.g. a run that never
    reached an error level): a median over the runs that happened to get there would flatter."""
    vals = [float(v) for v in values]
    if not vals or any(math.isnan(v) for v in vals):
        return math.nan, math.nan
    return float(statistics.median(vals)), min(vals)


def timing_columns(times: Sequence[float], first: bool = False) -> dict[str, object]:
    """The CSV columns of per-run seconds ``times``: median, min, repeats (and the first run)."""
    med, lo = median_min(times)
    cols: dict[str, object] = {"t_median_s": med, "t_min_s": lo, "repeats": len(times)}
    if first:
        cols["t_first_s"] = float(times[0]) if len(times) else math.nan
    return cols


def runs_note(repeats: int) -> str:
    """How a printed time was obtained: ``"median of 3 runs"``, or ``"1 run"`` (no median)."""
    return "1 run" if repeats == 1 else f"median of {repeats} runs"

