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

from uacell.history.backends import Backend, Query, Row, Sample

log = logging.getLogger(__name__)

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
    """Opaque continuation points: (time, seq) of the last sample returned, signed per node.

    A point names the exact sample a page ended on, so the next page starts strictly after it: no
    sample is repeated or skipped, also when many share one timestamp. The MAC (a key drawn per server
    start) makes a damaged or forged point, or one given for another node, Bad_ContinuationPointInvalid.
    """

    def __init__(self, key: bytes | None = None) -> None:
        self.key = key or os.urandom(16)

    def _mac(self, node: str, body: bytes) -> bytes:
        return hmac.new(self.key, node.encode() + b"\0" + body, hashlib.sha256).digest()[:_CP_MAC]

    def encode(self, node: str, t: int, seq: int) -> bytes:
        body = struct.pack(_CP_FORMAT, _CP_MAGIC, t, seq)
        return body + self._mac(node, body)

    def decode(self, node: str, point: bytes) -> tuple[int, int]:
        size = struct.calcsize(_CP_FORMAT)
        if len(point) != size + _CP_MAC:
            raise ContinuationPointInvalid("length")
        body, mac = point[:size], point[size:]
        if not hmac.compare_digest(mac, self._mac(node, body)):
            raise ContinuationPointInvalid("signature")
        magic, t, seq = struct.unpack(_CP_FORMAT, body)
        if magic != _CP_MAGIC:
            raise ContinuationPointInvalid("magic")
        return int(t), int(seq)


_FLUSH = object()
_STOP = object()


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
        self._seq = backend.max_seq()
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self.written = 0  # samples committed since start
        self.batches = 0
        self.errors = 0

    # -- writing (event loop side: never blocks) -------------------------------------------------

    def record(self, node: str, t: int, kind: int, status: int, etype: str, data: bytes) -> None:
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
        await asyncio.to_thread(done.wait)

    async def close(self) -> None:
        if self._thread is not None:
            self._queue.put(_STOP)
            await asyncio.to_thread(self._thread.join)
            self._thread = None
        else:
            self._write(self._drain_now())
        self.backend.close()

    def _drain_now(self) -> list[Row]:
        out: list[Row] = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return out
            if isinstance(item, tuple) and len(item) == 7:
                out.append(item)

    def _write(self, batch: Sequence[Row]) -> None:
        if not batch:
            return
        try:
            self.backend.write(batch)
            self.written += len(batch)
            self.batches += 1
        except Exception:
            self.errors += 1
            log.exception("history: could not write %d samples", len(batch))

    def prune(self) -> int:
        s = self.settings
        before = int((self.now() - s.max_age_days * 86400) * 1e6) if s.max_age_days > 0 else -(2**62)
        return self.backend.prune(before, int(s.max_mb * 1024 * 1024))

    def _run(self) -> None:
        interval = self.settings.flush_interval
        next_prune = time.monotonic()
        stopping = False
        while not stopping:
            batch: list[Row] = []
            waiters: list[threading.Event] = []
            item = self._queue.get()
            deadline = time.monotonic() + interval
            while True:
                if item is _STOP:
                    stopping = True
                elif isinstance(item, tuple) and len(item) == 2 and item[0] is _FLUSH:
                    waiters.append(item[1])
                    deadline = 0.0  # commit what is queued now
                elif isinstance(item, tuple):
                    batch.append(item)
                left = deadline - time.monotonic()
                if stopping or left <= 0:
                    batch += self._drain_now() if stopping else []
                    break
                try:
                    item = self._queue.get(timeout=left)
                except queue.Empty:
                    break
            self._write(batch)
            for w in waiters:
                w.set()
            if time.monotonic() >= next_prune:
                next_prune = time.monotonic() + self.settings.prune_interval
                try:
                    self.prune()
                except Exception:
                    log.exception("history: pruning failed")

    # -- reading (worker threads) ----------------------------------------------------------------

    async def read(self, q: Query) -> list[Sample]:
        return await asyncio.to_thread(self.backend.read, q)
