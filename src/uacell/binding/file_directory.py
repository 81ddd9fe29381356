"""The OPC UA side of a FileDirectoryType node over a ``FileStore`` (OPC 10000-20), for any companion.

``FileDirectoryBinding.create`` binds the directory node's CreateFile, CreateDirectory, Delete and
MoveOrCopy, and mirrors the store as nodes organized by the directory: a FileType node per file
(Size, Writable, UserWritable, OpenCount, MaxByteStringLength; Open, Close, Read, Write,
GetPosition, SetPosition) and a FileDirectoryType node per subdirectory. Entries appear and
disappear with the store's changes, through the ordered ``Publisher``.

NodeIds are derived from the path so that an entry keeps its NodeId while it exists:
``<directory id>/<relpath>/`` in the instantiator's namespace. The trailing ``/`` (a character no
file name contains) keeps entries apart from members, which the Instantiator names
``<entry id>.<BrowseName>``: a file ``a.Size`` can never collide with the Size of a file ``a``.

File handles belong to the calling session (``Caller.session_id``) and to the file they were opened
on; when a session closes, its handles are dropped and uncommitted writes discarded
(``session_closed``, which ``create`` hooks into ``app.security.on_session_closed``). UserWritable is
published as Writable; ``uacell.security.policy`` answers it per session role.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Hashable
from typing import TYPE_CHECKING, Any

from asyncua import ua
from asyncua.server.internal_session import InternalSession

from uacell.binding.space import address_space
from uacell.core.errors import CallError
from uacell.core.file_store import Change, Entry, FileStore
from uacell.core.registry import RegistryKey
from uacell.core.roles import Family
from uacell.ua import context, toolkit
from uacell.ua.context import Caller
from uacell.ua.instantiate import Selection
from uacell.ua.toolkit import ValueWriter

if TYPE_CHECKING:
    from uacell.host import BinderHost

log = logging.getLogger(__name__)

# Every bound directory, keyed by the browse path of its node ("Robot1.Controllers.Controller1.Programs").
FILE_DIRECTORIES: RegistryKey[FileDirectoryBinding] = RegistryKey("file directory")

FILE_TYPE = ua.NodeId(ua.ObjectIds.FileType)
FILE_DIRECTORY_TYPE = ua.NodeId(ua.ObjectIds.FileDirectoryType)
_FILE_MEMBERS = Selection(("MaxByteStringLength",))
_DIRECTORY_METHODS = ("CreateFile", "CreateDirectory", "Delete", "MoveOrCopy")
_FILE_METHODS = ("Open", "Close", "Read", "Write", "GetPosition", "SetPosition")
_HAS_TYPE_DEFINITION = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
_SAMPLES_SESSION = "uacell-samples"

# Variables kept current, with the VariantType of their DataType.
_VARIABLES = {
    "Size": ua.VariantType.UInt64,
    "Writable": ua.VariantType.Boolean,
    "UserWritable": ua.VariantType.Boolean,
    "OpenCount": ua.VariantType.UInt16,
    "MaxByteStringLength": ua.VariantType.UInt32,
}


class FileDirectoryBinding:
    """One FileDirectoryType node (and everything below it) bound to one ``FileStore``."""

    def __init__(
        self,
        app: BinderHost,
        directory_node: ua.NodeId,
        store: FileStore,
        family_dir: Family,
        family_file: Family,
    ) -> None:
        self.app = app
        self.node = directory_node
        self.store = store
        self.family_dir = family_dir
        self.family_file = family_file
        self._instantiator = app.cell.instantiator
        self._aspace = address_space(app.space)
        self._base = str(directory_node.Identifier)
        # relpath -> node and back, for the entries that exist in the address space
        self._nodes: dict[str, ua.NodeId] = {}
        self._paths: dict[ua.NodeId, str] = {directory_node: ""}
        self._is_dir: dict[str, bool] = {}
        self._variables: dict[str, dict[str, ua.NodeId]] = {}
        self._published: dict[str, Entry] = {}  # relpath -> the entry its variables were last published from
        self.values = ValueWriter(self._aspace, app.dispatcher.types.builtin_of)
        # handle -> (session, relpath) for handles opened through this binding
        self._handles: dict[int, tuple[Hashable, str]] = {}
        self._unhook: Callable[[], None] | None = None
        self._closed = False

    # ------------------------------------------------------------------ construction

    @classmethod
    async def create(
        cls,
        app: BinderHost,
        directory_node: ua.NodeId,
        store: FileStore,
        *,
        family_dir: Family = Family.DIRECTORY,
        family_file: Family = Family.FILE,
        samples: dict[str, bytes] | None = None,
        watch_sessions: bool = True,
    ) -> FileDirectoryBinding:
        """Bind ``directory_node`` (a FileDirectoryType instance with its methods) to ``store``.

        ``samples`` (file name -> content) are written when the store's directory is empty, i.e. on
        first start. ``watch_sessions`` closes a session's file handles when the session closes
        (needs ``app.security``). Register ``binding.close`` as the binder's closer.
        """
        self = cls(app, directory_node, store, family_dir, family_file)
        if samples and not store.entries():
            self._install_samples(samples)
        self._bind_directory(directory_node, "")
        for entry in store.entries():
            self._ensure_node(entry.relpath, entry.is_dir)
            if not entry.is_dir:
                await self._publish_values(entry.relpath, entry)
        store.listeners.append(self._on_change)
        if watch_sessions:
            self._watch_sessions()
        app.registry(FILE_DIRECTORIES).add(self._base, self)
        log.info("bound %s to %s (%d entries)", directory_node.to_string(), store.root, len(self._nodes))
        return self

    async def close(self) -> None:
        """Stop mirroring, drop every handle opened through this binding (uncommitted writes are lost)."""
        if self._closed:
            return
        self._closed = True
        if self._on_change in self.store.listeners:
            self.store.listeners.remove(self._on_change)
        if self._unhook is not None:
            self._unhook()
        for session in {s for s, _ in self._handles.values()}:
            self.store.close_session(session)
        self._handles.clear()

    def _install_samples(self, samples: dict[str, bytes]) -> None:
        for name, content in samples.items():
            try:
                relpath, handle = self.store.create_file(_SAMPLES_SESSION, "", name, True)
                assert handle is not None
                self.store.write(_SAMPLES_SESSION, handle, content)
                self.store.close(_SAMPLES_SESSION, handle)
                log.info("installed sample %s", relpath)
            except CallError as err:
                log.warning("cannot install sample %s: %s", name, err.message)
                self.store.close_session(_SAMPLES_SESSION)

    # ------------------------------------------------------------------ lookups

    def node_of(self, relpath: str) -> ua.NodeId:
        """The NodeId the entry at ``relpath`` has (or would have); "" is the directory node itself."""
        if relpath == "":
            return self.node
        return ua.NodeId(f"{self._base}/{relpath}/", self._instantiator.ns)

    def relpath_of(self, nodeid: ua.NodeId) -> str | None:
        """The relpath of the FileType node ``nodeid`` below this directory; None for anything else."""
        relpath = self._paths.get(nodeid)
        if relpath is None or relpath == "" or self._is_dir.get(relpath, True):
            return None
        return relpath

    def directory_of(self, nodeid: ua.NodeId) -> str | None:
        """The relpath of a FileDirectoryType node of this binding ("" for the directory itself)."""
        relpath = self._paths.get(nodeid)
        if relpath is None or (relpath != "" and not self._is_dir.get(relpath, False)):
            return None
        return relpath

    # ------------------------------------------------------------------ keeping the nodes current

    def refresh(self, relpath: str | None = None) -> None:
        """Republish a file's variables (all files if None), as the store has them now."""
        targets = [relpath] if relpath is not None else [p for p, d in self._is_dir.items() if not d]
        for p in targets:
            self._submit(p)

    def protection_changed(self, relpath: str) -> None:
        """The store's ``protect`` changed for ``relpath``: republish its Writable and UserWritable from
        what was published last (the disk did not change; a file not published yet is read)."""

        async def republish() -> None:
            entry = self._published.get(relpath)
            if entry is None:
                await self._apply(relpath)
            else:
                await self._publish_values(relpath, entry)

        self.app.publisher.submit(republish)

    def _watch_sessions(self) -> None:
        hooks = self.app.security.on_session_closed

        def closed(session: InternalSession) -> None:
            self.session_closed(context.caller_of(session).session_id)

        hooks.append(closed)
        self._unhook = lambda: hooks.remove(closed) if closed in hooks else None

    def session_closed(self, session_id: Hashable) -> int:
        """Drop the handles of a closed session; uncommitted writes are discarded. Returns how many."""
        for handle in [h for h, (s, _) in self._handles.items() if s == session_id]:
            del self._handles[handle]
        return self.store.close_session(session_id)

    def _on_change(self, change: Change) -> None:
        caller = context.current_caller()
        self.app.audit.record(
            "program_file",
            user=caller.display_user,
            session=caller.session_id,
            operation=change.kind,
            path=change.relpath,
            directory=change.is_dir,
            root=str(self.store.root),
        )
        self._submit(change.relpath)

    def _submit(self, relpath: str) -> None:
        self.app.publisher.submit(functools.partial(self._apply, relpath))

    async def _apply(self, relpath: str) -> None:
        """Make the address space match what the store has at ``relpath`` now."""
        if self._closed or relpath == "":
            return
        try:
            entry = self.store.entry(relpath)
        except CallError:
            entry = None
        if entry is None:
            self._remove_node(relpath)
            return
        if relpath in self._nodes and self._is_dir[relpath] != entry.is_dir:
            self._remove_node(relpath)  # replaced by an entry of the other kind
        self._ensure_node(relpath, entry.is_dir)
        if not entry.is_dir:
            await self._publish_values(relpath, entry)

    def _ensure_node(self, relpath: str, is_dir: bool) -> ua.NodeId:
        node = self._nodes.get(relpath)
        if node is not None:
            return node
        parent_rel, _, name = relpath.rpartition("/")
        parent = self._nodes.get(parent_rel) if parent_rel else self.node
        if parent is None:
            parent = self._ensure_node(parent_rel, True)
        node = self.node_of(relpath)
        self._instantiator.create(
            parent,
            FILE_DIRECTORY_TYPE if is_dir else FILE_TYPE,
            ua.QualifiedName(name, self._instantiator.ns),
            None if is_dir else _FILE_MEMBERS,
            reference_type=ua.ObjectIds.Organizes,
            path=str(node.Identifier),
        )
        self._nodes[relpath] = node
        self._paths[node] = relpath
        self._is_dir[relpath] = is_dir
        if is_dir:
            self._bind_directory(node, relpath)
        else:
            self._bind_file(node, relpath)
        log.debug("added node for %s", relpath)
        return node

    def _remove_node(self, relpath: str) -> None:
        node = self._nodes.get(relpath)
        if node is None:
            return
        doomed = self._subtree(node)
        for p in [p for p in self._nodes if p == relpath or p.startswith(relpath + "/")]:
            n = self._nodes.pop(p)
            self._paths.pop(n, None)
            self._is_dir.pop(p, None)
            self._variables.pop(p, None)
            self._published.pop(p, None)
        for n in doomed:
            self.app.dispatcher.unbind(n)
            self._instantiator.declarations.pop(n, None)
            self.values.forget(n)
        # Only the parent refers to the entry from outside its subtree; asyncua's own
        # DeleteTargetReferences would scan the whole address space once per node.
        parent_rel = relpath.rpartition("/")[0]
        parent = self._nodes.get(parent_rel) if parent_rel else self.node
        if parent is not None and parent in self._aspace:
            refs = self._aspace[parent].references
            refs[:] = [r for r in refs if r.NodeId != node]
        items = [ua.DeleteNodesItem(NodeId=n, DeleteTargetReferences=False) for n in doomed]
        self.app.space.delete_items(items)
        log.debug("removed %d node(s) for %s", len(doomed), relpath)

    def _subtree(self, node: ua.NodeId) -> list[ua.NodeId]:
        """``node`` and every node below it that this binding made (their ids share its prefix)."""
        prefix = str(node.Identifier)
        out, todo = [node], [node]
        while todo:
            for ref in self._aspace[todo.pop()].references:
                target = ref.NodeId
                if (
                    ref.IsForward
                    and ref.ReferenceTypeId != _HAS_TYPE_DEFINITION
                    and target.NamespaceIndex == node.NamespaceIndex
                    and isinstance(target.Identifier, str)
                    and target.Identifier.startswith(prefix)
                    and target not in out
                    and target in self._aspace
                ):
                    out.append(target)
                    todo.append(target)
        return out

    async def _publish_values(self, relpath: str, entry: Entry | None = None) -> None:
        """Size, Writable, OpenCount ... of the file at ``relpath`` (``entry``: the store's, if just read)."""
        if relpath not in self._nodes:
            return
        if entry is None:
            try:
                entry = self.store.entry(relpath)
            except CallError:
                return
        self._published[relpath] = entry
        writable = entry.writable and not (self.store.protect is not None and self.store.protect(relpath))
        values = {
            "Size": entry.size,
            "Writable": writable,
            # uacell.security.policy answers it per session: False for roles that may not write files.
            "UserWritable": writable,
            "OpenCount": min(self.store.open_count(relpath), 0xFFFF),
            "MaxByteStringLength": self.store.max_read,
        }
        for name, nodeid in self._variables.get(relpath, {}).items():
            await self.values.write(nodeid, values[name], _VARIABLES[name])

    # ------------------------------------------------------------------ method binding

    def _bind_directory(self, node: ua.NodeId, dir_relpath: str) -> None:
        d = self.app.dispatcher
        handlers = {
            "CreateFile": functools.partial(self._create_file, dir_relpath),
            "CreateDirectory": functools.partial(self._create_directory, dir_relpath),
            "Delete": functools.partial(self._delete, dir_relpath),
            "MoveOrCopy": functools.partial(self._move_or_copy, dir_relpath),
        }
        for name in _DIRECTORY_METHODS:
            d.bind(node, d.method_of(node, name), self.family_dir, handlers[name], serialize_on=self.store)

    def _bind_file(self, node: ua.NodeId, relpath: str) -> None:
        d = self.app.dispatcher
        handlers = {
            "Open": functools.partial(self._open, relpath),
            "Close": functools.partial(self._close, relpath),
            "Read": functools.partial(self._read, relpath),
            "Write": functools.partial(self._write, relpath),
            "GetPosition": functools.partial(self._get_position, relpath),
            "SetPosition": functools.partial(self._set_position, relpath),
        }
        for name in _FILE_METHODS:
            d.bind(
                node,
                d.method_of(node, name),
                self.family_file,
                handlers[name],
                serialize_on=self.store,
                # Open's only input is the mode: the dispatcher checks the role against it.
                file_mode_argument=0 if name == "Open" else None,
            )
        found = {name: toolkit.find_child(self._aspace, node, name) for name in _VARIABLES}
        self._variables[relpath] = {name: n for name, n in found.items() if n is not None}

    # --- FileType

    def _mine(self, caller: Caller, relpath: str, handle: int) -> None:
        """A handle is valid only for the session that opened it and on the file it was opened on."""
        if self._handles.get(handle) != (caller.session_id, relpath):
            raise CallError("BadInvalidArgument", f"invalid file handle {handle!r} for {relpath}", argument=0)

    async def _open(self, relpath: str, caller: Caller, mode: int) -> list[Any]:
        handle = self.store.open(caller.session_id, relpath, mode)
        self._handles[handle] = (caller.session_id, relpath)
        return [handle]

    async def _close(self, relpath: str, caller: Caller, handle: int) -> list[Any]:
        self._mine(caller, relpath, handle)
        try:
            self.store.close(caller.session_id, handle)
        finally:
            del self._handles[handle]  # the store ends the handle even when committing fails
        return []

    async def _read(self, relpath: str, caller: Caller, handle: int, length: int) -> list[Any]:
        self._mine(caller, relpath, handle)
        return [self.store.read(caller.session_id, handle, length)]

    async def _write(self, relpath: str, caller: Caller, handle: int, data: bytes | None) -> list[Any]:
        self._mine(caller, relpath, handle)
        self.store.write(caller.session_id, handle, data or b"")
        return []

    async def _get_position(self, relpath: str, caller: Caller, handle: int) -> list[Any]:
        self._mine(caller, relpath, handle)
        return [self.store.get_position(caller.session_id, handle)]

    async def _set_position(self, relpath: str, caller: Caller, handle: int, position: int) -> list[Any]:
        self._mine(caller, relpath, handle)
        self.store.set_position(caller.session_id, handle, position)
        return []

    # --- FileDirectoryType

    async def _create_file(self, dir_relpath: str, caller: Caller, name: str, request_open: bool) -> list[Any]:
        relpath, handle = self.store.create_file(caller.session_id, dir_relpath, name, bool(request_open))
        if handle is not None:
            self._handles[handle] = (caller.session_id, relpath)
        return [self.node_of(relpath), handle or 0]

    async def _create_directory(self, dir_relpath: str, caller: Caller, name: str) -> list[Any]:
        return [self.node_of(self.store.create_directory(dir_relpath, name))]

    async def _delete(self, dir_relpath: str, caller: Caller, target: ua.NodeId) -> list[Any]:
        self.store.delete(self._child(dir_relpath, target, argument=0))
        return []

    async def _move_or_copy(
        self,
        dir_relpath: str,
        caller: Caller,
        source: ua.NodeId,
        target_dir: ua.NodeId,
        copy: bool,
        new_name: str | None,
    ) -> list[Any]:
        src = self._child(dir_relpath, source, argument=0)
        target = self.directory_of(target_dir)
        if target is None:
            raise CallError("BadNotFound", f"{target_dir.to_string()} is not a directory here", argument=1)
        return [self.node_of(self.store.move_or_copy(src, target, bool(copy), new_name or None))]

    def _child(self, dir_relpath: str, nodeid: ua.NodeId, argument: int) -> str:
        """The relpath of a file or directory organized by the directory at ``dir_relpath``."""
        relpath = self._paths.get(nodeid)
        if not relpath or relpath.rpartition("/")[0] != dir_relpath:
            raise CallError("BadNotFound", f"{nodeid.to_string()} is not in this directory", argument=argument)
        return relpath
