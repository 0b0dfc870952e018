"""Ctrl-C during long calls into compiled code: Python runs its SIGINT handler only between
bytecodes of the main thread, so a SuperLU factorisation of a large system held an interrupt
off for half a minute (``glsldiff demo``, ``bench fit``). :func:`interruptible` runs such a call
in a worker thread (SuperLU releases the GIL) while the main thread waits in short slices, so
KeyboardInterrupt is raised within :data:`POLL_S`; the abandoned worker finishes in the
background (a daemon thread: it does not keep the program alive)."""
from __future__ import annotations

import threading
from typing import Any, Callable, TypeVar

__all__ = ["interruptible", "abandoned", "POLL_S"]

T = TypeVar("T")
#: How often the waiting main thread lets a pending Ctrl-C through, seconds.
POLL_S = 0.2
_WORKERS: list[threading.Thread] = []


def abandoned() -> bool:
    """Whether a call interrupted by Ctrl-C is still running in its worker: the program should
    then end with ``os._exit`` after its message (an interpreter shutting down around compiled
    code still running in a thread can fail while flushing its streams)."""
    return any(w.is_alive() for w in _WORKERS)


def interruptible(fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """``fn(*args, **kwargs)``, interruptible by Ctrl-C within :data:`POLL_S` seconds when
    called from the main thread (elsewhere: called directly). Its exception is re-raised here."""
    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    box: dict[str, Any] = {}
    done = threading.Event()

    def work() -> None:
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as exc:   # handed to the caller
            box["error"] = exc
        finally:
            done.set()

    worker = threading.Thread(target=work, name=f"interruptible {getattr(fn, '__name__', 'call')}", daemon=True)
    worker.start()
    _WORKERS.append(worker)
    # wait on an event, not on the thread: Ctrl-C inside Thread.join leaves the thread's state
    # broken for the interpreter's shutdown
    while not done.wait(POLL_S):
        pass
    worker.join()
    _WORKERS.remove(worker)
    if "error" in box:
        raise box["error"]
    return box["value"]
