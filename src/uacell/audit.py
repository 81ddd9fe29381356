"""The audit trail: who did what, as JSON lines, by default in ``<data_dir>/audit.log``.

Every record goes through the logger ``uacell.audit`` (so it can also be routed elsewhere with the
usual logging configuration) and, for each ``AuditTrail``, into its own rotated file. Events:

``login``            user, client address, ApplicationUri, result (a status code name)
``session_open``     session, client address, ApplicationUri
``session_close``    session, user
``call``             user, object (NodeId path), method, result, Status output when the method has one
``write``            user, node, attribute, result
``program_file``     user, operation (added, changed, removed), path below the programs directory
``user`` / ``cert``  changes made with the ``uacell user`` and ``uacell cert`` commands
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import logging.handlers
from pathlib import Path
from typing import Any

from uacell.config import Config

LOGGER = "uacell.audit"
AUDIT_FILE = "audit.log"
_log = logging.getLogger(LOGGER)
_log.propagate = False  # its own trail; not repeated in the service log


class _AuditFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        # The rotating handler formats each record twice (size check, then write): build the line once.
        line: str | None = getattr(record, "audit_line", None)
        if line is None:
            entry = {
                "time": dt.datetime.fromtimestamp(record.created, dt.UTC).isoformat(timespec="milliseconds"),
                "event": record.getMessage(),
                **getattr(record, "audit", {}),
            }
            line = json.dumps(entry, default=str, ensure_ascii=False)
            record.audit_line = line
        return line


class AuditTrail:
    """One server's (or one command's) audit trail; ``record`` never raises."""

    def __init__(self, path: Path | None, *, max_bytes: int = 10 * 1024 * 1024, backups: int = 5) -> None:
        self.path = path
        self._handler: logging.Handler | None = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            handler = logging.handlers.RotatingFileHandler(
                path, maxBytes=max_bytes, backupCount=backups, encoding="utf-8"
            )
            handler.setFormatter(_AuditFormatter())
            handler.addFilter(lambda record: getattr(record, "audit_trail", None) is self)
            _log.addHandler(handler)
            if _log.level == logging.NOTSET:
                _log.setLevel(logging.INFO)
            self._handler = handler

    @classmethod
    def for_config(cls, config: Config) -> AuditTrail:
        cfg = config.logging
        if not cfg.audit:
            return cls(None)
        path = cfg.audit_file or config.server.data_dir / AUDIT_FILE
        return cls(path, max_bytes=cfg.max_bytes, backups=cfg.backups)

    def record(self, event: str, **fields: Any) -> None:
        try:
            _log.info(event, extra={"audit": fields, "audit_trail": self})
        except Exception:  # an audit failure must never turn into the operation's failure
            logging.getLogger(__name__).exception("audit record %s failed", event)

    def close(self) -> None:
        if self._handler is not None:
            _log.removeHandler(self._handler)
            self._handler.close()
            self._handler = None
