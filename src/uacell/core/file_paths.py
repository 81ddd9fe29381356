"""The paths of a ``FileStore`` (uacell.core.file_store): names it accepts, entries resolved below its
root without leaving it (no '..', no symlinks), listings that hide its temporaries, and copies and
clean-ups that are complete or not at all. Pure: no OPC UA."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NoReturn

from uacell.core.errors import CallError

logger = logging.getLogger(__name__)

# OpenFileMode bits (OPC 10000-20 4.2.2); bits 4..7 are reserved and must be zero.
MODE_READ = 1
MODE_WRITE = 2
MODE_ERASE_EXISTING = 4
MODE_APPEND = 8

#: Prefix of the store's own temporary files and directories: hidden, refused as a name, removed on start.
TEMP_PREFIX = ".uacell-tmp-"

MAX_NAME_BYTES = 255  # NAME_MAX on the file systems uacell runs on
#: What each file or directory costs on top of its content, for ``max_bytes``: many empty files fill it too.
ENTRY_BYTES = 512


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


def refuse(status: str, message: str, argument: int | None = None, argument_status: str | None = None) -> NoReturn:
    logger.debug("file store refuses: %s (%s)", status, message)
    raise CallError(status, message, argument=argument, argument_status=argument_status)


def fsync_dir(path: Path) -> None:
    """Make a rename/create/unlink in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove(path: Path) -> None:
    """Remove a file or directory tree; missing is fine (used on clean-up paths)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def copy_synced(src: str | Path, dst: str | Path) -> None:
    shutil.copy2(src, dst)
    fd = os.open(dst, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class StorePaths:
    """Paths below ``root`` (a part of ``FileStore``)."""

    root: Path
    _root_text: str

    @staticmethod
    def _check_name(name: object, argument: int | None) -> None:
        """A single path component that the store may create (no separators, no '..', not ours)."""
        ok = (
            isinstance(name, str)
            and name not in ("", ".", "..")
            and not any(c in name for c in "/\\\0")
            and not name.startswith(TEMP_PREFIX)
            and len(name.encode("utf-8", "surrogateescape")) <= MAX_NAME_BYTES
        )
        if not ok:
            refuse(
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
            refuse("BadInvalidArgument", f"invalid path {relpath!r}", argument=argument)
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
                    refuse("BadNotFound", f"{relpath} not found", argument=argument)
                # Symlinks are neither listed nor followed: they could lead out of the root.
                if stat.S_ISLNK(mode):
                    refuse("BadNotFound", f"{relpath} not found", argument=argument)
        if mode is None:
            refuse("BadNotFound", f"{relpath} not found", argument=argument)
        if want_dir is not None and stat.S_ISDIR(mode) != want_dir:
            refuse("BadNotFound", f"{relpath} is not a {'directory' if want_dir else 'file'}", argument=argument)
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

    def _copy(self, src: Path, dest: Path) -> None:
        """Copy a file or tree so that ``dest`` appears complete or not at all."""
        temp = Path(tempfile.mkdtemp(prefix=TEMP_PREFIX, dir=dest.parent))
        try:
            staged = temp / "c"
            if src.is_dir():
                shutil.copytree(src, staged, ignore=self._not_copied, copy_function=copy_synced)
                for dirpath, _dirs, _files in os.walk(staged):
                    fsync_dir(Path(dirpath))
            else:
                copy_synced(src, staged)
            os.rename(staged, dest)
            fsync_dir(dest.parent)
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
            remove(path)
        if found:
            logger.warning("removed %d leftover temporary file(s) under %s", len(found), self.root)
