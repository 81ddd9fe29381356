"""Logging set-up: text or JSON lines on standard error, an optional rotated log file, per-logger levels,
and a rate limit on repeated identical warnings and errors (the log stays readable under attack).

``configure_console`` runs first (from the command-line options alone, so that even a configuration
error is reported in the chosen format); ``configure`` then applies the ``[logging]`` section. Every
handler they install carries the one ``RepeatFilter``: in each ``window`` seconds it lets the first
``burst`` identical records (logger, level, text) and the first ``similar`` ones of one message template
through and drops the rest; the first record let through after a drop says how many were dropped.

``quiet_expected`` installs an ``ExpectedFaults`` filter on a library's loggers: a fault uacell expects
and handles itself (a PLC killed, a client gone) is one DEBUG line there instead of an ERROR with a
traceback; uacell says it once, in its own words, where it handles it.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import logging.handlers
import sys
import time
from collections.abc import Callable, Iterable
from typing import Any

from uacell.config import Config

_HANDLER_MARK = "_uacell_handler"
# Loggers whose level the configuration set ([logging] levels): uacell's own defaults leave them alone.
configured_levels: set[str] = set()
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# LogRecord attributes that are not extra fields.
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime", "taskName"}


_Key = tuple[str, int, str]


class RepeatFilter(logging.Filter):
    """Drop WARNING-and-above records beyond ``burst`` identical ones (same logger, level and text) and
    beyond ``similar`` ones of one message template (the same text with other arguments) per
    ``window`` seconds. So a flood stays short however its arguments vary, while different sources of
    one kind of fault (five PLCs lost at once) are each said. The first record let through after a
    drop says how many were dropped."""

    def __init__(
        self,
        *,
        burst: int = 5,
        similar: int = 20,
        window: float = 60.0,
        level: int = logging.WARNING,
        max_keys: int = 1024,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__()
        self.burst, self.similar, self.window, self.level = burst, similar, window, level
        self.max_keys = max_keys
        self._clock = clock
        # key -> (window start, passed, dropped); identical texts and templates each by their own key
        self._seen: dict[_Key, tuple[float, int, int]] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < self.level:
            return True
        now = self._clock()
        try:
            message = record.getMessage()
        except Exception:  # arguments that do not fit: the handler reports it when it formats
            message = str(record.msg)
        text = (record.name, record.levelno, "=" + message)
        template = (record.name, record.levelno, "T" + str(record.msg))
        counts = [(key, most, *self._window(key, now)) for key, most in ((text, self.burst), (template, self.similar))]
        for key, most, start, passed, dropped in counts:
            if passed >= most:  # dropped: counted once, under the first limit it met
                self._seen[key] = (start, passed, dropped + 1)
                return False
        notes = []
        for (key, _, start, passed, dropped), kind in zip(counts, ("identical", "similar"), strict=True):
            if dropped:
                notes.append(f"{dropped} {kind} messages suppressed")
            self._seen[key] = (start, passed + 1, 0)
        if notes:
            record.msg, record.args = f"{message} [{'; '.join(notes)}]", None
        return True

    def _window(self, key: _Key, now: float) -> tuple[float, int, int]:
        """``key``'s (window start, passed, dropped), a new window begun if the last one is over."""
        if len(self._seen) >= self.max_keys and key not in self._seen:
            self._forget(now)
        start, passed, dropped = self._seen.get(key, (now, 0, 0))
        return (now, 0, dropped) if now - start >= self.window else (start, passed, dropped)

    def reset(self) -> None:
        """Forget every count (a test starts with none of an earlier test's)."""
        self._seen.clear()

    def _forget(self, now: float) -> None:
        for key in [k for k, (start, _, _) in self._seen.items() if now - start >= self.window]:
            del self._seen[key]
        if len(self._seen) >= self.max_keys:  # all recent: forget the oldest half
            for key in sorted(self._seen, key=lambda k: self._seen[k][0])[: self.max_keys // 2]:
                del self._seen[key]


# One filter for every handler uacell installs, so a flood counts once whatever the destination.
REPEAT = RepeatFilter()


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time (UTC, ISO 8601), level, logger, message, extras, exception."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": dt.datetime.fromtimestamp(record.created, dt.UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in vars(record).items():
            if key not in _STANDARD and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str, ensure_ascii=False)


def formatter(fmt: str) -> logging.Formatter:
    return JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT)


