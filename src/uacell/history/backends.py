"""Where samples are kept: one table keyed by node, ordered by (time, seq).

A backend is used from one writer thread (``write``, ``prune``) and from reader threads (``read``),
each with its own connection. Times are integer microseconds since the Unix epoch (UTC); ``seq`` is a
number the store gives every sample, increasing, so that samples sharing a time keep an order.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

VALUE = 0  # a sample's kind: a variable's value
EVENT = 1  # an event fired through a notifier


@dataclass(frozen=True)
class Sample:
    node: str  # the variable's or notifier's NodeId, as a string
    time: int  # microseconds since the epoch
    seq: int
    kind: int  # VALUE or EVENT
    status: int  # a value's StatusCode; 0 for events
    etype: str  # an event's EventType NodeId string; "" for values
    data: bytes  # the encoded Variant (values) or fields (events)


# A sample as queued and written: (node, time, seq, kind, status, etype, data).
Row = tuple[str, int, int, int, int, str, bytes]


@dataclass(frozen=True)
class Query:
    node: str
    kind: int
    lo: int | None  # time >= lo (None: no bound)
    hi: int | None  # time < hi (forward) / time > hi (reverse): see Backend.read
    reverse: bool
    limit: int
    after: tuple[int, int] | None = None  # continue after this (time, seq), in the query's direction
    lo_inclusive: bool = True


class Backend(Protocol):
    def write(self, rows: Sequence[Row]) -> None: ...
    def read(self, q: Query) -> list[Sample]: ...
    def max_seq(self) -> int: ...
    def prune(self, before: int, max_bytes: int) -> int: ...
    def close(self) -> None: ...


_COLUMNS = "node, time, seq, kind, status, etype, data"


def _where(q: Query, param: str) -> tuple[str, list[object]]:
    """The WHERE clause and parameters of ``q`` (``param`` is the driver's placeholder)."""
    p = param
    sql = [f"node = {p}", f"kind = {p}"]
    args: list[object] = [q.node, q.kind]
    if q.lo is not None:
        sql.append(f"time >= {p}" if q.lo_inclusive else f"time > {p}")
        args.append(q.lo)
    if q.hi is not None:
        sql.append(f"time < {p}")
        args.append(q.hi)
    if q.after is not None:
        t, s = q.after
        op = "<" if q.reverse else ">"
        sql.append(f"(time {op} {p} OR (time = {p} AND seq {op} {p}))")
        args += [t, t, s]
    order = "DESC" if q.reverse else "ASC"
    return " AND ".join(sql) + f" ORDER BY time {order}, seq {order} LIMIT {int(q.limit)}", args


class SqliteBackend:
    """The embedded store: ``history.sqlite`` in the data directory, WAL, one table."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        con = self._con()
        con.execute("PRAGMA journal_mode=WAL")
        con.execute(
            "CREATE TABLE IF NOT EXISTS samples (node TEXT NOT NULL, time INTEGER NOT NULL,"
            " seq INTEGER NOT NULL, kind INTEGER NOT NULL, status INTEGER NOT NULL,"
            " etype TEXT NOT NULL, data BLOB NOT NULL)"
        )
        con.execute("CREATE INDEX IF NOT EXISTS samples_node_time ON samples (node, kind, time, seq)")
        con.execute("CREATE INDEX IF NOT EXISTS samples_time ON samples (time)")
        con.commit()
        self._all: list[sqlite3.Connection] = []

    def _con(self) -> sqlite3.Connection:
        con: sqlite3.Connection | None = getattr(self._local, "con", None)
        if con is None:
            con = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            # The writer commits once per batch; NORMAL keeps WAL commits durable against a crash of
            # the process (kill -9); only a power loss may lose the last commits (docs/history.md).
            con.execute("PRAGMA synchronous=NORMAL")
            con.execute("PRAGMA busy_timeout=5000")
            self._local.con = con
            getattr(self, "_all", []).append(con)
        return con

    def write(self, rows: Sequence[Row]) -> None:
        con = self._con()
        con.execute("BEGIN")
        try:
            con.executemany(f"INSERT INTO samples ({_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
        except BaseException:
            con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")

    def read(self, q: Query) -> list[Sample]:
        where, args = _where(q, "?")
        rows = self._con().execute(f"SELECT {_COLUMNS} FROM samples WHERE {where}", args).fetchall()
        return [Sample(r[0], r[1], r[2], r[3], r[4], r[5], bytes(r[6])) for r in rows]

    def _one(self, sql: str, args: tuple[object, ...] = ()) -> object:
        """The first column of the one row ``sql`` gives (read to its end: no statement stays open and
        holds an old WAL snapshot)."""
        rows = self._con().execute(sql, args).fetchall()
        return rows[0][0] if rows else None

    def max_seq(self) -> int:
        top = self._one("SELECT MAX(seq) FROM samples")
        return int(top) if isinstance(top, int) else 0

    def size(self) -> int:
        pages, free, size = (self._one(f"PRAGMA {p}") for p in ("page_count", "freelist_count", "page_size"))
        assert isinstance(pages, int) and isinstance(free, int) and isinstance(size, int)
        return (pages - free) * size

    def prune(self, before: int, max_bytes: int) -> int:
        """Delete samples older than ``before``, then the oldest until the data fit ``max_bytes``."""
        con = self._con()
        deleted = con.execute("DELETE FROM samples WHERE time < ?", (before,)).rowcount
        while max_bytes > 0 and self.size() > max_bytes:
            count = self._one("SELECT COUNT(*) FROM samples")
            if not isinstance(count, int) or count == 0:
                break
            chunk = max(1, count // 10)
            deleted += con.execute(
                "DELETE FROM samples WHERE rowid IN (SELECT rowid FROM samples ORDER BY time, seq LIMIT ?)",
                (chunk,),
            ).rowcount
        return int(deleted)

    def close(self) -> None:
        for con in self._all:
            try:
                con.close()
            except sqlite3.Error:
                pass
        self._all.clear()
        self._local = threading.local()
