"""Durable PackML Admin data: one JSON file per unit, and in a server a journal beside them (decision 28).

A unit's file is replaced atomically: a save writes a temporary file next to it, fsyncs it, renames it
over the file with ``os.replace`` and fsyncs the directory, so at every instant the file is either the
previous complete file or the new complete file.

In a server the saves run on one ``AdminWriter`` thread shared by every unit, off the event loop, and
go to the directory's journal (``journal.jsonl``): a batch of saves is one appended line per unit and
one fsync, instead of a file replaced per unit (about a hundred a second in a cell of 100 units, whose
times gain a second each second). Every save carries the unit's sequence number; a load takes the
newer of the unit's file and its last complete line in the journal, so a crash loses nothing a done
callback was told of. The journal is folded into the units' files (each replaced atomically, then the
journal emptied) once it passes ``JOURNAL_LIMIT`` bytes, when the writer closes, and, left by a crash,
before the next run appends to it.

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
BATCH = 10  # stores written per batch (one journal fsync each): bounds how long a waiting call waits
JOURNAL = "journal.jsonl"
JOURNAL_LIMIT = 4 * 1024 * 1024  # bytes of journal before it is folded into the units' files
# Told once the data it was submitted with is durable (None) or could not be stored (the error).
Done = Callable[[OSError | None], None]


class AdminStore:
    """Load and save one unit's Admin data as JSON at ``path``; saves go through ``writer`` if given."""

    def __init__(self, path: str | os.PathLike[str], writer: AdminWriter | None = None) -> None:
        self.path = Path(path)
        self.writer = writer
        self.seq = 0  # the sequence number of the newest data stored or loaded (newer data: a higher one)

    def load(self) -> dict[str, Any] | None:
        """The stored data, or None if the file is absent (a first start: logged at INFO) or damaged
        (unreadable, corrupt, an unknown format: a WARNING). The newer of the file and the unit's last
        line in the directory's journal, when there is one. Temporaries a crash left beside the file
        (``<name>.json.<random>.tmp``, from a save that never reached its rename) are removed first."""
        with _journal_lock(self.path.parent):
            logged = _read_journal(self.path.parent).get(self.path.name)
            data = self._load_file(first_start=logged is None)
        if logged is not None and (data is None or logged.get("seq", 0) > data.get("seq", 0)):
            data = logged
        if data is None:
            return None
        self.seq = max(self.seq, int(data.get("seq", 0)))
        return {k: v for k, v in data.items() if k != "seq"}

    def _load_file(self, first_start: bool = False) -> dict[str, Any] | None:
        self._clean_temporaries()
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            if first_start:
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
        """Store ``data`` atomically and durably in the unit's file, now, in the calling thread."""
        self._save_stamped(self._stamped(data))

    def submit(self, data: dict[str, Any], done: Done) -> None:
        """Store ``data`` and then call ``done``: on the writer's thread if the store has a writer (``done``
        is called on the event loop), else now. ``data`` must not change afterwards."""
        if self.writer is not None:
            self.writer.submit(self, self._stamped(data), done)
        else:
            _stored_now(lambda: self.save(data), done)

    def _stamped(self, data: dict[str, Any]) -> dict[str, Any]:
        self.seq += 1
        return {**data, "seq": self.seq}

    def _save_stamped(self, data: dict[str, Any]) -> None:
        self._replace(data)
        _fsync_dir(self.path.parent)

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
    ``BATCH`` queued stores at a time, appends them to their directory's ``Journal`` (one fsync for the
    batch), and then calls the batch's ``done`` callbacks on the event loop, in submission order. A
    store somebody waits for (``flush(store)``) moves to the head of the queue. Closing folds the
    journals into the units' files.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._cond = threading.Condition()
        self._queue: dict[AdminStore, tuple[dict[str, Any], Done]] = {}  # in order of first submission
        self._writing: frozenset[AdminStore] = frozenset()
        self._waiters: list[tuple[AdminStore | None, asyncio.Future[None]]] = []
        self._closing = False
        self._journals: dict[Path, Journal] = {}  # by directory; used on the writer's thread only
        self._thread = threading.Thread(target=self._run, name="packml-admin-writer", daemon=True)
        self._thread.start()

    def submit(self, store: AdminStore, data: dict[str, Any], done: Done) -> None:
        with self._cond:
            if not self._closing:
                self._queue[store] = (data, done)  # a queued store keeps its place, with the newest data
                self._cond.notify()
                return
        log.debug("admin writer closed; storing %s in the caller's thread", store.path)
        with _journal_lock(store.path.parent):  # after the closing fold, never beside it
            _stored_now(lambda: store._save_stamped(data), done)

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
                    break
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
        for journal in self._journals.values():  # closing: a clean restart finds the units' files whole
            journal.fold()
            journal.close()

    def _write(self, batch: dict[AdminStore, tuple[dict[str, Any], Done]]) -> list[tuple[Done, OSError | None]]:
        """One journal append (and fsync) per directory for the batch; a journal past its limit is then
        folded into the units' files."""
        errors: dict[AdminStore, OSError] = {}
        directories: dict[Path, list[AdminStore]] = {}
        for store in batch:
            directories.setdefault(store.path.parent, []).append(store)
        for directory, stores in directories.items():
            journal = self._journals.get(directory)
            if journal is None:
                journal = self._journals[directory] = Journal(directory)
            try:
                journal.append([(store, batch[store][0]) for store in stores])
            except OSError as exc:
                errors.update((store, exc) for store in stores)
            except Exception as exc:  # a bug, not the disk: tell the model, keep the thread
                log.exception("storing PackML admin data to %s failed", journal.path)
                errors.update((store, OSError(str(exc))) for store in stores)
        for journal in self._journals.values():
            if journal.size > JOURNAL_LIMIT:
                journal.fold()
        return [(done, errors.get(store)) for store, (_, done) in batch.items()]

    def _call_soon(self, callback: Callable[..., None], *args: Any) -> None:
        try:
            self._loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # the loop is closed: nobody is left to tell
            log.debug("event loop closed; dropping an admin writer callback")


