"""The audit trail: who did what, as JSON lines, by default in ``<data_dir>/audit.log``.

Each ``AuditTrail`` writes its own rotated file; records also reach the logger ``uacell.audit`` when
a handler is attached to it (so they can be routed elsewhere with the usual logging configuration).
Events:

``login``            user, client address, ApplicationUri, result (a status code name)
``session_open``     session, client address, ApplicationUri
``session_close``    session, user
``call``             user, object (NodeId path), method, result, Status output when the method has one
``write``            user, node, attribute, result
``program_file``     user, operation (added, changed, removed), path below the programs directory
``user`` / ``cert``  changes made with the ``uacell user`` and ``uacell cert`` commands

Recording costs the caller one append: a writer thread of the trail formats and writes what was
recorded every ``FLUSH_INTERVAL`` seconds (decision 41). ``close`` (a clean stop, SIGTERM included)
writes everything recorded before it; a process killed outright loses at most the last interval.
"""

from __future__ import annotations

import atexit
import collections
import datetime as dt
import json
import logging
import os
import threading
import time
import weakref
from pathlib import Path
from typing import Any

from uacell.config import Config

LOGGER = "uacell.audit"
AUDIT_FILE = "audit.log"
_log = logging.getLogger(LOGGER)
_log.propagate = False  # its own trail; not repeated in the service log
FLUSH_INTERVAL = 0.2  # seconds: the longest a record waits in memory before it is written

Entry = tuple[float, str, dict[str, Any]]  # (time, event, fields) as recorded


def audit_line(created: float, event: str, fields: dict[str, Any]) -> str:
    """One record as the JSON line the trail holds."""
    entry = {
        "time": dt.datetime.fromtimestamp(created, dt.UTC).isoformat(timespec="milliseconds"),
        "event": event,
        **fields,
    }
    return _ENCODER.encode(entry)


def _json_value(value: Any) -> Any:
    """A field's value that JSON has no type for, as docs/operations.md says: a NodeId (or
    QualifiedName) in its standard string form (``ns=1;i=11``, ``ns=6;s=Robot1.Controllers``), a
    status code or enumeration by its name, a tuple as a list, bytes as hex, anything else as text."""
    to_string = getattr(value, "to_string", None)
    if callable(to_string):
        return str(to_string())
    name = getattr(value, "name", None)
    if isinstance(name, str) and hasattr(value, "value"):  # ua.StatusCode, an Enum
        return name
    if isinstance(value, tuple | set | frozenset):
        return list(value)
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex()
    return str(value)


# json.dumps with these makes one per call
_ENCODER = json.JSONEncoder(default=_json_value, ensure_ascii=False)


class _RotatingFile:
    """An append-only text file rotated like logging's RotatingFileHandler (``audit.log.1`` ... ``.N``)."""

    def __init__(self, path: Path, max_bytes: int, backups: int) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.backups = backups
        self._file = path.open("a", encoding="utf-8")
        self._size = self._file.tell()

    def write(self, lines: list[str]) -> None:
        chunk: list[str] = []
        size = 0
        for line in lines:
            n = len(line.encode("utf-8")) + 1
            if self._size + size + n > self.max_bytes and self._size + size > 0:
                self._file.write("".join(chunk))
                self._rotate()
                chunk, size = [], 0
            chunk.append(line + "\n")
            size += n
        self._file.write("".join(chunk))
        self._file.flush()
        self._size += size

    def _rotate(self) -> None:
        self._file.close()
        if self.backups > 0:
            for i in range(self.backups - 1, 0, -1):
                older = self.path.with_name(f"{self.path.name}.{i}")
                if older.exists():
                    os.replace(older, self.path.with_name(f"{self.path.name}.{i + 1}"))
            os.replace(self.path, self.path.with_name(f"{self.path.name}.1"))
        else:
            self.path.unlink(missing_ok=True)
        self._file = self.path.open("a", encoding="utf-8")
        self._size = 0

    def close(self) -> None:
        self._file.close()


class AuditTrail:
    """One server's (or one command's) audit trail; ``record`` never raises and never waits."""

    def __init__(
        self,
        path: Path | None,
        *,
        max_bytes: int = 10 * 1024 * 1024,
        backups: int = 5,
        flush_interval: float = FLUSH_INTERVAL,
    ) -> None:
        self.path = path
        self.flush_interval = flush_interval
        self._file: _RotatingFile | None = None
        self._pending: collections.deque[Entry] = collections.deque()  # append/popleft are atomic
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one writer at a time: the thread, or flush() from outside it
        self._thread: threading.Thread | None = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = _RotatingFile(path, max_bytes, backups)
        _OPEN.add(self)

    @classmethod
    def for_config(cls, config: Config) -> AuditTrail:
        cfg = config.logging
        if not cfg.audit:
            return cls(None)
        path = cfg.audit_file or config.server.data_dir / AUDIT_FILE
        return cls(path, max_bytes=cfg.max_bytes, backups=cfg.backups)

    def record(self, event: str, **fields: Any) -> None:
        """Keep ``event`` with ``fields``; written within ``flush_interval`` seconds."""
        self._pending.append((time.time(), event, fields))
        if self._stop.is_set():  # closed: handed on at once (the file is closed)
            self.flush()
        elif self._thread is None:
            self._start()

    def flush(self) -> None:
        """Write everything recorded so far (the writer thread does this every ``flush_interval``)."""
        with self._lock:
            batch: list[Entry] = []
            while self._pending:
                batch.append(self._pending.popleft())
            if batch:
                self._write(batch)

    def _start(self) -> None:
        with self._lock:
            if self._thread is None and not self._stop.is_set():
                self._thread = threading.Thread(target=self._run, name="uacell-audit", daemon=True)
                self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.flush_interval):
            self.flush()

    def _write(self, batch: list[Entry]) -> None:
        try:
            if self._file is not None:
                self._file.write([audit_line(*entry) for entry in batch])
            if _log.handlers:  # routed elsewhere too
                for created, event, fields in batch:
                    record = _log.makeRecord(
                        LOGGER, logging.INFO, __file__, 0, event, (), None, extra={"audit": fields}
                    )
                    record.created = created
                    _log.handle(record)
        except Exception:  # an audit failure must never turn into the operation's failure
            logging.getLogger(__name__).exception("writing %d audit records failed", len(batch))

    def close(self) -> None:
        """Write what is pending, stop the writer thread and close the file (idempotent)."""
        with self._lock:
            self._stop.set()
            thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()
        self.flush()
        _OPEN.discard(self)
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None


# Trails still open when the interpreter exits (a command that returned early) write what they hold.
_OPEN: weakref.WeakSet[AuditTrail] = weakref.WeakSet()


@atexit.register
def _close_open_trails() -> None:
    for trail in list(_OPEN):
        trail.close()
