"""Stop requests (Ctrl-C, SIGTERM) that cannot be lost.

Python delivers a signal by raising in whatever code runs at that moment; when that is a
weakref callback or a __del__ (garbage collection inside torch or h5py), the interpreter prints
"Exception ignored" and carries on, so a plain KeyboardInterrupt can vanish and the run
completes. The handler therefore also records the request, and long loops call
`check_stop()` at safe points (DatasetWriter.write, once per chunk), which raises it again.
"""

from __future__ import annotations

import contextlib
import signal

_pending: int | None = None


class Interrupted(KeyboardInterrupt):
    """A stop request (SIGINT or SIGTERM), raised like Ctrl-C so every `with`/`finally` cleans up."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _handler(signum, frame) -> None:
    global _pending
    _pending = signum
    raise Interrupted(signum)


def install() -> None:
    """SIGINT and SIGTERM raise Interrupted (and stay pending until handled by the app's exit)."""
    global _pending
    _pending = None
    signal.signal(signal.SIGTERM, _handler)
    signal.signal(signal.SIGINT, _handler)


def check_stop() -> None:
    """Raise Interrupted if a stop was requested (call at safe points of long loops)."""
    if _pending is not None:
        raise Interrupted(_pending)


def pending() -> int | None:
    return _pending


def _record(signum, frame) -> None:
    global _pending
    _pending = signum


@contextlib.contextmanager
def deferred(raise_on_exit: bool = True):
    """A block that a stop request does not cut: inside, Ctrl-C / SIGTERM are recorded, not raised;
    they are raised on leaving the block (raise_on_exit; else at the caller's next `check_stop()`).
    For HDF5 writes: an exception raised while h5py's C code runs (a dataset being created or
    flushed) leaves objects that fail again when the interpreter exits, a traceback after the
    one-line message."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield  # handlers can only be set in the main thread; there, nothing is delivered anyway
        return
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in previous:
        signal.signal(s, _record)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if raise_on_exit:
        check_stop()


__all__ = ["Interrupted", "install", "check_stop", "pending", "deferred"]
