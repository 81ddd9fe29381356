"""``Controller/Programs``: the program files, their protection while loaded, and client NodeIds."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import Any

from asyncua import ua

from uacell.binding.file_directory import FileDirectoryBinding
from uacell.core.capabilities import has
from uacell.core.errors import CallError
from uacell.core.file_store import FileStore
from uacell.robotics.binding.shared import ControllerBinding
from uacell.robotics.equipment import AxisInfo, ProgramCatalogue
from uacell.robotics.program import AXIS_COUNT, samples, wave_program
from uacell.robotics.program_cache import PROGRAM_SUFFIX, DirectoryLibrary

log = logging.getLogger(__name__)
_A = ua.AttributeIds


def install_samples(root: Path, axes: Sequence[AxisInfo] = (), *, moves: bool = True) -> bool:
    """Write sample programs into ``root`` if it does not exist yet (first start).

    A six-axis arm gets the shipped samples (docs/programs.md); an arm with another number of axes a
    generated ``Wave`` program that moves each axis within its limits; a controller that moves no
    motion device (``moves`` false) a program without ``move``.
    """
    if root.exists():
        return False
    root.mkdir(parents=True)
    if not moves:
        files = {"idle.robot": IDLE_PROGRAM}
    elif len(axes) in (0, AXIS_COUNT):
        files = samples()
    else:
        files = {"wave.robot": wave_program(axes)}
    for name, text in files.items():
        (root / name).write_text(text, encoding="utf-8")
    log.info("installed %d sample programs in %s", len(files), root)
    return True


IDLE_PROGRAM = """\
# Idle: this controller moves no motion device, so its programs may wait, repeat and call, not move.
program Idle version 1.0
repeat 3
  wait 1
