"""A robot controller's program files, through a web user's own OPC UA session: listed per FileDirectoryType
the HMI's discovery found, read, written and deleted with the FileType and FileDirectoryType methods
(OPC 10000-5 C), so that the server's roles and limits apply."""

from __future__ import annotations

import contextlib
import logging
from typing import Any, Protocol

from asyncua import Client, Node, ua

from uacell.binding.web_discovery import Cell
from uacell.web.discovery import list_files
from uacell.web.errors import CallFailed, UnknownKey

log = logging.getLogger(__name__)
_FILE_CHUNK = 60000


class Owner(Protocol):
    """The session whose files these are (``uacell.web.uasession.UaSession``)."""

    client: Client | None
    cell: Cell
    files: dict[str, list[dict[str, Any]]]
    user: str | None

    def emit(self, message: dict[str, Any]) -> None: ...

    def require(self) -> Client: ...


class ProgramFiles:
    def __init__(self, session: Owner) -> None:
        self.session = session

    async def refresh(self) -> None:
        client = self.session.client
        if client is None:
            return
        for key, directory in self.session.cell.directories.items():
            files = await list_files(client, directory)
            viewable = await self._may_read(client, files[0]["node"]) if files else True
            self.session.files[key] = [{"name": f["name"], "path": f["path"], "viewable": viewable} for f in files]
        self.session.emit({"type": "files", "files": self.session.files})

    async def _may_read(self, client: Client, file_node: ua.NodeId) -> bool:
        """Whether this user may read the directory's files: the server's UserExecutable of FileType's
        Read (every file of a directory is read under the same role)."""
        try:
            read = await Node(client.uaclient, file_node).get_child("0:Read")
            value = await read.read_attribute(ua.AttributeIds.UserExecutable)
            return bool(value.Value.Value)
        except Exception:  # no answer: let the server decide when the user tries
            return True

    async def _file_method(self, file_node: ua.NodeId, name: str, *inputs: ua.Variant) -> list[Any]:
        client = self.session.require()
        method = next(
            (
                r.NodeId
                for r in await Node(client.uaclient, file_node).get_children_descriptions()
                if r.BrowseName.Name == name
            ),
            None,
        )
        if method is None:
            raise CallFailed(ua.StatusCodes.BadMethodInvalid, name)
        request = ua.CallMethodRequest(ObjectId=file_node, MethodId=method, InputArguments=list(inputs))
        (result,) = await client.uaclient.call([request])
        if not result.StatusCode.is_good():
            raise CallFailed(result.StatusCode.value, name)
        return [v.Value for v in result.OutputArguments or []]

    async def _find_file(self, directory: str, path: str) -> ua.NodeId | None:
        client = self.session.require()
        node = self.session.cell.directories.get(directory)
        if node is None:
            raise UnknownKey(directory)
        return next((f["node"] for f in await list_files(client, node) if f["path"] == path), None)

    async def read(self, directory: str, path: str) -> str:
        node = await self._find_file(directory, path)
        if node is None:
            raise CallFailed(ua.StatusCodes.BadNotFound, path)
        (handle,) = await self._file_method(node, "Open", ua.Variant(1, ua.VariantType.Byte))
        h = ua.Variant(handle, ua.VariantType.UInt32)
        data = b""
        try:
            while True:
                (chunk,) = await self._file_method(node, "Read", h, ua.Variant(_FILE_CHUNK, ua.VariantType.Int32))
                if not chunk:
                    break
                data += chunk
        finally:
            with contextlib.suppress(CallFailed):
                await self._file_method(node, "Close", h)
        return data.decode("utf-8", errors="replace")

    async def write(self, directory: str, name: str, content: bytes) -> None:
        """Create ``name`` in the directory (or replace its content) through FileType methods."""
        node = await self._find_file(directory, name)
        if node is None:
            dir_node = self.session.cell.directories[directory]
            node, handle = await self._file_method(
                dir_node,
                "CreateFile",
                ua.Variant(name, ua.VariantType.String),
                ua.Variant(True, ua.VariantType.Boolean),
            )
        else:
            (handle,) = await self._file_method(node, "Open", ua.Variant(2 | 4, ua.VariantType.Byte))
        h = ua.Variant(handle, ua.VariantType.UInt32)
        try:
            for start in range(0, len(content), _FILE_CHUNK):
                chunk = content[start : start + _FILE_CHUNK]
                await self._file_method(node, "Write", h, ua.Variant(chunk, ua.VariantType.ByteString))
        finally:
            with contextlib.suppress(CallFailed):
                await self._file_method(node, "Close", h)
        log.info("%s wrote program file %s", self.session.user or "anonymous", name)
        await self.refresh()

    async def delete(self, directory: str, path: str) -> None:
        node = await self._find_file(directory, path)
        if node is None:
            raise CallFailed(ua.StatusCodes.BadNotFound, path)
        await self._file_method(
            self.session.cell.directories[directory], "Delete", ua.Variant(node, ua.VariantType.NodeId)
        )
        log.info("%s deleted program file %s", self.session.user or "anonymous", path)
        await self.refresh()
