"""Peak memory of a piece of work, for the benchmarks that print memory beside time.

Linux keeps a process's peak resident set (``VmHWM`` in ``/proc/self/status``) and lets the
process reset it (writing ``5`` to ``/proc/self/clear_refs``), so :class:`PeakMemory` measures
everything the work allocated, compiled libraries (SuperLU, pyamg) included, not only what
numpy reports: the peak resident set during the block minus the resident set before it.
Before the block, freed heap memory is handed back to the system (glibc ``malloc_trim``), so
what an earlier piece of work freed but kept resident (SuperLU's factor) does not hide the next
one's growth. Elsewhere the figure is NaN.
"""
from __future__ import annotations

import ctypes
import math
from pathlib import Path
from types import TracebackType

__all__ = ["PeakMemory"]

_STATUS = Path("/proc/self/status")
_CLEAR = Path("/proc/self/clear_refs")


def _trim() -> None:
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _status_kib(field: str) -> float:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return math.nan


class PeakMemory:
    """``with PeakMemory() as mem: ...`` then ``mem.mib``: the peak resident memory the block
    added, MiB (NaN where the peak cannot be reset)."""

    def __init__(self) -> None:
        self.mib = math.nan
        self._before = math.nan

    def __enter__(self) -> "PeakMemory":
        _trim()
        try:
            _CLEAR.write_text("5")   # reset VmHWM to the current resident set
        except OSError:
            return self
        self._before = _status_kib("VmRSS")
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        if not math.isnan(self._before):
            self.mib = max(_status_kib("VmHWM") - self._before, 0.0) / 1024.0
