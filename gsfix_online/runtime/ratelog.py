"""Rate-limited warnings: a flood of bad input costs one log line per reason per period."""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable


class RateLimitedLog:
    """At most one warning per ``key`` per ``period_s``; suppressed ones are counted in the next."""

    def __init__(
        self,
        logger: logging.Logger,
        period_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._logger = logger
        self._period_s = period_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def warning(self, key: str, text: str) -> bool:
        """Log ``text`` (one line) unless ``key`` was logged within the period; True if logged."""
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self._period_s:
            self._suppressed[key] += 1
            return False
        n = self._suppressed.pop(key, 0)
        more = (
            f" (+{n} more like this in the last {now - last:.0f} s)"
            if n and last is not None
            else ""
        )
        self._logger.warning("%s%s", text.replace("\n", " "), more)
        self._last[key] = now
        return True