class Journal:
    """The journal of one directory of units' files, appended to by the writer's thread.

    Each line is ``{"unit": <file name>, "data": <the stamped data>}``; a line a crash cut short (or
    one that does not parse) is skipped by the readers. ``fold`` replaces each unit's file that the
    journal holds newer data for and then empties the journal.
    """

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.path = directory / JOURNAL
        self.size = 0
        self._file: Any = None
        self._latest: dict[str, dict[str, Any]] = {}  # by unit file name: the newest data appended

    def append(self, entries: list[tuple[AdminStore, dict[str, Any]]]) -> None:
        if self._file is not None and not self._still_there():
            self.close()  # the directory or the journal was removed meanwhile: made again, as a file would be
        if self._file is None:
            self._open()
        payload = "".join(
            json.dumps({"unit": store.path.name, "data": {**data, "version": FORMAT_VERSION}}, sort_keys=True) + "\n"
            for store, data in entries
        )
        try:
            self._file.write(payload)
            self._file.flush()
            os.fsync(self._file.fileno())
        except BaseException:
            self.close()  # a line may be cut short: opened again, after folding what is whole
            raise
        self.size += len(payload)
        for store, data in entries:
            self._latest[store.path.name] = data

    def fold(self) -> None:
        """Replace each unit's file the journal holds newer data for, then empty the journal (kept as it
        is, and an ERROR logged, when the disk refuses: a load still reads it)."""
        with _journal_lock(self.directory):
            try:
                if self._file is None:
                    self._fold_found()
                    return
                self._write_files(self._latest)
                self._file.truncate(0)
                os.fsync(self._file.fileno())
                _forget_journal(self.directory)
            except OSError as exc:
                log.error("cannot fold the PackML admin journal %s (%s); it is kept", self.path, exc)
                return
            self._latest.clear()
            self.size = 0

    def _still_there(self) -> bool:
        try:
            return os.stat(self.path).st_ino == os.fstat(self._file.fileno()).st_ino
        except OSError:
            return False

    def _open(self) -> None:
        with _journal_lock(self.directory):
            self._fold_found()  # a journal an earlier run left (a crash): never appended to as it is
            self.directory.mkdir(parents=True, exist_ok=True)
            # kept open until closed; readable by the service user only, as the units' files are (mkstemp)
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
            self._file = os.fdopen(fd, "a", encoding="utf-8")
            _fsync_dir(self.directory)  # the journal's own name durable before anything relies on it
            self.size = 0

    def _fold_found(self) -> None:
        found = _read_journal(self.directory)
        if not found:
            return
        self._write_files(found)
        with open(self.path, "r+b") as f:
            f.truncate(0)
            os.fsync(f.fileno())
        _forget_journal(self.directory)

    def _write_files(self, latest: dict[str, dict[str, Any]]) -> None:
        for name, data in latest.items():
            store = AdminStore(self.directory / name)
            on_file = store._load_file()
            if on_file is None or int(on_file.get("seq", 0)) < int(data.get("seq", 0)):
                store._replace({k: v for k, v in data.items() if k != "version"})
        _fsync_dir(self.directory)

    def close(self) -> None:
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None


