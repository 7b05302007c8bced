"""Stop requests (Ctrl-C, SIGTERM) that cannot be lost.

Python delivers a signal by raising in whatever code runs at that moment; when that is a
weakref callback or a __del__ (garbage collection inside torch or h5py), the interpreter prints
"Exception ignored" and carries on, so a plain KeyboardInterrupt can vanish and the run
completes. The handler therefore also records the request, and long loops call
`check_stop()` at safe points (DatasetWriter.write, once per chunk), which raises it again.
"""

from __future__ import annotations

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


__all__ = ["Interrupted", "install", "check_stop", "pending"]
