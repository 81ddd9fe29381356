"""Keep the log readable under attack: repeated identical warnings and errors are rate-limited.

``RepeatFilter`` lets the first ``burst`` records with the same logger, level and message template
through in each ``window`` seconds and drops the rest; the first record let through after a drop says
how many were dropped. ``install_repeat_filter()`` puts one on every handler of the root logger.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

_Key = tuple[str, int, str]


class RepeatFilter(logging.Filter):
    """Drop identical WARNING-and-above records beyond ``burst`` per ``window`` seconds."""

    def __init__(
        self,
        *,
        burst: int = 5,
        window: float = 60.0,
        level: int = logging.WARNING,
        max_keys: int = 1024,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__()
        self.burst, self.window, self.level, self.max_keys = burst, window, level, max_keys
        self._clock = clock
        self._seen: dict[_Key, tuple[float, int, int]] = {}  # key -> (window start, passed, dropped)

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < self.level:
            return True
        key = (record.name, record.levelno, str(record.msg))
        now = self._clock()
        start, passed, dropped = self._seen.get(key, (now, 0, 0))
        if now - start >= self.window:
            start, passed = now, 0
        if passed >= self.burst:
            self._seen[key] = (start, passed, dropped + 1)
            return False
        if dropped:
            record.msg = f"{record.msg} [{dropped} identical messages suppressed]"
        if len(self._seen) >= self.max_keys and key not in self._seen:
            self._forget(now)
        self._seen[key] = (start, passed + 1, 0)
        return True

    def _forget(self, now: float) -> None:
        for key in [k for k, (start, _, _) in self._seen.items() if now - start >= self.window]:
            del self._seen[key]
        if len(self._seen) >= self.max_keys:  # all recent: forget the oldest half
            for key in sorted(self._seen, key=lambda k: self._seen[k][0])[: self.max_keys // 2]:
                del self._seen[key]


def install_repeat_filter(logger: logging.Logger | None = None) -> RepeatFilter:
    """Add one ``RepeatFilter`` to every handler of ``logger`` (default: the root logger)."""
    repeat = RepeatFilter()
    for handler in (logger or logging.getLogger()).handlers:
        handler.addFilter(repeat)
    return repeat
