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

The store is split along its responsibilities: paths and listings (``uacell.core.file_paths``), open
files and their handles (``uacell.core.file_handles``), and here the directory methods, the byte quota
and the change events.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import threading
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Literal

from uacell.core.file_handles import Handle, HandlePool, OpenFiles
from uacell.core.file_paths import (
    ENTRY_BYTES,
    MODE_APPEND,
    MODE_ERASE_EXISTING,
    MODE_READ,
    MODE_WRITE,
    TEMP_PREFIX,
    Change,
    Entry,
    Listener,
    Protect,
    fsync_dir,
    refuse,
)
from uacell.core.files import settled

__all__ = [  # what other modules import from here, wherever it is defined
    "ENTRY_BYTES", "MODE_APPEND", "MODE_ERASE_EXISTING", "MODE_READ", "MODE_WRITE", "TEMP_PREFIX",
    "Change", "Entry", "FileStore", "HandlePool", "Listener", "Protect",
]  # fmt: skip

logger = logging.getLogger(__name__)


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


class FileStore(OpenFiles):
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
        self._handles: dict[int, Handle] = {}
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

    # ------------------------------------------------------------------ FileDirectoryType

    def create_file(
        self, session: Hashable, dir_relpath: str, name: str, request_file_open: bool
    ) -> tuple[str, int | None]:
        """CreateFile: an empty file; with ``request_file_open`` also a Read+Write handle."""
        with self._lock:
            relpath = self._create(dir_relpath, name, _make_empty_file, directory=False)
            handle = self.open(session, relpath, MODE_READ | MODE_WRITE) if request_file_open else None
            return relpath, handle

    def create_directory(self, dir_relpath: str, name: str) -> str:
        """CreateDirectory: returns the new directory's relpath."""
        with self._lock:
            return self._create(dir_relpath, name, Path.mkdir, directory=True)

    def _create(self, dir_relpath: str, name: str, make: Callable[[Path], object], directory: bool) -> str:
        """A new entry ``name`` in the directory ``dir_relpath``, made by ``make(path)`` and durable
        (its directory fsynced); its relpath. Refused when the name is taken or there is no room."""
        what = "directory" if directory else "file"
        parent = self._existing(dir_relpath, want_dir=True)
        self._check_name(name, argument=0)
        path = parent / name
        if os.path.lexists(path):
            refuse("BadBrowseNameDuplicated", f"{name} already exists", argument=0)
        self._check_room(ENTRY_BYTES)
        try:
            make(path)
            fsync_dir(parent)
        except FileExistsError:
            refuse("BadBrowseNameDuplicated", f"{name} already exists", argument=0)
        except OSError as exc:
            logger.exception("cannot create %s %s", what, path)
            refuse("BadUnexpectedError", f"cannot create {name}: {exc.strerror}")
        relpath = self._rel(path)
        self._grew(ENTRY_BYTES)
        logger.info("created %s %s", what, relpath)
        self._emit("added", relpath, directory)
        return relpath

    def delete(self, relpath: str) -> None:
        """Delete a file, or a directory with everything below it."""
        with self._lock:
            if relpath == "":
                refuse("BadInvalidArgument", "the root cannot be deleted", argument=0)
            path = self._existing(relpath, argument=0)
            relpath = self._rel(path)
            self._check_unlocked(path, argument=0)
            gone = [self._entry(path), *(self._entry(p) for p in self._walk(path))]
            try:
                if path.is_dir():
                    # Rename away first: the directory disappears at once, a crash leaves only a temporary.
                    doomed = Path(tempfile.mkdtemp(prefix=TEMP_PREFIX, dir=path.parent))
                    os.rename(path, doomed / "d")
                    fsync_dir(path.parent)
                    shutil.rmtree(doomed, ignore_errors=True)
                else:
                    path.unlink()
                    fsync_dir(path.parent)
            except OSError as exc:
                logger.exception("cannot delete %s", relpath)
                refuse("BadUnexpectedError", f"cannot delete {relpath}: {exc.strerror}")
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
                refuse("BadInvalidArgument", "the root cannot be moved or copied", argument=0)
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
                refuse("BadBrowseNameDuplicated", f"{dest_rel} already exists", argument=where)
            if src.is_dir() and dest_rel.startswith(src_rel + "/"):
                refuse("BadInvalidArgument", "a directory cannot go inside itself", argument=1)
            gone = [] if create_copy else [self._entry(src), *(self._entry(p) for p in self._walk(src))]
            if create_copy:
                self._check_room(self._size_of(src))
            try:
                if create_copy:
                    self._copy(src, dest)
                else:
                    os.rename(src, dest)
                    fsync_dir(dest.parent)
                    if src.parent != dest.parent:
                        fsync_dir(src.parent)
            except OSError as exc:
                logger.exception("cannot %s %s", "copy" if create_copy else "move", src_rel)
                refuse("BadUnexpectedError", f"cannot move or copy {src_rel}: {exc.strerror}")
            self._usage = None
            logger.info("%s %s -> %s", "copied" if create_copy else "moved", src_rel, dest_rel)
            for e in reversed(gone):
                self._emit("removed", e.relpath, e.is_dir)
            self._emit("added", dest_rel, dest.is_dir())
            for p in self._walk(dest):
                self._emit("added", self._rel(p), p.is_dir())
            return dest_rel

    # ------------------------------------------------------------------ quota and events

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
            refuse("BadResourceUnavailable", f"the directory would hold more than {self.max_bytes} bytes")

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
                refuse("BadInvalidState", f"{rel} is in use", argument=argument)
            if any(h.relpath == rel for h in self._handles.values()):
                refuse("BadInvalidState", f"{rel} is open", argument=argument)


def _make_empty_file(path: Path) -> None:
    """An empty file at ``path``, durable; FileExistsError if there is one."""
    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
