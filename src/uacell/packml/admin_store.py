"""Durable PackML Admin data: one JSON file, replaced atomically (decision 28).

A save writes a temporary file next to the target, fsyncs it, renames it over the target with
``os.replace`` and fsyncs the directory, so at every instant the target is either the previous
complete file or the new complete file: a crash mid-write loses nothing already stored.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

FORMAT_VERSION = 1


class AdminStore:
    """Load and save one unit's Admin data as JSON at ``path``."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    def load(self) -> dict[str, Any] | None:
        """The stored data, or None (with a logged warning) if the file is absent or unreadable."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            log.warning("no PackML admin data at %s yet; starting from defaults", self.path)
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

    def save(self, data: dict[str, Any]) -> None:
        """Store ``data`` atomically and durably."""
        directory = self.path.parent
        directory.mkdir(parents=True, exist_ok=True)
        payload = json.dumps({**data, "version": FORMAT_VERSION}, indent=1, sort_keys=True)
        fd, tmp_name = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp", dir=directory)
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
        _fsync_dir(directory)


def _fsync_dir(directory: Path) -> None:
    # Makes the rename itself durable; not possible (nor needed) on Windows.
    if os.name != "posix":
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
