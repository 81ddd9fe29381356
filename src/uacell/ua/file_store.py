"""The file-system side of a FileDirectoryType / FileType tree (OPC 10000-20, formerly 10000-5 Annex C).

``FileStore`` serves one real directory: listing, per-session file handles (Open, Read, Write,
GetPosition, SetPosition, Close) and the directory methods (CreateFile, CreateDirectory, Delete,
MoveOrCopy), refusing with the status codes the specification lists. It knows nothing of OPC UA
nodes: entries are relative POSIX paths ("sub/prog.robot", "" is the root) and a session is any
hashable the binding chooses.

Writes never touch the real file before Close: a write handle works on a private temporary file in
the same directory, and Close replaces the file atomically and durably (fsync, rename, fsync of the
directory). A crash or a dropped session leaves the old content. Temporary files are hidden from
listings and removed when the store starts.

Bounded: a ``HandlePool`` (shared by every store of a server) caps open handles per session and in
all, and ``max_bytes`` caps what the directory holds (each entry counts ``ENTRY_BYTES`` on top of its
size; content being written counts as soon as it is written). Both refuse with Bad_ResourceUnavailable.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import stat
import tempfile
import threading
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Literal, NoReturn

from uacell.errors import CallError
from uacell.files import settled

logger = logging.getLogger(__name__)

# OpenFileMode bits (OPC 10000-20 4.2.2); bits 4..7 are reserved and must be zero.
MODE_READ = 1
MODE_WRITE = 2
MODE_ERASE_EXISTING = 4
MODE_APPEND = 8

#: Prefix of the store's own temporary files and directories: hidden, refused as a name, removed on start.
TEMP_PREFIX = ".uacell-tmp-"

_MAX_NAME_BYTES = 255  # NAME_MAX on the file systems uacell runs on
_MAX_HANDLE = 0xFFFFFFFF  # handles are UInt32; 0 means "no handle" in CreateFile
#: What each file or directory costs on top of its content, for ``max_bytes``: many empty files fill it too.
ENTRY_BYTES = 512


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
                _refuse("BadResourceUnavailable", f"a session may hold at most {self.per_session} open files")
            if sum(self._open.values()) >= self.total:
                _refuse("BadResourceUnavailable", f"the server holds {self.total} open files, its limit")
            self._open[session] = mine + 1

    def give(self, session: Hashable) -> None:
        with self._lock:
            left = self._open.get(session, 0) - 1
            if left > 0:
                self._open[session] = left
            else:
                self._open.pop(session, None)


@dataclass(frozen=True)
class Entry:
    """A file or directory below the root. ``size`` is the committed size (0 for directories)."""

    relpath: str
    is_dir: bool
    size: int
    writable: bool

    @property
    def name(self) -> str:
        return self.relpath.rpartition("/")[2]


@dataclass(frozen=True)
class Change:
    """Something the binding must mirror: an entry appeared, disappeared, or its size/OpenCount changed."""

    kind: Literal["added", "removed", "changed"]
    relpath: str
    is_dir: bool


Listener = Callable[[Change], None]
Protect = Callable[[str], bool]


@dataclass
class _Handle:
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


def _refuse(status: str, message: str, argument: int | None = None, argument_status: str | None = None) -> NoReturn:
    logger.debug("file store refuses: %s (%s)", status, message)
    raise CallError(status, message, argument=argument, argument_status=argument_status)


def _fsync_dir(path: Path) -> None:
    """Make a rename/create/unlink in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    """Remove a file or directory tree; missing is fine (used on clean-up paths)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def _signature(dirs: list[Path]) -> tuple[tuple[Path, int], ...] | None:
    """The directories' modification times, or None when one is too recent (``files.settled``) or gone."""
    out = []
    for d in dirs:
        try:
            st = os.stat(d)
        except OSError:
            return None
        if not settled(st):
            return None
        out.append((d, st.st_mtime_ns))
    return tuple(out)


def _unchanged(signature: tuple[tuple[Path, int], ...]) -> bool:
    try:
        return all(os.stat(d).st_mtime_ns == mtime for d, mtime in signature)
    except OSError:
        return False


