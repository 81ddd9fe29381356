"""Logging set-up: text or JSON lines on standard error, an optional rotated log file, per-logger levels.

``configure_console`` runs first (from the command-line options alone, so that even a configuration
error is reported in the chosen format); ``configure`` then applies the ``[logging]`` section.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import logging.handlers
import sys
from typing import Any

from uacell.config import Config

_HANDLER_MARK = "_uacell_handler"
# Loggers whose level the configuration set ([logging] levels): uacell's own defaults leave them alone.
configured_levels: set[str] = set()
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# LogRecord attributes that are not extra fields.
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime", "taskName"}


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

    The audit trail has its own file, opened by whoever records (``uacell.audit.AuditTrail``).
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
