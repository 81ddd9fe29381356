"""The PostgreSQL backend, for plants that keep history centrally ([history] backend = "postgresql").

The same one table and index as SQLite (``uacell.history.backends``), through psycopg 3; one
connection per thread (the writer thread, each reader thread). ``prune``'s size bound is the table's
total relation size.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

from uacell.core.extras import MissingExtra
from uacell.history.backends import _COLUMNS, Query, Row, Sample, _where


class PostgresBackend:
    """The table is created when missing, at the first connection that succeeds: the database may be
    unreachable when uacell starts (the store then keeps samples in memory and tries again). A
    connection that failed is dropped and made anew at the next use."""

    def __init__(self, dsn: str, table: str = "uacell_samples") -> None:
        try:  # only needed with this backend: the 'postgres' extra
            import psycopg
        except ImportError as exc:
            raise MissingExtra.of("[history] backend = 'postgresql'", exc) from exc

        if not table.isidentifier():
            raise ValueError(f"table name {table!r}")
        self._psycopg = psycopg
        self.dsn = dsn
        self.table = table
        self._local = threading.local()
        self._all: list[Any] = []
        self._lock = threading.Lock()
        self._table_ready = False
        try:
            self._con()
        except psycopg.OperationalError:
            pass  # unreachable now: the first use that connects creates the table

    def _create_table(self, con: Any) -> None:
        table = self.table
        with con.transaction():
            con.execute(
                f"CREATE TABLE IF NOT EXISTS {table} (node TEXT NOT NULL, time BIGINT NOT NULL,"
                " seq BIGINT NOT NULL, kind SMALLINT NOT NULL, status BIGINT NOT NULL,"
                " etype TEXT NOT NULL, data BYTEA NOT NULL)"
            )
            con.execute(f"CREATE INDEX IF NOT EXISTS {table}_node_time ON {table} (node, kind, time, seq)")
            con.execute(f"CREATE INDEX IF NOT EXISTS {table}_time ON {table} (time)")
        self._table_ready = True

    def _con(self) -> Any:
        con = getattr(self._local, "con", None)
        if con is None or con.closed or con.broken:
            con = self._psycopg.connect(self.dsn, autocommit=True, connect_timeout=5)
            self._local.con = con
            with self._lock:
                self._all.append(con)
            if not self._table_ready:
                self._create_table(con)
        return con

    def _use(self, work: Any, again: bool = False) -> Any:
        """``work(connection)``; a connection that failed is closed, so that the next use reconnects.
        ``again`` (work that only reads): done once more on a new connection first, since a thread's
        connection made before the database went away fails its first use after the database is back."""
        con = self._con()
        try:
            return work(con)
        except self._psycopg.OperationalError:
            try:
                con.close()
            except Exception:
                pass
            if not again:
                raise
        return work(self._con())

    def write(self, rows: Sequence[Row]) -> None:
        sql = f"INSERT INTO {self.table} ({_COLUMNS}) VALUES (%s, %s, %s, %s, %s, %s, %s)"

        def insert(con: Any) -> None:
            with con.transaction(), con.cursor() as cur:
                cur.executemany(sql, rows)

        self._use(insert)

    def read(self, q: Query) -> list[Sample]:
        where, args = _where(q, "%s")
        sql = f"SELECT {_COLUMNS} FROM {self.table} WHERE {where}"
        rows = self._use(lambda con: con.execute(sql, args).fetchall(), again=True)
        return [Sample(r[0], int(r[1]), int(r[2]), int(r[3]), int(r[4]), r[5], bytes(r[6])) for r in rows]

    def max_seq(self) -> int:
        row = self._use(lambda con: con.execute(f"SELECT MAX(seq) FROM {self.table}").fetchone(), again=True)
        return int(row[0]) if row and row[0] is not None else 0

    def size(self) -> int:
        """The bytes the live rows take (a plain DELETE does not shrink the relation itself)."""
        row = self._con().execute(f"SELECT COALESCE(SUM(pg_column_size(t.*)), 0) FROM {self.table} t").fetchone()
        return int(row[0]) if row else 0

    def prune(self, before: int, max_bytes: int) -> int:
        con = self._con()
        deleted = con.execute(f"DELETE FROM {self.table} WHERE time < %s", (before,)).rowcount
        while max_bytes > 0 and self.size() > max_bytes:
            (count,) = con.execute(f"SELECT COUNT(*) FROM {self.table}").fetchone()
            if count == 0:
                break
            chunk = max(1, count // 10)
            deleted += con.execute(
                f"DELETE FROM {self.table} WHERE ctid IN (SELECT ctid FROM {self.table} ORDER BY time, seq LIMIT %s)",
                (chunk,),
            ).rowcount
        return int(deleted)

    def close(self) -> None:
        with self._lock:
            for con in self._all:
                try:
                    con.close()
                except Exception:
                    pass
            self._all.clear()
        self._local = threading.local()
