"""SIGTERM handled as Ctrl-C, so that a killed command cleans up as an interrupted one does."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

_received = threading.Event()


def _interrupt(signum: int, frame: object) -> None:
    _received.set()
    raise KeyboardInterrupt


def interrupted() -> bool:
    """Whether SIGTERM arrived within the current `sigterm_interrupts` block. The
    KeyboardInterrupt it raises can surface as another error when it lands inside library code
    (in a thread pool's lock, a RuntimeError "release unlocked lock"): such an error is the
    interrupt, not a failure of its own."""
    return _received.is_set()


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """Within the block, SIGTERM raises KeyboardInterrupt in the main thread: temporary outputs
    are removed and worker processes stopped on the way out, as on Ctrl-C. (Only the main
    thread can take signals; elsewhere the block changes nothing.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