class FileStore:
    """Files and directories below ``root`` with OPC UA FileType/FileDirectoryType semantics.

    ``protect(relpath) -> bool`` says an entry is in use (the loaded program): it cannot be deleted,
    moved or opened for writing. ``listeners`` receive a ``Change`` after every visible change.
    """

    def __init__(
        self,
        root: Path,
        *,
        protect: Protect | None = None,
        max_read: int = 1 << 20,
        max_bytes: int | None = None,
        handles: HandlePool | None = None,
    ) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._root_text = str(self.root)
        self.protect: Protect | None = protect
        self.listeners: list[Listener] = []
        self.max_read = max_read
        self.max_bytes = max_bytes
        self.handles = handles if handles is not None else HandlePool()
        self._usage: int | None = None  # committed bytes (see ENTRY_BYTES), None: walk to know
        self._listings: dict[str, tuple[tuple[tuple[Path, int], ...], tuple[str, ...]]] = {}  # files()
        self._handles: dict[int, _Handle] = {}
        self._next_handle = 1
        self._lock = threading.RLock()
        self._clean_temporaries()

    # ------------------------------------------------------------------ listing

    def entries(self, dir_relpath: str = "") -> list[Entry]:
        """Every entry below ``dir_relpath`` (recursively), parents before their children."""
        with self._lock:
            base = self._existing(dir_relpath, want_dir=True)
            return [self._entry(p) for p in self._walk(base)]

    def files(self, suffix: str = "") -> list[str]:
        """The relative paths of every visible file whose name ends in ``suffix``, sorted: a listing that,
        unlike ``entries``, asks the disk for nothing but the directories, and is kept while none of
        them changed (their modification times; a directory changed in the last two seconds is read
        again, whatever the file system's clock resolution: ``files.settled``)."""
        with self._lock:
            cached = self._listings.get(suffix)
            if cached is not None and _unchanged(cached[0]):
                return list(cached[1])
            found: list[str] = []
            dirs: list[Path] = []
            for p in self._walk(self.root, files_only=True, dirs=dirs):
                if p.name.endswith(suffix):
                    found.append(self._rel(p))
            found.sort()
            signature = _signature(dirs)
            if signature is not None:
                self._listings[suffix] = (signature, tuple(found))
            return found

    def entry(self, relpath: str) -> Entry:
        """The entry at ``relpath``; Bad_NotFound if there is none."""
        with self._lock:
            # The components were checked (names, no symlinks): the entry's path is ``relpath`` itself.
            return self._entry(self._existing(relpath), relpath)

    def open_count(self, relpath: str) -> int:
        """OpenCount: the number of valid handles on the file, over all sessions."""
        with self._lock:
            return sum(1 for h in self._handles.values() if h.relpath == relpath)

    # ------------------------------------------------------------------ FileType

    def open(self, session: Hashable, relpath: str, mode: int) -> int:
        """Open: a handle valid for ``session`` only. Writing goes to a private copy until Close."""
        with self._lock:
            self._check_mode(mode)
            path = self._existing(relpath, want_dir=False)
            relpath = self._rel(path)
            others = [h for h in self._handles.values() if h.relpath == relpath]
            if mode & MODE_WRITE:
                if self._protected(relpath):
                    _refuse("BadInvalidState", f"{relpath} is in use and cannot be written")
                if others:
                    _refuse("BadNotWritable", f"{relpath} is already open")
                if not (os.access(path, os.W_OK) and os.access(path.parent, os.W_OK)):
                    _refuse("BadNotWritable", f"{relpath} is read-only")
            elif any(h.writable for h in others):
                _refuse("BadNotReadable", f"{relpath} is open for writing")
            if mode & MODE_READ and not os.access(path, os.R_OK):
                _refuse("BadNotReadable", f"{relpath} cannot be read")
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
                _refuse("BadUnexpectedError", f"cannot open {relpath}: {exc.strerror}")
            position = os.fstat(file.fileno()).st_size if mode & MODE_APPEND else 0
            handle = self._new_handle()
            self._handles[handle] = _Handle(session, relpath, mode, file, position, temp, base)
            logger.debug("open %s mode %d -> handle %d", relpath, mode, handle)
            self._emit("changed", relpath, False)
            return handle

    def read(self, session: Hashable, handle: int, length: int) -> bytes:
        """Read: up to ``length`` bytes (at most ``max_read``) from the position; b"" at end of file."""
        with self._lock:
            h = self._handle(session, handle)
            if not isinstance(length, int) or length <= 0:
                _refuse("BadInvalidArgument", "length must be positive", argument=1)
            if not h.readable:
                _refuse("BadInvalidState", "the file was not opened for reading")
            try:
                h.file.seek(h.position)
                data = h.file.read(min(length, self.max_read))
            except OSError as exc:
                logger.exception("cannot read %s", h.relpath)
                _refuse("BadUnexpectedError", f"cannot read {h.relpath}: {exc.strerror}")
            h.position += len(data)
            return data

    def write(self, session: Hashable, handle: int, data: bytes) -> None:
        """Write at the position (into the private copy; the file changes on Close)."""
        with self._lock:
            h = self._handle(session, handle)
            if not h.writable:
                _refuse("BadInvalidState", "the file was not opened for writing")
            if self._protected(h.relpath):
                # Became the loaded program after Open: refuse rather than change it under the robot.
                _refuse("BadNotWritable", f"{h.relpath} is in use and cannot be written")
            if not data:
                return
            size = os.fstat(h.file.fileno()).st_size
            self._check_room(max(0, h.position + len(data) - size))
            try:
                h.file.seek(h.position)
                h.file.write(data)
            except OSError as exc:
                logger.exception("cannot write %s", h.relpath)
                _refuse("BadUnexpectedError", f"cannot write {h.relpath}: {exc.strerror}")
            h.position += len(data)

    def get_position(self, session: Hashable, handle: int) -> int:
        with self._lock:
            return self._handle(session, handle).position

    def set_position(self, session: Hashable, handle: int, position: int) -> None:
        """SetPosition; a position past the end is set to the end (as the specification says)."""
        with self._lock:
            h = self._handle(session, handle)
            if not isinstance(position, int) or position < 0:
                _refuse("BadInvalidArgument", "position must be a UInt64", argument=1)
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
                    _refuse("BadInvalidState", f"{h.relpath} is in use; the written content was discarded")
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

    # ------------------------------------------------------------------ FileDirectoryType

    def create_file(
        self, session: Hashable, dir_relpath: str, name: str, request_file_open: bool
    ) -> tuple[str, int | None]:
        """CreateFile: an empty file; with ``request_file_open`` also a Read+Write handle."""
        with self._lock:
            parent = self._existing(dir_relpath, want_dir=True)
            self._check_name(name, argument=0)
            path = parent / name
            if os.path.lexists(path):
                _refuse("BadBrowseNameDuplicated", f"{name} already exists", argument=0)
            self._check_room(ENTRY_BYTES)
            try:
                fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
                _fsync_dir(parent)
            except FileExistsError:
                _refuse("BadBrowseNameDuplicated", f"{name} already exists", argument=0)
            except OSError as exc:
                logger.exception("cannot create %s", path)
                _refuse("BadUnexpectedError", f"cannot create {name}: {exc.strerror}")
            relpath = self._rel(path)
            self._grew(ENTRY_BYTES)
            logger.info("created file %s", relpath)
            self._emit("added", relpath, False)
            handle = self.open(session, relpath, MODE_READ | MODE_WRITE) if request_file_open else None
            return relpath, handle

    def create_directory(self, dir_relpath: str, name: str) -> str:
        """CreateDirectory: returns the new directory's relpath."""
        with self._lock:
            parent = self._existing(dir_relpath, want_dir=True)
            self._check_name(name, argument=0)
            path = parent / name
            if os.path.lexists(path):
                _refuse("BadBrowseNameDuplicated", f"{name} already exists", argument=0)
            self._check_room(ENTRY_BYTES)
            try:
                path.mkdir()
                _fsync_dir(parent)
            except FileExistsError:
                _refuse("BadBrowseNameDuplicated", f"{name} already exists", argument=0)
            except OSError as exc:
                logger.exception("cannot create directory %s", path)
                _refuse("BadUnexpectedError", f"cannot create {name}: {exc.strerror}")
            relpath = self._rel(path)
            self._grew(ENTRY_BYTES)
            logger.info("created directory %s", relpath)
            self._emit("added", relpath, True)
            return relpath

    def delete(self, relpath: str) -> None:
        """Delete a file, or a directory with everything below it."""
        with self._lock:
            if relpath == "":
                _refuse("BadInvalidArgument", "the root cannot be deleted", argument=0)
            path = self._existing(relpath, argument=0)
            relpath = self._rel(path)
            self._check_unlocked(path, argument=0)
            gone = [self._entry(path), *(self._entry(p) for p in self._walk(path))]
            try:
                if path.is_dir():
                    # Rename away first: the directory disappears at once, a crash leaves only a temporary.
                    doomed = Path(tempfile.mkdtemp(prefix=TEMP_PREFIX, dir=path.parent))
                    os.rename(path, doomed / "d")
                    _fsync_dir(path.parent)
                    shutil.rmtree(doomed, ignore_errors=True)
                else:
                    path.unlink()
                    _fsync_dir(path.parent)
            except OSError as exc:
                logger.exception("cannot delete %s", relpath)
                _refuse("BadUnexpectedError", f"cannot delete {relpath}: {exc.strerror}")
            self._usage = None
            logger.info("deleted %s", relpath)
            for e in reversed(gone):
                self._emit("removed", e.relpath, e.is_dir)

    def move_or_copy(
        self, src_relpath: str, target_dir_relpath: str, create_copy: bool, new_name: str | None = None
    ) -> str:
        """MoveOrCopy (also rename: same directory, new name). Returns the new relpath."""
        with self._lock:
            if src_relpath == "":
                _refuse("BadInvalidArgument", "the root cannot be moved or copied", argument=0)
            src = self._existing(src_relpath, argument=0)
            target = self._existing(target_dir_relpath, want_dir=True, argument=1)
            name = new_name or src.name
            if new_name:
                self._check_name(new_name, argument=3)
            dest = target / name
            src_rel, dest_rel = self._rel(src), self._rel(dest)
            if not create_copy:
                self._check_unlocked(src, argument=0)
            if os.path.lexists(dest):
                where = 3 if new_name else None
                _refuse("BadBrowseNameDuplicated", f"{dest_rel} already exists", argument=where)
            if src.is_dir() and dest_rel.startswith(src_rel + "/"):
                _refuse("BadInvalidArgument", "a directory cannot go inside itself", argument=1)
            gone = [] if create_copy else [self._entry(src), *(self._entry(p) for p in self._walk(src))]
            if create_copy:
                self._check_room(self._size_of(src))
            try:
                if create_copy:
                    self._copy(src, dest)
                else:
                    os.rename(src, dest)
                    _fsync_dir(dest.parent)
                    if src.parent != dest.parent:
                        _fsync_dir(src.parent)
            except OSError as exc:
                logger.exception("cannot %s %s", "copy" if create_copy else "move", src_rel)
                _refuse("BadUnexpectedError", f"cannot move or copy {src_rel}: {exc.strerror}")
            self._usage = None
            logger.info("%s %s -> %s", "copied" if create_copy else "moved", src_rel, dest_rel)
            for e in reversed(gone):
                self._emit("removed", e.relpath, e.is_dir)
            self._emit("added", dest_rel, dest.is_dir())
            for p in self._walk(dest):
                self._emit("added", self._rel(p), p.is_dir())
            return dest_rel

    # ------------------------------------------------------------------ internals

    def usage(self) -> int:
        """Bytes the directory holds as ``max_bytes`` counts them (committed content, ENTRY_BYTES each)."""
        with self._lock:
            if self._usage is None:
                self._usage = sum(self._size_of(p, walk=False) for p in self._walk(self.root))
            return self._usage

    def _size_of(self, path: Path, *, walk: bool = True) -> int:
        paths = [path, *self._walk(path)] if walk else [path]
        total = 0
        for p in paths:
            with contextlib.suppress(OSError):
                total += ENTRY_BYTES + (0 if p.is_dir() else p.stat().st_size)
        return total

    def _grew(self, size: int) -> None:
        if self._usage is not None:
            self._usage += size

    def _check_room(self, extra: int) -> None:
        """Bad_ResourceUnavailable if ``extra`` more bytes (on top of uncommitted writes) exceed max_bytes."""
        if self.max_bytes is None or extra <= 0:
            return
        pending = 0
        for h in self._handles.values():
            if h.temp is not None:
                with contextlib.suppress(OSError):
                    pending += max(0, os.fstat(h.file.fileno()).st_size - h.base)
        if self.usage() + pending + extra > self.max_bytes:
            _refuse("BadResourceUnavailable", f"the directory would hold more than {self.max_bytes} bytes")

    def _emit(self, kind: Literal["added", "removed", "changed"], relpath: str, is_dir: bool) -> None:
        change = Change(kind, relpath, is_dir)
        for listener in list(self.listeners):
            try:
                listener(change)
            except Exception:
                # A listener's bug must not undo or half-apply a change that already happened on disk.
                logger.exception("file store listener failed on %s", change)

    def _protected(self, relpath: str) -> bool:
        return self.protect is not None and bool(self.protect(relpath))

    def _check_unlocked(self, path: Path, argument: int) -> None:
        """Bad_InvalidState if ``path`` or anything below it is protected or has an open handle."""
        for p in [path, *self._walk(path)]:
            rel = self._rel(p)
            if self._protected(rel):
                _refuse("BadInvalidState", f"{rel} is in use", argument=argument)
            if any(h.relpath == rel for h in self._handles.values()):
                _refuse("BadInvalidState", f"{rel} is open", argument=argument)

    @staticmethod
    def _check_mode(mode: int) -> None:
        if not isinstance(mode, int) or not 0 < mode <= 0x0F:
            _refuse("BadInvalidArgument", f"invalid open mode {mode!r}", argument=0)
        if not mode & (MODE_READ | MODE_WRITE):
            _refuse("BadInvalidArgument", "open mode has neither Read nor Write", argument=0)
        if mode & (MODE_ERASE_EXISTING | MODE_APPEND) and not mode & MODE_WRITE:
            _refuse("BadInvalidArgument", "EraseExisting and Append need Write", argument=0)

    @staticmethod
    def _check_name(name: object, argument: int | None) -> None:
        """A single path component that the store may create (no separators, no '..', not ours)."""
        ok = (
            isinstance(name, str)
            and name not in ("", ".", "..")
            and not any(c in name for c in "/\\\0")
            and not name.startswith(TEMP_PREFIX)
            and len(name.encode("utf-8", "surrogateescape")) <= _MAX_NAME_BYTES
        )
        if not ok:
            _refuse(
                "BadInvalidArgument",
                f"invalid name {name!r}",
                argument=argument,
                argument_status="BadBrowseNameInvalid",
            )

    def _existing(self, relpath: str, *, want_dir: bool | None = None, argument: int | None = None) -> Path:
        """The path of an existing entry, never outside the root and never through a symlink: each
        component is a valid name (no separator, no '..') and no component is a symlink (one ``lstat``
        each), so the path stays below the root."""
        if not isinstance(relpath, str):
            _refuse("BadInvalidArgument", f"invalid path {relpath!r}", argument=argument)
        path = self._root_text
        # Below the root, the last component's lstat is the mode (and fails when the root is gone).
        mode = None if relpath else self._root_mode()
        if relpath:
            for part in relpath.split("/"):
                self._check_name(part, argument=argument)
                path = f"{path}/{part}"
                try:
                    mode = os.lstat(path).st_mode
                except OSError:
                    _refuse("BadNotFound", f"{relpath} not found", argument=argument)
                # Symlinks are neither listed nor followed: they could lead out of the root.
                if stat.S_ISLNK(mode):
                    _refuse("BadNotFound", f"{relpath} not found", argument=argument)
        if mode is None:
            _refuse("BadNotFound", f"{relpath} not found", argument=argument)
        if want_dir is not None and stat.S_ISDIR(mode) != want_dir:
            _refuse("BadNotFound", f"{relpath} is not a {'directory' if want_dir else 'file'}", argument=argument)
        return Path(path)

    def _root_mode(self) -> int | None:
        try:
            return os.stat(self._root_text).st_mode
        except OSError:
            return None

    def _rel(self, path: Path) -> str:
        return path.relative_to(self.root).as_posix() if path != self.root else ""

    def _entry(self, path: Path, rel: str | None = None) -> Entry:
        st = os.stat(path)
        rel = self._rel(path) if rel is None else rel
        if stat.S_ISDIR(st.st_mode):
            return Entry(rel, True, 0, os.access(path, os.W_OK))
        writable = os.access(path, os.W_OK) and os.access(path.parent, os.W_OK)
        return Entry(rel, False, st.st_size, writable)

    def _walk(self, base: Path, *, files_only: bool = False, dirs: list[Path] | None = None) -> Iterator[Path]:
        """Visible entries (or only files) below ``base``, top-down and sorted: no temporaries, no symlinks;
        ``dirs`` receives every directory read."""
        if not base.is_dir():
            return
        for dirpath, dirnames, filenames in os.walk(base):
            here = Path(dirpath)
            if dirs is not None:
                dirs.append(here)
            dirnames[:] = sorted(d for d in dirnames if not d.startswith(TEMP_PREFIX) and not (here / d).is_symlink())
            files = [f for f in filenames if not f.startswith(TEMP_PREFIX) and not (here / f).is_symlink()]
            for name in sorted(files if files_only else [*dirnames, *files]):
                yield here / name

    def _new_handle(self) -> int:
        while True:
            handle = self._next_handle
            self._next_handle = handle % _MAX_HANDLE + 1
            if handle not in self._handles:
                return handle

    def _handle(self, session: Hashable, handle: int) -> _Handle:
        h = self._handles.get(handle) if isinstance(handle, int) else None
        if h is None or h.session != session:
            _refuse("BadInvalidArgument", f"invalid file handle {handle!r}", argument=0)
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

    def _commit(self, h: _Handle) -> None:
        assert h.temp is not None
        target = self.root / h.relpath
        try:
            h.file.flush()
            os.fsync(h.file.fileno())
            h.file.close()
            os.replace(h.temp, target)
            _fsync_dir(target.parent)
            self._usage = None
        except OSError as exc:
            logger.exception("cannot commit %s; the old content is kept", h.relpath)
            self._discard(h)
            _refuse("BadUnexpectedError", f"cannot write {h.relpath}: {exc.strerror}")
        logger.info("wrote %s (%d bytes)", h.relpath, target.stat().st_size)

    @staticmethod
    def _discard(h: _Handle) -> None:
        with contextlib.suppress(OSError):
            h.file.close()
        if h.temp is not None:
            with contextlib.suppress(FileNotFoundError):
                h.temp.unlink()

    def _copy(self, src: Path, dest: Path) -> None:
        """Copy a file or tree so that ``dest`` appears complete or not at all."""
        temp = Path(tempfile.mkdtemp(prefix=TEMP_PREFIX, dir=dest.parent))
        try:
            staged = temp / "c"
            if src.is_dir():
                shutil.copytree(src, staged, ignore=self._not_copied, copy_function=_copy_synced)
                for dirpath, _dirs, _files in os.walk(staged):
                    _fsync_dir(Path(dirpath))
            else:
                _copy_synced(src, staged)
            os.rename(staged, dest)
            _fsync_dir(dest.parent)
        finally:
            shutil.rmtree(temp, ignore_errors=True)

    @staticmethod
    def _not_copied(dirpath: str, names: list[str]) -> set[str]:
        return {n for n in names if n.startswith(TEMP_PREFIX) or os.path.islink(os.path.join(dirpath, n))}

    def _clean_temporaries(self) -> None:
        """Remove what interrupted writes, copies and deletes left behind."""
        found = []
        for dirpath, dirnames, filenames in os.walk(self.root):
            for name in [*dirnames, *filenames]:
                if name.startswith(TEMP_PREFIX):
                    found.append(Path(dirpath) / name)
            dirnames[:] = [d for d in dirnames if not d.startswith(TEMP_PREFIX)]
        for path in found:
            _remove(path)
        if found:
            logger.warning("removed %d leftover temporary file(s) under %s", len(found), self.root)


def _copy_synced(src: str | Path, dst: str | Path) -> None:
    shutil.copy2(src, dst)
    fd = os.open(dst, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
