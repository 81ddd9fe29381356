"""The history store: samples queued by the event loop, written in batches by one writer thread.

``record_value`` / ``record_event`` only append to a queue (no I/O on the event loop). The writer
thread takes what is queued at most every ``flush_interval`` seconds and commits it as one
transaction, so a kill -9 loses at most the samples of the last interval. It prunes by age and size
every ``prune_interval`` seconds. Reads run in worker threads on their own connections.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import logging
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

from uacell.history.backends import Backend, Query, Row, Sample

Encode = Callable[[], bytes]  # encodes a sample's data when the writer thread commits it
Queued = tuple[str, int, int, int, int, str, "bytes | Encode"]  # a Row whose data may be still to encode

log = logging.getLogger(__name__)
T = TypeVar("T")

_CP_FORMAT = ">4sqq"  # magic, time, seq
_CP_MAGIC = b"uch1"
_CP_MAC = 8


class ContinuationPointInvalid(ValueError):
    """A continuation point this server did not give for this node (or damaged)."""


@dataclass(frozen=True)
class StoreSettings:
    flush_interval: float = 0.5  # seconds between batch commits (the most a kill -9 loses)
    max_age_days: float = 30.0  # 0: keep forever
    max_mb: float = 1024.0  # 0: no size bound
    prune_interval: float = 60.0


class Cursor:
    """Opaque continuation points: (time, seq) of the last sample returned, signed per session and node.

    A point names the exact sample a page ended on, so the next page starts strictly after it: no
    sample is repeated or skipped, also when many share one timestamp. The MAC (a key drawn per server
    start) makes a damaged or forged point, or one given for another node or to another session,
    Bad_ContinuationPointInvalid (OPC 10000-4 7.9: a point belongs to the session it was given to).
    """

    def __init__(self, key: bytes | None = None) -> None:
        self.key = key or os.urandom(16)

    def _mac(self, node: str, body: bytes, session: str) -> bytes:
        signed = session.encode() + b"\0" + node.encode() + b"\0" + body
        return hmac.new(self.key, signed, hashlib.sha256).digest()[:_CP_MAC]

    def encode(self, node: str, t: int, seq: int, session: str = "") -> bytes:
        body = struct.pack(_CP_FORMAT, _CP_MAGIC, t, seq)
        return body + self._mac(node, body, session)

    def decode(self, node: str, point: bytes, session: str = "") -> tuple[int, int]:
        size = struct.calcsize(_CP_FORMAT)
        if len(point) != size + _CP_MAC:
            raise ContinuationPointInvalid("length")
        body, mac = point[:size], point[size:]
        if not hmac.compare_digest(mac, self._mac(node, body, session)):
            raise ContinuationPointInvalid("signature")
        magic, t, seq = struct.unpack(_CP_FORMAT, body)
        if magic != _CP_MAGIC:
            raise ContinuationPointInvalid("magic")
        return int(t), int(seq)


_FLUSH = object()
_STOP = object()
PENDING_MAX = 200_000  # samples kept in memory while the store does not answer
RETRY = 1.0  # seconds between attempts to write to a store that did not answer


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _encoded(row: Queued) -> Row | None:
    node, t, seq, kind, status, etype, data = row
    if isinstance(data, bytes):
        return (node, t, seq, kind, status, etype, data)
    try:
        return (node, t, seq, kind, status, etype, data())
    except Exception:
        log.exception("history: could not encode a sample of %s", node)
        return None


class HistoryStore:
    """Batched writes to a backend from one thread; reads in worker threads."""

    def __init__(
        self,
        backend: Backend,
        settings: StoreSettings = StoreSettings(),
        now: Callable[[], float] = time.time,
    ) -> None:
        self.backend = backend
        self.settings = settings
        self.now = now
        self.cursor = Cursor()
        try:
            self._seq = backend.max_seq()
        except Exception as exc:  # the database is not there yet: numbers that follow any it holds
            self._seq = int(now() * 1e6)
            log.warning(
                "history: the store does not answer (%s); samples are kept in memory until it does", first_line(exc)
            )
            self.down = True
        else:
            self.down = False  # the last write failed: samples wait in memory (``pending``)
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._wake = threading.Event()  # a flush or the stop asked for: commit now
        self._thread: threading.Thread | None = None
        self.written = 0  # samples committed since start
        self.batches = 0
        self.errors = 0
        self.pending: list[Row] = []  # encoded samples a failed write left, written first next time
        self.dropped = 0  # samples given up because more than PENDING_MAX waited

    # -- writing (event loop side: never blocks) -------------------------------------------------

    def record(self, node: str, t: int, kind: int, status: int, etype: str, data: bytes | Encode) -> None:
        """Queue one sample; ``data`` may be a function that encodes it, called in the writer thread
        (the event loop only queues: no encoding, no wake-up of the writer per sample)."""
        self._seq += 1
        self._queue.put((node, t, self._seq, kind, status, etype, data))  # a Row: no object per sample

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="uacell-history-writer", daemon=True)
            self._thread.start()

    async def flush(self) -> None:
        """Wait until everything recorded so far is committed."""
        if self._thread is None:
            self._write(self._drain_now())
            return
        done = threading.Event()
        self._queue.put((_FLUSH, done))
        self._wake.set()
        await asyncio.to_thread(done.wait)

    async def close(self) -> None:
        if self._thread is not None:
            self._queue.put(_STOP)
            self._wake.set()
            await asyncio.to_thread(self._thread.join)
            self._thread = None
        else:
            self._write(self._drain_now())
        if self.pending:
            log.warning("history: %d samples not written at the stop: the store does not answer", len(self.pending))
        self.backend.close()

    def _drain_now(self) -> list[Queued]:
        out: list[Queued] = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return out
            if isinstance(item, tuple) and len(item) == 7:
                out.append(item)

    def _write(self, queued: Sequence[Queued]) -> None:
        """Commit what is pending and ``queued``; when the store does not answer (a database gone, a
        disk full), keep it all in memory, at most ``PENDING_MAX`` samples (the oldest are given up
        beyond), and try again at the next batch or after ``RETRY`` seconds: one warning when it
        stops answering, one line when it answers again (docs/history.md)."""
        batch = self.pending + [row for row in map(_encoded, queued) if row is not None]
        if not batch:
            return
        try:
            self.backend.write(batch)
        except Exception as exc:
            self.errors += 1
            if len(batch) > PENDING_MAX:
                self.dropped += len(batch) - PENDING_MAX
                batch = batch[-PENDING_MAX:]
            self.pending = batch
            if not self.down:
                self.down = True
                log.warning(
                    "history: the store does not answer (%s); %d samples kept in memory until it does",
                    first_line(exc),
                    len(batch),
                )
            return
        self.pending = []
        self.written += len(batch)
        self.batches += 1
        if self.down:
            self.down = False
            lost = f", {self.dropped} given up" if self.dropped else ""
            log.warning("history: the store answers again; %d samples written%s", len(batch), lost)

    def prune(self) -> int:
        s = self.settings
        before = int((self.now() - s.max_age_days * 86400) * 1e6) if s.max_age_days > 0 else -(2**62)
        return self.backend.prune(before, int(s.max_mb * 1024 * 1024))

    def _run(self) -> None:
        # Wakes once per batch: at the first sample after a quiet spell, then commits what came in
        # the next ``flush_interval`` seconds (or at once for a flush or the stop).
        interval = self.settings.flush_interval
        pruned = -float("inf")  # when it last pruned (the interval is read each time: settings may change)
        stopping = False
        while not stopping:
            try:  # while samples wait for a store that did not answer, try again every RETRY seconds
                first = self._queue.get(timeout=RETRY if self.pending else None)
            except queue.Empty:
                self._write([])
                continue
            self._wake.wait(interval)
            self._wake.clear()
            batch: list[Queued] = []
            waiters: list[threading.Event] = []
            for item in [first, *self._drain_items()]:
                if item is _STOP:
                    stopping = True
                elif isinstance(item, tuple) and len(item) == 2 and item[0] is _FLUSH:
                    waiters.append(item[1])
                elif isinstance(item, tuple):
                    batch.append(item)
            self._write(batch)
            for w in waiters:
                w.set()
            if time.monotonic() - pruned >= self.settings.prune_interval and not self.down:
                pruned = time.monotonic()
                try:
                    self.prune()
                except Exception as exc:  # the store went away meanwhile: the next prune tries again
                    log.warning("history: pruning failed (%s)", first_line(exc))

    def _drain_items(self) -> list[object]:
        out: list[object] = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    # -- reading (worker threads) ----------------------------------------------------------------

    async def read(self, q: Query) -> list[Sample]:
        return await asyncio.to_thread(self.backend.read, q)

    async def read_mapped(self, q: Query, convert: Callable[[list[Sample]], list[T]]) -> list[T]:
        """``convert`` (a pure function) of what ``q`` finds, run in the reading thread too."""
        return await asyncio.to_thread(lambda: convert(self.backend.read(q)))
