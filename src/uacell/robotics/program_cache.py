"""The program files of a controller and the cache of their texts: the wrapper a binder composes and
hands to the pure model (``uacell.robotics.model``) as its ``ProgramLibrary``.

The model reads no file; this module does, and keeps the text of a small file while the file is
unchanged (``uacell.core.files.stamp``), so that loading the same program again costs one ``stat``.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

from uacell.core.files import settled, stamp
from uacell.robotics.loading import INLINE_PROGRAM_BYTES, KEPT_TEXTS
from uacell.robotics.program import DEFAULT_LIMITS, ProgramTooLarge

PROGRAM_SUFFIX = ".robot"


class DirectoryLibrary:
    """Programs stored as ``*.robot`` files in a directory tree; a file's name is its stem.

    ``read`` reads at most ``max_bytes`` (``ProgramTooLarge`` beyond) and decodes UTF-8 strictly.
    """

    def __init__(self, root: Path | str, *, max_bytes: int = DEFAULT_LIMITS.max_file_bytes) -> None:
        self.root = Path(root)
        self.max_bytes = max_bytes
        self._texts: dict[str, tuple[tuple[int, int, int, int], str]] = {}  # relpath -> (stamp, text)

    def _files(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return sorted(p for p in self.root.rglob(f"*{PROGRAM_SUFFIX}") if p.is_file())

    def names(self) -> list[str]:
        return sorted({p.stem for p in self._files()})

    def resolve(self, name: str) -> str | None:
        # Sorted paths make the choice stable when two subdirectories hold the same name.
        for p in self._files():
            if p.stem == name:
                return p.relative_to(self.root).as_posix()
        return None

    def _path(self, relpath: str) -> str:
        rel = PurePosixPath(relpath)
        if rel.is_absolute() or ".." in rel.parts:
            raise FileNotFoundError(relpath)
        return os.path.join(self.root, relpath)

    def read_small(self, relpath: str) -> str | None:
        """``read`` for a file of at most INLINE_PROGRAM_BYTES; None for a larger one, or one whose
        size cannot be known (``read`` then says why)."""
        return self._read(relpath, small=True)

    def read(self, relpath: str) -> str:
        """The file's text. A small file's text is kept while its status (inode, size, times) is what it
        was when read, and it had not changed for two seconds then (``files.settled``): loading the
        same program again costs one ``stat``, not a read and a decode."""
        text = self._read(relpath, small=False)
        assert text is not None
        return text

    def _read(self, relpath: str, small: bool) -> str | None:
        path = self._path(relpath)
        try:
            st: os.stat_result | None = os.stat(path)
        except OSError:
            st = None  # open says why
        if small and (st is None or st.st_size > INLINE_PROGRAM_BYTES):
            return None
        kept = self._texts.get(relpath)
        if kept is not None and st is not None and kept[0] == stamp(st):
            return kept[1]
        with open(path, "rb") as f:
            data = f.read(self.max_bytes + 1)
        if len(data) > self.max_bytes:
            raise ProgramTooLarge(0, f"the file is larger than {self.max_bytes} bytes")
        text = data.decode("utf-8")
        self._texts.pop(relpath, None)
        if st is not None and st.st_size == len(data) <= INLINE_PROGRAM_BYTES and settled(st):
            if len(self._texts) >= KEPT_TEXTS:
                self._texts.pop(next(iter(self._texts)), None)  # the oldest
            self._texts[relpath] = (stamp(st), text)
        return text