end
"""


def adopt_legacy_programs(programs_dir: Path, root: Path, keep: Sequence[str]) -> int:
    """Move the files of the single-controller layout (``programs/*``) into ``root``; return how many.

    Before cells were configurable, the one controller's files lived directly in ``programs/``. On
    the first start of a newer uacell they become that controller's (``programs/<robot>/<controller>``),
    so nothing a user stored is lost. ``keep`` are the robots' directory names, never moved.
    """
    if root.exists() or not programs_dir.is_dir():
        return 0
    legacy = [e for e in sorted(programs_dir.iterdir()) if e.name not in keep]
    if not any(e.is_file() and e.suffix == PROGRAM_SUFFIX for e in legacy):
        return 0
    root.mkdir(parents=True)
    for entry in legacy:
        entry.rename(root / entry.name)
    log.warning("moved %d entries of the old programs/ layout to %s", len(legacy), root)
    return len(legacy)


class StoreLibrary(DirectoryLibrary):
    """The ProgramLibrary over a FileStore: the store's listing hides its temporary files. Names are
    looked up in an index of the store's listing, made again when the listing changed."""

    def __init__(self, store: FileStore) -> None:
        super().__init__(store.root)
        self.store = store
        self._listed: list[str] = []
        self._index: dict[str, str] = {}  # name -> relpath

    def _files(self) -> list[Path]:
        return sorted(self.root / relpath for relpath in self.store.files(PROGRAM_SUFFIX))

    def resolve(self, name: str) -> str | None:
        listed = self.store.files(PROGRAM_SUFFIX)
        if listed != self._listed:
            index: dict[str, str] = {}
            # In the order of DirectoryLibrary's sorted paths: the same file wins a name held twice.
            for relpath in sorted(listed, key=lambda r: r.split("/")):
                index.setdefault(PurePosixPath(relpath).stem, relpath)
            self._listed, self._index = listed, index
        return self._index.get(name)


class Programs:
    """The Programs directory of one controller, and the NodeIds clients name files and modules by."""

    def __init__(self, binding: ControllerBinding) -> None:
        self.binding = binding
        self.directory: FileDirectoryBinding | None = None
        self._protected: set[str] = set()
        self.controller_programs: dict[str, ua.NodeId] = {}  # the controller's own, by name

    async def setup(self) -> None:
        b = self.binding
        b.store.protect = self.protect
        node = b.child(b.controller.node, "Programs")
        self.directory = await FileDirectoryBinding.create(b.app, node, b.store)
        await self._sync_catalogue()

    async def _sync_catalogue(self) -> None:
        """One object per program the controller holds (a ``ProgramCatalogue``), organized by Programs
        beside its files, named as LoadByName takes it: ``Programs/<name>`` (BaseObjectType, its
        Description says it is the controller's). LoadByNodeId takes its NodeId."""
        b = self.binding
        equipment = b.cell.equipment
        if not has(equipment, ProgramCatalogue):
            return
        names = list(equipment.program_names())
        if names == list(self.controller_programs):
            return
        folder = b.child(b.controller.node, "Programs")
        for gone in [n for n in self.controller_programs if n not in names]:
            node = self.controller_programs.pop(gone)
            await b.app.space.delete([node])
            b.forget_children()
        for name in names:
            if name not in self.controller_programs:
                node = b.app.cell.instantiator.create(
                    folder, ua.NodeId(ua.ObjectIds.BaseObjectType), ua.QualifiedName(name, b.ns),
                    reference_type=ua.ObjectIds.Organizes, path=f"{b.controller.path}.Programs.{name}",
                )  # fmt: skip
                text = ua.LocalizedText(f"uacell: the controller's program {name} (held by the controller, no file)")
                await b.app.space.write(node, _A.Description, ua.Variant(text))
                self.controller_programs[name] = node

    def controller_program_of(self, id_: Any) -> str | None:
        """The name of the controller's program whose object ``id_`` is, or None."""
        nodeid = self.local_nodeid(id_)
        return next((n for n, node in self.controller_programs.items() if node == nodeid), None)

    async def publish(self) -> None:
        await self._sync_catalogue()
        protected = self.protected_files()
        if protected != self._protected and self.directory is not None:
            # Writable/UserWritable of the files that became (un)protected.
            for relpath in protected ^ self._protected:
                self.directory.protection_changed(relpath)
        self._protected = protected

    async def close(self) -> None:
        if self.directory is not None:
            await self.directory.close()

    # --- protection -------------------------------------------------------------------------------
    def protected_files(self) -> set[str]:
        files: set[str] = set()
        for task in self.binding.cell.tasks.values():
            if task.program_file is not None:
                files.add(task.program_file)
            files.update(m.relpath for m in task.modules if m.relpath is not None)
        return files

    def protect(self, relpath: str) -> bool:
        """The loaded programs and modules cannot be deleted, moved or overwritten."""
        return relpath in self.protected_files()

    # --- NodeIds given by clients (docs/decisions.md 10) -------------------------------------------
    def local_nodeid(self, id_: Any) -> ua.NodeId:
        """The local NodeId an ExpandedNodeId names; Bad_NodeIdInvalid if null, remote or of an unknown URI."""
        if id_ is None or not isinstance(id_, ua.NodeId):
            raise CallError("BadNodeIdInvalid", "Id is null", argument=0)
        server_index = getattr(id_, "ServerIndex", 0) or 0
        if server_index != 0:
            raise CallError("BadNodeIdInvalid", f"Id names server {server_index}", argument=0)
        index = id_.NamespaceIndex
        uri = getattr(id_, "NamespaceUri", None)
        if uri:
            array = self.binding.app.space.attribute(ua.NodeId(ua.ObjectIds.Server_NamespaceArray))
            if uri not in array:
                raise CallError("BadNodeIdInvalid", f"unknown namespace {uri}", argument=0)
            index = array.index(uri)
        nodeid = ua.NodeId(id_.Identifier, index, id_.NodeIdType)
        if nodeid.is_null():
            raise CallError("BadNodeIdInvalid", "Id is null", argument=0)
        return nodeid

    def file_of(self, id_: Any) -> str:
        """The relpath in Programs of the FileType node ``id_``; Bad_NodeIdUnknown if it is none."""
        nodeid = self.local_nodeid(id_)
        # None for directories and anything outside Programs
        relpath = self.directory.relpath_of(nodeid) if self.directory is not None else None
        if relpath is None:
            raise CallError("BadNodeIdUnknown", f"{nodeid.to_string()} is not a file in Programs", argument=0)
        return relpath
