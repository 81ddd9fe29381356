"""Durable PackML Admin data: one JSON file per unit, replaced atomically (decision 28).

A save writes a temporary file next to the target, fsyncs it, renames it over the target with
``os.replace`` and fsyncs the directory, so at every instant the target is either the previous
complete file or the new complete file: a crash mid-write loses nothing already stored.

In a server the saves run on one ``AdminWriter`` thread shared by every unit, off the event loop.
A store's data that changes again while it waits is written once, with the newest data, and whoever
submitted it is told once it is durable: the model publishes stored values only then.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import os
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
BATCH = 10  # stores written per batch (one directory fsync each): bounds how long a waiting call waits
# Told once the data it was submitted with is durable (None) or could not be stored (the error).
Done = Callable[[OSError | None], None]


class AdminStore:
    """Load and save one unit's Admin data as JSON at ``path``; saves go through ``writer`` if given."""

    def __init__(self, path: str | os.PathLike[str], writer: AdminWriter | None = None) -> None:
        self.path = Path(path)
        self.writer = writer

    def load(self) -> dict[str, Any] | None:
        """The stored data, or None if the file is absent (a first start: logged at INFO) or damaged
        (unreadable, corrupt, an unknown format: a WARNING). Temporaries a crash left beside the file
        (``<name>.json.<random>.tmp``, from a save that never reached its rename) are removed first."""
        self._clean_temporaries()
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            log.info("no PackML admin data at %s yet (a first start); starting from defaults", self.path)
            return None
        except OSError as exc:
            log.warning("cannot read PackML admin data %s (%s); starting from defaults", self.path, exc)
            return None
        try:
            data = json.loads(raw)
        except ValueError as exc:  # includes undecodable bytes
            log.warning("PackML admin data %s is corrupt (%s); starting from defaults", self.path, exc)
            return None
        if not isinstance(data, dict) or data.get("version") != FORMAT_VERSION:
            log.warning("PackML admin data %s has an unknown format; starting from defaults", self.path)
            return None
        return data

    def _clean_temporaries(self) -> None:
        prefix = self.path.name + "."
        try:  # names, not Paths: every unit of a cell lists the same directory
            names = os.listdir(self.path.parent)
        except OSError:
            return  # no directory yet (a first start), or unreadable: the load says so
        found = [self.path.parent / n for n in names if n.startswith(prefix) and n.endswith(".tmp")]
        removed = 0
        for leftover in found:
            try:
                leftover.unlink()
                removed += 1
            except OSError as exc:
                log.warning("cannot remove the leftover temporary %s (%s)", leftover, exc)
        if removed:
            log.warning(
                "removed %d leftover temporary file(s) of %s (a save interrupted by a crash)", removed, self.path
            )

    def save(self, data: dict[str, Any]) -> None:
        """Store ``data`` atomically and durably, now, in the calling thread."""
        self._replace(data)
        _fsync_dir(self.path.parent)

    def submit(self, data: dict[str, Any], done: Done) -> None:
        """Store ``data`` and then call ``done``: on the writer's thread if the store has a writer (``done``
        is called on the event loop), else now. ``data`` must not change afterwards."""
        if self.writer is not None:
            self.writer.submit(self, data, done)
            return
        try:
            self.save(data)
        except OSError as exc:
            done(exc)
        else:
            done(None)

    async def stored(self) -> None:
        """Return once nothing submitted to this store waits to be written."""
        if self.writer is not None:
            await self.writer.flush(self)

    def _replace(self, data: dict[str, Any]) -> None:
        # Atomic but not yet durable: the caller fsyncs the directory (once for several stores).
        directory = self.path.parent
        payload = json.dumps({**data, "version": FORMAT_VERSION}, sort_keys=True)  # no indent: the C encoder
        prefix = self.path.name + "."
        try:
            fd, tmp_name = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=directory)
        except FileNotFoundError:  # the first save, or the directory was removed: made (again) only then
            directory.mkdir(parents=True, exist_ok=True)
            fd, tmp_name = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=directory)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(payload)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp_name, self.path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp_name)
            raise


