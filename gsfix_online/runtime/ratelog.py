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


def warn_repeated(
    logger: logging.Logger, node: str, count: int, stamp_ns: int, last_ns: int, stat: str
) -> None:
    """The once-per-run WARNING of a map node that dropped a frame as repeated (a stamp not newer
    than the last it used): at the first drop only, the ``count`` stays in ``stat``. A replay
    restarted sends its frames again, but so does an input out of time order, whose frames
    would all be lost silently (check it with ``gsfix-online info``)."""
    if count != 1:
        return
    logger.warning(
        "%s: frame at %d ns is not newer than the last used (%d ns): dropped as repeated; "
        "every such frame is dropped and counted in %s (1 so far): an input out of time order "
        "loses frames this way (see gsfix-online info)",
        node, stamp_ns, last_ns, stat,
    )  # fmt: skip
