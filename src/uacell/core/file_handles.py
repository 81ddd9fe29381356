"""Open files of a ``FileStore`` (uacell.core.file_store), OPC 10000-20 FileType: per-session handles
(Open, Read, Write, GetPosition, SetPosition, Close), bounded by a ``HandlePool``. A write handle works
on a private copy that Close commits atomically and durably. Pure: no OPC UA."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import threading
from collections.abc import Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO, Literal

from uacell.core.file_paths import (
    MODE_APPEND,
    MODE_ERASE_EXISTING,
    MODE_READ,
    MODE_WRITE,
    TEMP_PREFIX,
    StorePaths,
    fsync_dir,
    refuse,
)

logger = logging.getLogger(__name__)

_MAX_HANDLE = 0xFFFFFFFF  # handles are UInt32; 0 means "no handle" in CreateFile


class HandlePool:
    """Open file handles: at most ``per_session`` for one session and ``total`` over all sessions.

    One pool serves every ``FileStore`` of a server, so the limits hold server-wide.
    """

    def __init__(self, per_session: int = 16, total: int = 128) -> None:
        if per_session < 1 or total < 1:
            raise ValueError("handle limits must be positive")
        self.per_session, self.total = per_session, total
        self._open: dict[Hashable, int] = {}
        self._lock = threading.Lock()

    @property
    def in_use(self) -> int:
        with self._lock:
            return sum(self._open.values())

    def take(self, session: Hashable) -> None:
        """Count one more handle for ``session``; Bad_ResourceUnavailable beyond a limit."""
        with self._lock:
            mine = self._open.get(session, 0)
            if mine >= self.per_session:
                refuse("BadResourceUnavailable", f"a session may hold at most {self.per_session} open files")
            if sum(self._open.values()) >= self.total:
                refuse("BadResourceUnavailable", f"the server holds {self.total} open files, its limit")
            self._open[session] = mine + 1

    def give(self, session: Hashable) -> None:
        with self._lock:
            left = self._open.get(session, 0) - 1
            if left > 0:
                self._open[session] = left
            else:
                self._open.pop(session, None)


@dataclass
class Handle:
    session: Hashable
    relpath: str
    mode: int
    file: BinaryIO
    position: int
    temp: Path | None  # write handles only: the private copy that Close commits
    base: int = 0  # write handles: the file's committed size when opened (what the copy may grow from)

    @property
    def readable(self) -> bool:
        return bool(self.mode & MODE_READ)

    @property
    def writable(self) -> bool:
        return bool(self.mode & MODE_WRITE)


class OpenFiles(StorePaths):
    """The FileType side of ``FileStore``: its open handles."""

    handles: HandlePool
    max_read: int
    _handles: dict[int, Handle]
    _next_handle: int
    _lock: threading.RLock
    _usage: int | None

    if TYPE_CHECKING:  # FileStore's

        def _check_room(self, extra: int) -> None: ...

        def _protected(self, relpath: str) -> bool: ...

        def _emit(self, kind: Literal["added", "removed", "changed"], relpath: str, is_dir: bool) -> None: ...

    def open_count(self, relpath: str) -> int:
        """OpenCount: the number of valid handles on the file, over all sessions."""
        with self._lock:
            return sum(1 for h in self._handles.values() if h.relpath == relpath)

    def open(self, session: Hashable, relpath: str, mode: int) -> int:
        """Open: a handle valid for ``session`` only. Writing goes to a private copy until Close."""
        with self._lock:
            self._check_mode(mode)
            path = self._existing(relpath, want_dir=False)
            relpath = self._rel(path)
            others = [h for h in self._handles.values() if h.relpath == relpath]
            if mode & MODE_WRITE:
                if self._protected(relpath):
                    refuse("BadInvalidState", f"{relpath} is in use and cannot be written")
                if others:
                    refuse("BadNotWritable", f"{relpath} is already open")
                if not (os.access(path, os.W_OK) and os.access(path.parent, os.W_OK)):
                    refuse("BadNotWritable", f"{relpath} is read-only")
            elif any(h.writable for h in others):
                refuse("BadNotReadable", f"{relpath} is open for writing")
            if mode & MODE_READ and not os.access(path, os.R_OK):
                refuse("BadNotReadable", f"{relpath} cannot be read")
            self.handles.take(session)
            try:
                base = path.stat().st_size
                if mode & MODE_WRITE:
                    file, temp = self._private_copy(path, erase=bool(mode & MODE_ERASE_EXISTING))
                else:
                    file, temp = open(path, "rb"), None
            except OSError as exc:
                self.handles.give(session)
                logger.error("cannot open %s: %s", relpath, exc)
                refuse("BadUnexpectedError", f"cannot open {relpath}: {exc.strerror}")
            position = os.fstat(file.fileno()).st_size if mode & MODE_APPEND else 0
            handle = self._new_handle()
            self._handles[handle] = Handle(session, relpath, mode, file, position, temp, base)
            logger.debug("open %s mode %d -> handle %d", relpath, mode, handle)
            self._emit("changed", relpath, False)
            return handle

    def read(self, session: Hashable, handle: int, length: int) -> bytes:
        """Read: up to ``length`` bytes (at most ``max_read``) from the position; b"" at end of file."""
        with self._lock:
            h = self._handle(session, handle)
            if not isinstance(length, int) or length <= 0:
                refuse("BadInvalidArgument", "length must be positive", argument=1)
            if not h.readable:
                refuse("BadInvalidState", "the file was not opened for reading")
            try:
                h.file.seek(h.position)
                data = h.file.read(min(length, self.max_read))
            except OSError as exc:
                logger.exception("cannot read %s", h.relpath)
                refuse("BadUnexpectedError", f"cannot read {h.relpath}: {exc.strerror}")
            h.position += len(data)
            return data

    def write(self, session: Hashable, handle: int, data: bytes) -> None:
        """Write at the position (into the private copy; the file changes on Close)."""
        with self._lock:
            h = self._handle(session, handle)
            if not h.writable:
                refuse("BadInvalidState", "the file was not opened for writing")
            if self._protected(h.relpath):
                # Became the loaded program after Open: refuse rather than change it under the robot.
                refuse("BadNotWritable", f"{h.relpath} is in use and cannot be written")
            if not data:
                return
            size = os.fstat(h.file.fileno()).st_size
            self._check_room(max(0, h.position + len(data) - size))
            try:
                h.file.seek(h.position)
                h.file.write(data)
            except OSError as exc:
                logger.exception("cannot write %s", h.relpath)
                refuse("BadUnexpectedError", f"cannot write {h.relpath}: {exc.strerror}")
            h.position += len(data)

    def get_position(self, session: Hashable, handle: int) -> int:
        with self._lock:
            return self._handle(session, handle).position

    def set_position(self, session: Hashable, handle: int, position: int) -> None:
        """SetPosition; a position past the end is set to the end (as the specification says)."""
        with self._lock:
            h = self._handle(session, handle)
            if not isinstance(position, int) or position < 0:
                refuse("BadInvalidArgument", "position must be a UInt64", argument=1)
            h.file.flush()
            h.position = min(position, os.fstat(h.file.fileno()).st_size)

    def close(self, session: Hashable, handle: int) -> None:
        """Close: the handle ends; a write handle's content replaces the file atomically and durably.

        The handle is gone even when committing fails (Bad_UnexpectedError, or Bad_InvalidState if the
        file became protected meanwhile); then the old content is kept and the private copy removed.
        """
        with self._lock:
            h = self._handle(session, handle)
            del self._handles[handle]
            self.handles.give(session)
            try:
                if h.temp is None:
                    h.file.close()
                elif self._protected(h.relpath):
                    self._discard(h)
                    refuse("BadInvalidState", f"{h.relpath} is in use; the written content was discarded")
                else:
                    self._commit(h)
            finally:
                self._emit("changed", h.relpath, False)

    def close_session(self, session: Hashable) -> int:
        """Drop every handle ``session`` holds; uncommitted writes are discarded. Returns how many."""
        with self._lock:
            mine = [n for n, h in self._handles.items() if h.session == session]
            for n in mine:
                h = self._handles.pop(n)
                self.handles.give(session)
                self._discard(h)
                self._emit("changed", h.relpath, False)
            if mine:
                logger.info("closed %d file handle(s) of a closed session", len(mine))
            return len(mine)

    def close_all(self) -> int:
        """Drop every handle of every session (shutting down); uncommitted writes are discarded."""
        with self._lock:
            sessions = {h.session for h in self._handles.values()}
        return sum(self.close_session(session) for session in sessions)

    @staticmethod
    def _check_mode(mode: int) -> None:
        if not isinstance(mode, int) or not 0 < mode <= 0x0F:
            refuse("BadInvalidArgument", f"invalid open mode {mode!r}", argument=0)
        if not mode & (MODE_READ | MODE_WRITE):
            refuse("BadInvalidArgument", "open mode has neither Read nor Write", argument=0)
        if mode & (MODE_ERASE_EXISTING | MODE_APPEND) and not mode & MODE_WRITE:
            refuse("BadInvalidArgument", "EraseExisting and Append need Write", argument=0)

    def _new_handle(self) -> int:
        while True:
            handle = self._next_handle
            self._next_handle = handle % _MAX_HANDLE + 1
            if handle not in self._handles:
                return handle

    def _handle(self, session: Hashable, handle: int) -> Handle:
        h = self._handles.get(handle) if isinstance(handle, int) else None
        if h is None or h.session != session:
            refuse("BadInvalidArgument", f"invalid file handle {handle!r}", argument=0)
        return h

    @staticmethod
    def _private_copy(path: Path, erase: bool) -> tuple[BinaryIO, Path]:
        """A temporary file next to ``path`` holding its content (or nothing), open for read+write."""
        fd, name = tempfile.mkstemp(prefix=TEMP_PREFIX, dir=path.parent)
        temp = Path(name)
        try:
            file = os.fdopen(fd, "r+b")
        except BaseException:
            os.close(fd)
            temp.unlink()
            raise
        try:
            shutil.copymode(path, temp)
            if not erase:
                with open(path, "rb") as src:
                    shutil.copyfileobj(src, file)
                file.flush()
            return file, temp
        except BaseException:
            file.close()
            temp.unlink()
            raise

    def _commit(self, h: Handle) -> None:
        assert h.temp is not None
        target = self.root / h.relpath
        try:
            h.file.flush()
            os.fsync(h.file.fileno())
            h.file.close()
            os.replace(h.temp, target)
            fsync_dir(target.parent)
            self._usage = None
        except OSError as exc:
            logger.exception("cannot commit %s; the old content is kept", h.relpath)
            self._discard(h)
            refuse("BadUnexpectedError", f"cannot write {h.relpath}: {exc.strerror}")
        logger.info("wrote %s (%d bytes)", h.relpath, target.stat().st_size)

    @staticmethod
    def _discard(h: Handle) -> None:
        with contextlib.suppress(OSError):
            h.file.close()
        if h.temp is not None:
            with contextlib.suppress(FileNotFoundError):
                h.temp.unlink()
