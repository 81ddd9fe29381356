"""A DataSet's ConfigurationVersion (OPC 10000-14 v1.05 §6.2.3.2.6): two VersionTimes (OPC 10000-4 §7.43,
seconds since 2000-01-01 UTC). MajorVersion changes when fields are removed, reordered, inserted or
change type; MinorVersion alone when fields are only added at the end; both stay while the fields do.
The last versions are kept in ``<data_dir>/pubsub-versions.json`` so that a restart with the same
cell keeps them (the pure rule is ``next_version``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)
EPOCH = datetime(2000, 1, 1, tzinfo=UTC)
FILE_NAME = "pubsub-versions.json"


@dataclass(frozen=True)
class Version:
    major: int
    minor: int

    def json(self) -> dict[str, int]:
        return {"MajorVersion": self.major, "MinorVersion": self.minor}


def version_time(t: datetime) -> int:
    """VersionTime: whole seconds since 2000-01-01T00:00:00Z, a UInt32."""
    return int((t.astimezone(UTC) - EPOCH).total_seconds()) & 0xFFFFFFFF


def next_version(previous: dict[str, Any] | None, shape: list[Any], now: int) -> Version:
    """The version of a DataSet with fields ``shape`` (one entry per field, in order), given the last
    recorded ``{"shape", "major", "minor"}``; a new VersionTime is later than the last one."""
    if previous is None:
        return Version(now, now)
    old_shape, major, minor = previous.get("shape"), int(previous.get("major", 0)), int(previous.get("minor", 0))
    if old_shape == shape:
        return Version(major, minor)
    later = max(now, minor + 1)
    if isinstance(old_shape, list) and shape[: len(old_shape)] == old_shape:
        return Version(major, later)  # only added at the end: a minor change
    return Version(later, later)


class VersionStore:
    """The recorded versions per DataSetWriter name; without a directory nothing is kept."""

    def __init__(self, directory: Path | None) -> None:
        self.path = directory / FILE_NAME if directory is not None else None
        self.records: dict[str, Any] = {}
        if self.path is not None and self.path.exists():
            try:
                loaded = json.loads(self.path.read_text())
                self.records = loaded if isinstance(loaded, dict) else {}
            except (OSError, ValueError) as exc:
                log.warning("pubsub: %s unreadable (%s); DataSet versions start anew", self.path, exc)

    def version(self, name: str, shape: list[Any], now: datetime) -> Version:
        version = next_version(self.records.get(name), shape, version_time(now))
        self.records[name] = {"shape": shape, "major": version.major, "minor": version.minor}
        return version

    def save(self) -> None:
        if self.path is None:
            return
        tmp = self.path.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps(self.records, indent=1))
            os.replace(tmp, self.path)
        except OSError as exc:
            log.warning("pubsub: cannot keep the DataSet versions in %s: %s", self.path, exc)
            with contextlib.suppress(OSError):
                tmp.unlink()