class AdminWriter:
    """One thread that stores the Admin data of every unit of a server, off the event loop.

    ``submit`` queues a store's data; data queued for a store that has not been written yet is
    replaced by newer data (written once, only the newest ``done`` is called). The thread takes up to
    ``BATCH`` queued stores at a time, writes each file atomically, fsyncs each directory once for the
    batch, and then calls the batch's ``done`` callbacks on the event loop, in submission order. A
    store somebody waits for (``flush(store)``) moves to the head of the queue.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._cond = threading.Condition()
        self._queue: dict[AdminStore, tuple[dict[str, Any], Done]] = {}  # in order of first submission
        self._writing: frozenset[AdminStore] = frozenset()
        self._waiters: list[tuple[AdminStore | None, asyncio.Future[None]]] = []
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="packml-admin-writer", daemon=True)
        self._thread.start()

    def submit(self, store: AdminStore, data: dict[str, Any], done: Done) -> None:
        with self._cond:
            if not self._closing:
                self._queue[store] = (data, done)  # a queued store keeps its place, with the newest data
                self._cond.notify()
                return
        log.debug("admin writer closed; storing %s in the caller's thread", store.path)
        AdminStore(store.path).submit(data, done)

    async def flush(self, store: AdminStore | None = None) -> None:
        """Return once nothing submitted (to ``store``, or at all) waits to be written, and the written
        data's ``done`` callbacks have run."""
        with self._cond:
            if self._idle(store):
                return
            if store in self._queue:  # somebody waits for it: next
                self._queue = {store: self._queue.pop(store), **self._queue}
            waiter: asyncio.Future[None] = self._loop.create_future()
            self._waiters.append((store, waiter))
        await waiter

    async def close(self) -> None:
        """Write everything submitted so far, then stop the thread; later submits write in the caller."""
        await self.flush()
        with self._cond:
            self._closing = True
            self._cond.notify()
        await asyncio.to_thread(self._thread.join)

    def _idle(self, store: AdminStore | None) -> bool:
        if store is None:
            return not self._queue and not self._writing
        return store not in self._queue and store not in self._writing

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return
                batch = dict(itertools.islice(self._queue.items(), BATCH))
                for store in batch:
                    del self._queue[store]
                self._writing = frozenset(batch)
            results = self._write(batch)
            with self._cond:
                self._writing = frozenset()
                ready = [w for s, w in self._waiters if self._idle(s)]
                self._waiters = [(s, w) for s, w in self._waiters if not self._idle(s)]
            # Scheduled in this order, the callbacks run before any waiter resumes.
            for done, error in results:
                self._call_soon(done, error)
            for waiter in ready:
                self._call_soon(_resolve, waiter)

    def _write(self, batch: dict[AdminStore, tuple[dict[str, Any], Done]]) -> list[tuple[Done, OSError | None]]:
        errors: dict[AdminStore, OSError] = {}
        directories: dict[Path, list[AdminStore]] = {}
        for store, (data, _) in batch.items():
            try:
                store._replace(data)
            except OSError as exc:
                errors[store] = exc
            except Exception as exc:  # a bug, not the disk: tell the model, keep the thread
                log.exception("storing PackML admin data to %s failed", store.path)
                errors[store] = OSError(str(exc))
            else:
                directories.setdefault(store.path.parent, []).append(store)
        for directory, stores in directories.items():
            try:
                _fsync_dir(directory)
            except OSError as exc:
                errors.update((s, exc) for s in stores)
        return [(done, errors.get(store)) for store, (_, done) in batch.items()]

    def _call_soon(self, callback: Callable[..., None], *args: Any) -> None:
        try:
            self._loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # the loop is closed: nobody is left to tell
            log.debug("event loop closed; dropping an admin writer callback")


def _resolve(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)


def _fsync_dir(directory: Path) -> None:
    # Makes the rename itself durable; not possible (nor needed) on Windows.
    if os.name != "posix":
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