def _replace_handlers(root: logging.Logger, handlers: list[logging.Handler]) -> None:
    for old in [h for h in root.handlers if getattr(h, _HANDLER_MARK, False)]:
        root.removeHandler(old)
        old.close()
    for h in handlers:
        setattr(h, _HANDLER_MARK, True)
        h.addFilter(REPEAT)  # a flood of identical errors must not fill the disk
        root.addHandler(h)


def configure_console(level: str = "INFO", fmt: str = "text") -> None:
    """Log to standard error at ``level`` in ``fmt`` ("text" or "json")."""
    root = logging.getLogger()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(formatter(fmt))
    _replace_handlers(root, [handler])
    root.setLevel(level)


def configure(config: Config) -> None:
    """Apply ``[logging]``: level, format, file with rotation, per-logger levels.

    The audit trail has its own file, opened by whoever records (``uacell.security.audit.AuditTrail``).
    """
    cfg = config.logging
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if cfg.file is not None:
        cfg.file.parent.mkdir(parents=True, exist_ok=True)
        handlers.append(
            logging.handlers.RotatingFileHandler(
                cfg.file, maxBytes=cfg.max_bytes, backupCount=cfg.backups, encoding="utf-8"
            )
        )
    for h in handlers:
        h.setFormatter(formatter(cfg.format))
    root = logging.getLogger()
    _replace_handlers(root, handlers)
    root.setLevel(cfg.level)
    for name, level in cfg.levels.items():
        logging.getLogger(name).setLevel(level)
        configured_levels.add(name)


class ExpectedFaults(logging.Filter):
    """Drops a library's WARNING-or-above record of a fault uacell expects and handles itself
    (``expected(record)`` says which), and says it again on the same logger as one DEBUG line without
    the traceback; every other record passes unchanged, so a genuine bug keeps its ERROR and traceback.

    ``kind`` names the filter: ``quiet_expected`` installs one filter of a kind on a logger."""

    def __init__(self, kind: str, expected: Callable[[logging.LogRecord], bool]) -> None:
        super().__init__(kind)
        self.kind = kind
        self.expected = expected

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING or not self.expected(record):
            return True
        logger = logging.getLogger(record.name)
        if logger.isEnabledFor(logging.DEBUG):
            exc = record.exc_info[1] if record.exc_info else None
            cause = f" ({type(exc).__name__}: {exc})" if exc is not None else ""
            logger.debug("%s%s [an expected fault: uacell handles it]", record.getMessage(), cause)
        return False


def quiet_expected(kind: str, loggers: Iterable[str], expected: Callable[[logging.LogRecord], bool]) -> None:
    """Install ``ExpectedFaults(kind, expected)`` on each of ``loggers`` (by exact name: a logger's
    filters do not apply to its children), once however often it is called."""
    for name in loggers:
        logger = logging.getLogger(name)
        if not any(isinstance(f, ExpectedFaults) and f.kind == kind for f in logger.filters):
            logger.addFilter(ExpectedFaults(kind, expected))


def exception_of(record: logging.LogRecord) -> BaseException | None:
    """The exception a record carries (``log.exception``), if any."""
    return record.exc_info[1] if record.exc_info else None


class RefusalLog:
    """Logs a refusal at INFO (a client's doing, not the server's fault) at most once per client address,
    reason and ``interval`` seconds, so a flood of attempts cannot flood the log; the next report says
    how many were left out."""

    MAX_KEYS = 4096

    def __init__(
        self,
        interval: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        self.log = logger or logging.getLogger("uacell.security.policy")
        self.interval = interval
        self._clock = clock
        self._last: dict[tuple[str, str], float] = {}
        self._left_out: dict[tuple[str, str], int] = {}

    def report(self, address: str, reason: str, message: str) -> bool:
        """Log ``message`` unless this address and reason were logged less than ``interval`` ago."""
        now = self._clock()
        key = (address, reason)
        last = self._last.get(key)
        if last is not None and now - last < self.interval:
            self._left_out[key] = self._left_out.get(key, 0) + 1
            return False
        if len(self._last) >= self.MAX_KEYS:
            self._forget(now)
        left_out = self._left_out.pop(key, 0)
        self._last[key] = now
        more = f" ({left_out} more such refusals from {address} not logged)" if left_out else ""
        self.log.info("%s%s", message, more)
        return True

    def _forget(self, now: float) -> None:
        for key in [k for k, t in self._last.items() if now - t >= self.interval]:
            del self._last[key]
            self._left_out.pop(key, None)
