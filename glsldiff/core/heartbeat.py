"""A line on stderr while a command is quiet: long steps (a grid build, a Monte Carlo render,
fTetWild, a factorisation) print a line before they start, but some take minutes; so that a
user or a log never sees a command silent for more than :data:`EVERY_S` seconds,
:class:`Heartbeat` watches what the command writes to stdout and stderr and, after that long
without a line, prints ``glsldiff: still working (T s; last: <the last line>)``."""
from __future__ import annotations

import sys
import threading
import time
from typing import Any, TextIO

__all__ = ["Heartbeat", "EVERY_S"]

#: Seconds of silence before a heartbeat line.
EVERY_S = 10.0


class _Watched:
    """A text stream that notes when it was last written to and its last non-empty line."""

    def __init__(self, inner: TextIO, beat: "Heartbeat") -> None:
        self._inner, self._beat = inner, beat

    def write(self, text: str) -> int:
        self._beat.saw(text)
        return self._inner.write(text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class Heartbeat:
    """Context manager around one command: ``sys.stdout`` and ``sys.stderr`` watched, a daemon
    thread printing the heartbeat line; both restored on exit."""

    def __init__(self, every: float = EVERY_S) -> None:
        self.every = every
        self._last = self._t0 = time.monotonic()
        self._line = ""
        self._stop = threading.Event()
        self._lock = threading.Lock()

    def saw(self, text: str) -> None:
        lines = [part.strip() for part in text.replace("\r", "\n").split("\n") if part.strip()]
        with self._lock:
            self._last = time.monotonic()
            if lines:
                self._line = lines[-1]

    def _run(self, err: TextIO) -> None:
        while not self._stop.wait(1.0):
            with self._lock:
                now = time.monotonic()
                quiet = now - self._last >= self.every
                if quiet:
                    self._last = now
                    last = self._line[:90] + ("..." if len(self._line) > 90 else "")
            if quiet:
                err.write(f"glsldiff: still working ({now - self._t0:.0f} s{'; last: ' + last if last else ''})\n")
                err.flush()

    def __enter__(self) -> "Heartbeat":
        self._out, self._err = sys.stdout, sys.stderr
        sys.stdout, sys.stderr = _Watched(self._out, self), _Watched(self._err, self)   # type: ignore[assignment]
        self._thread = threading.Thread(target=self._run, args=(self._err,), name="heartbeat", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        sys.stdout, sys.stderr = self._out, self._err
