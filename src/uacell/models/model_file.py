"""One official NodeSet2 file a companion needs (a leaf: companions declare theirs with it)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ModelFile:
    """An official NodeSet2 file: its model key, namespace, file name, digest, where the npm package
    holds it, and the keys of the models it requires (loaded before it)."""

    key: str
    namespace_uri: str
    filename: str
    sha256: str
    package_path: str
    requires: tuple[str, ...] = ()
