"""Files written whole or not at all (a leaf module: it imports nothing of uacell)."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

# A file or directory changed more recently than this is read again rather than trusted to a cache
# keyed by its status: a change within the file system's timestamp resolution would not show.
SETTLE_NS = 2_000_000_000


def settled(st: os.stat_result) -> bool:
    """Did the entry last change (content or status) more than ``SETTLE_NS`` ago?"""
    return max(st.st_mtime_ns, st.st_ctime_ns) <= time.time_ns() - SETTLE_NS


def stamp(st: os.stat_result) -> tuple[int, int, int, int]:
    """What changes whenever a file is replaced or written: inode, size, modification and change times."""
    return (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def atomic_write(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Write ``data`` to ``path`` so readers see the old or the new file, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)  # make the rename itself durable
    finally:
        os.close(dir_fd)