_JOURNAL_LOCKS: dict[Path, threading.Lock] = {}
_JOURNAL_LOCKS_GUARD = threading.Lock()
_JOURNAL_CACHE: dict[Path, tuple[tuple[int, int], dict[str, dict[str, Any]]]] = {}


def _journal_lock(directory: Path) -> threading.Lock:
    """Loads of a directory's units and the folding of its journal exclude each other (a load reads the
    unit's file and then the journal: a fold between the two would hide the newer data)."""
    with _JOURNAL_LOCKS_GUARD:
        return _JOURNAL_LOCKS.setdefault(directory, threading.Lock())


def _read_journal(directory: Path) -> dict[str, dict[str, Any]]:
    """The newest whole line per unit of ``directory``'s journal ({} when there is none), parsed once
    for every unit that loads (kept while the file's size and time are unchanged)."""
    path = directory / JOURNAL
    try:
        stat = path.stat()
    except OSError:
        return {}
    key = (stat.st_size, stat.st_mtime_ns)
    cached = _JOURNAL_CACHE.get(directory)
    if cached is not None and cached[0] == key:
        return cached[1]
    latest: dict[str, dict[str, Any]] = {}
    damaged = 0
    try:
        raw = path.read_bytes()
    except OSError as exc:
        log.warning("cannot read the PackML admin journal %s (%s); using the units' files", path, exc)
        return {}
    # The part after the last line end is a line cut short (by a crash, or still being appended): never
    # told durable, so nothing a client has read.
    for line in raw.split(b"\n")[:-1]:
        try:
            entry = json.loads(line)
            name, data = str(entry["unit"]), dict(entry["data"])
            seq = int(data["seq"])
        except (ValueError, KeyError, TypeError):
            damaged += 1
            continue
        if data.get("version") == FORMAT_VERSION and seq >= int(latest.get(name, {}).get("seq", -1)):
            latest[name] = data
    if damaged:
        log.warning(
            "PackML admin journal %s: skipped %d damaged line(s); the units' files are used for them", path, damaged
        )
    _JOURNAL_CACHE[directory] = (key, latest)
    return latest


def _forget_journal(directory: Path) -> None:
    _JOURNAL_CACHE.pop(directory, None)


def _stored_now(save: Callable[[], None], done: Done) -> None:
    """``save()`` in the calling thread, then ``done`` with its error (None: durable)."""
    try:
        save()
    except OSError as exc:
        done(exc)
    else:
        done(None)


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
