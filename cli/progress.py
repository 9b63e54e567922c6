"""Progress on the console: a tqdm bar that keeps its clock moving through long steps (a line
every few seconds when stderr is not a terminal), with log lines written above it, and one bar
for a command's successive phases."""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

TICK_SECONDS = 1.0
"""How often a shown progress bar is drawn again on a terminal while its count stands still (a
long step: the first frame of a run, a registration), so that its clock shows the command is
alive."""

HEARTBEAT_SECONDS = 10.0
"""The same when stderr is not a terminal (a file, a pipe, a CI log): a line every 10 s at most,
not one a second."""


@contextlib.contextmanager
def progress_bar(
    desc: str, unit: str, total: int | None = None, hidden: bool = False
) -> Iterator[Any]:
    """A tqdm bar on stderr; hidden with `gsc -q`, with --json, or when `hidden` is set. Log
    lines written to the console while it is shown go above it rather than onto its line. It is
    drawn again every `TICK_SECONDS` on a terminal, every `HEARTBEAT_SECONDS` elsewhere, from
    its delay on (its elapsed time moves during a long step)."""
    from tqdm import tqdm

    quiet = logging.getLogger("gscompress").getEffectiveLevel() > logging.INFO
    # delay: a command that fails at once prints its error without an empty bar before it
    with tqdm(
        total=total, desc=desc, unit=unit, leave=False, disable=hidden or quiet, delay=0.5
    ) as bar:
        root = logging.getLogger()
        handlers = list(root.handlers)
        root.handlers = [
            _AboveBar(h, bar) if type(h) is logging.StreamHandler else h for h in handlers
        ]
        stop = threading.Event()
        if not bar.disable:
            every = TICK_SECONDS if _is_terminal(sys.stderr) else HEARTBEAT_SECONDS
            threading.Thread(
                target=_tick, args=(bar, stop, every), name="bar-tick", daemon=True
            ).start()
        try:
            yield bar
        finally:
            stop.set()
            root.handlers = handlers


def _is_terminal(stream: Any) -> bool:
    """Whether `stream` is a terminal."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _tick(bar: Any, stop: threading.Event, every: float) -> None:
    """Draw `bar` again `every` seconds until `stop` is set (from its delay on).

    It takes only tqdm's thread lock, for as long as one drawing, and never waits for it long:
    tqdm's own `refresh` takes its process lock too and keeps both when the drawing raises (a
    closed pipe), which on this thread would leave the command's own thread waiting forever.
    A console that cannot be written ends the ticking."""
    lock = getattr(bar.get_lock(), "th_lock", None)
    while not stop.wait(every):
        if lock is None or bar.disable or time.time() < bar.start_t + bar.delay:
            continue
        if not lock.acquire(timeout=every):
            continue
        try:
            bar.refresh(nolock=True)
            _drawn(bar)
        except (OSError, ValueError):  # (a closed pipe or file)
            return
        finally:
            lock.release()


def _drawn(bar: Any) -> None:
    """Record that `bar` is on the console: tqdm tells a shown bar by the time of its last
    update's drawing, and a bar drawn otherwise (`refresh`, `reset`) would be left on its line
    by `close` and by log lines (`_AboveBar`). Its next update then counts its rate from the
    end of its delay, at most that much later than its start."""
    bar.last_print_t = max(bar.last_print_t, bar.start_t + bar.delay)


class Phases:
    """One progress bar for a command's successive phases (the frames of a run, its final
    refinement, its final scoring...): a pipeline's `phases(name, done, total)` callback.

    The first call with a new `name` starts that phase on the bar (its description, count,
    clock and unit, `units[name]` or "step"); each call moves the count to `done` of `total`
    (None: a count without an end, such as the cuts a byte budget tries).
    """

    def __init__(self, bar: Any, units: dict[str, str] | None = None) -> None:
        self.bar, self.units, self.name = bar, units or {}, ""

    def __call__(self, name: str, done: int, total: int | None) -> None:
        bar = self.bar
        if name != self.name:
            self.name = name
            bar.set_postfix_str("", refresh=False)
            bar.set_description_str(name, refresh=False)
            bar.unit = self.units.get(name, "step")
            bar.initial = 0
            if not bar.disable and time.time() >= bar.start_t + bar.delay:  # (drawn anew)
                bar.reset(total)
                _drawn(bar)
            else:  # (not drawn before its delay: a command that fails at once shows no bar)
                bar.n = bar.last_print_n = 0
        bar.total = total
        bar.update(done - bar.n)


class _AboveBar(logging.Handler):
    """A console handler's lines written above a shown progress bar (tqdm's own logging
    redirect also draws a bar still in its delay, which then stays on the error's line)."""

    def __init__(self, console: logging.StreamHandler[Any], bar: Any):
        super().__init__(console.level)
        self.console, self.bar = console, bar

    def emit(self, record: logging.LogRecord) -> None:
        bar = self.bar
        if bar.disable or bar.last_print_t < bar.start_t + bar.delay:  # not shown (yet)
            self.console.handle(record)
            return
        with bar.external_write_mode(file=self.console.stream):
            self.console.handle(record)


def advance(bar: Any, done: int, total: int) -> None:
    """Move a `progress_bar` to `done` of `total` (the pipeline's progress callbacks)."""
    bar.total = total
    bar.update(done - bar.n)
