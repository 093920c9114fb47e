"""Progress people can read: one live line on a terminal, plain periodic lines elsewhere.

The long commands (``repair``, ``demo``, ``replay``, ``convert``, ``fixer pretrain``,
``report``) show their progress through :class:`Progress`:

- on a terminal, a single live display (tqdm) that redraws in place; log lines printed through
  :meth:`Progress.write` (and the ``logging`` module while it runs) appear above it;
- when the output goes to a file or a pipe, a plain line every ``every_s`` seconds (default 30,
  ``GSFIX_PROGRESS_EVERY_S`` in the environment changes it) with the count, the rate, the time
  left and what the job waits for, and one line at the end. No carriage returns, so a log file
  reads line by line.

This is outer-layer code: components report through a callback or a count, never through this.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack
from typing import Any, TextIO, TypeVar

logger = logging.getLogger(__name__)

EVERY_ENV = "GSFIX_PROGRESS_EVERY_S"
DEFAULT_EVERY_S = 30.0

T = TypeVar("T")


def default_every_s() -> float:
    """Seconds between plain lines: ``GSFIX_PROGRESS_EVERY_S`` or 30."""
    raw = os.environ.get(EVERY_ENV, "").strip()
    if not raw:
        return DEFAULT_EVERY_S
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{EVERY_ENV} must be a positive number of seconds, got {raw!r}")
    return value


def _duration(s: float) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    s = max(0.0, s)
    if s < 60:
        return f"{s:.0f} s"
    m, sec = divmod(int(round(s)), 60)
    if m < 60:
        return f"{m} min {sec:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


def _is_tty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or not a real stream
        return False


class Progress:
    """A count towards an optional total, shown live on a terminal or as periodic plain lines.

    ``total`` may grow while it runs (:meth:`set`); ``text`` is a short note (e.g. a loss) and
    ``waiting`` what the job waits for, both shown in the display. Thread-safe: a watcher thread
    may call :meth:`set` while another writes log lines.
    """

    def __init__(
        self,
        desc: str,
        total: int | None = None,
        unit: str = "item",
        *,
        enabled: bool = True,
        stream: TextIO | None = None,  # default: standard error
        every_s: float | None = None,  # plain lines; default: default_every_s()
        live: bool | None = None,  # default: whether ``stream`` is a terminal
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.desc = desc
        self.unit = unit
        self.total = total
        self.n = 0
        self.text = ""
        self.waiting = ""
        self.enabled = enabled
        self.stream: TextIO = stream if stream is not None else sys.stderr
        self.every_s = default_every_s() if every_s is None else float(every_s)
        if not (math.isfinite(self.every_s) and self.every_s > 0):
            raise ValueError(f"every_s must be a positive number of seconds, got {every_s!r}")
        self.live = _is_tty(self.stream) if live is None else live
        self._clock = clock
        self._t0 = clock()
        self._next_line = self._t0 + self.every_s
        self._lock = threading.RLock()
        self._closed = False
        self._bar: Any = None
        self._stack = ExitStack()
        if enabled and self.live:
            from tqdm import tqdm
            from tqdm.contrib.logging import logging_redirect_tqdm

            self._bar = tqdm(
                total=total, desc=desc, unit=unit, file=self.stream, leave=False,
                dynamic_ncols=True, mininterval=0.2,
            )  # fmt: skip
            # log records go through tqdm.write while the bar is up, so they do not break it
            self._stack.enter_context(logging_redirect_tqdm())

    # -- updates -----------------------------------------------------------------------------

    def update(self, n: int = 1) -> None:
        """``n`` more done."""
        with self._lock:
            self.set(self.n + n)

    def set(
        self,
        n: int | None = None,
        total: int | None = None,
        text: str | None = None,
        waiting: str | None = None,
    ) -> None:
        """Set the count, the total, the note or what it waits for (``""`` clears it)."""
        with self._lock:
            if n is not None:
                self.n = int(n)
            if total is not None:
                self.total = int(total)
            if text is not None:
                self.text = text
            if waiting is not None:
                self.waiting = waiting
            if self._bar is not None:
                self._bar.total = self.total
                self._bar.n = self.n
                self._bar.set_postfix_str(self._note(), refresh=False)
                self._bar.refresh()
            self.tick()

    def tick(self) -> None:
        """Print the plain line when it is due (callers that wait call this now and then)."""
        if not self.enabled or self.live or self._closed:
            return
        with self._lock:
            now = self._clock()
            if now < self._next_line:
                return
            self._next_line = now + self.every_s
            self._print(self.line(now))

    # -- text --------------------------------------------------------------------------------

    def _note(self) -> str:
        parts = [self.text] if self.text else []
        if self.waiting:
            parts.append(f"waiting for {self.waiting}")
        return "; ".join(parts)

    def line(self, now: float | None = None) -> str:
        """The plain line: ``desc: n/total units (p %), rate, elapsed, left; note``."""
        now = self._clock() if now is None else now
        elapsed = max(now - self._t0, 1e-9)
        rate = self.n / elapsed
        units = self.unit if self.n == 1 and not self.total else f"{self.unit}s"
        if self.total:
            count = f"{self.n}/{self.total} {units} ({100.0 * self.n / self.total:.0f} %)"
        else:
            count = f"{self.n} {units}"
        parts = [count, f"{rate:.2f} {self.unit}/s", f"{_duration(elapsed)} elapsed"]
        if self.total and 0 < self.n < self.total:
            parts.append(f"about {_duration((self.total - self.n) / rate)} left")
        note = self._note()
        return f"{self.desc}: {', '.join(parts)}" + (f"; {note}" if note else "")

    def _print(self, line: str) -> None:
        self.stream.write(line + "\n")
        self.stream.flush()

    def write(self, line: str) -> None:
        """A log line that keeps the live display intact (printed as is otherwise)."""
        line = line.rstrip("\n")
        with self._lock:
            if self._bar is not None:
                self._bar.write(line, file=self.stream)
            else:
                self._print(line)

    def lines(self) -> _LineSink:
        """A file-like object whose lines go through :meth:`write` (for subprocess output)."""
        return _LineSink(self)

    # -- end ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Take the live display down; in plain mode print the last line."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._bar is not None:
                self._bar.close()
                self._stack.close()
            elif self.enabled:
                self._print(self.line() + " (done)")

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _LineSink:
    """``write()``/``flush()`` that hands complete lines to a :class:`Progress`."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self._buf = ""

    def write(self, s: str) -> int:
        self._buf += s
        *done, self._buf = self._buf.split("\n")
        for line in done:
            self.progress.write(line)
        return len(s)

    def flush(self) -> None:
        pass


def track(
    items: Iterable[T],
    desc: str,
    total: int | None = None,
    unit: str = "item",
    *,
    enabled: bool = True,
    stream: TextIO | None = None,
    every_s: float | None = None,
) -> Iterator[T]:
    """Iterate ``items`` with a :class:`Progress` (total: ``len(items)`` when it has one)."""
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with Progress(desc, total, unit, enabled=enabled, stream=stream, every_s=every_s) as p:
        for item in items:
            yield item
            p.update()
