"""What a web session keeps reading again while it is connected: ``UserExecutable`` of every method
whenever an ``Executable`` changes (what the page enables is what the server says this user may do
now), and the TaskModules folders whenever a loaded program may have changed. One read at a time
each; a request while one runs is kept, so no change is missed."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any, Protocol

from asyncua import Client, Node, ua

from uacell.binding.web_discovery import Cell

log = logging.getLogger(__name__)


class Reading(Protocol):
    """The session a ``Refresher`` reads for (``uacell.web.uasession.UaSession``)."""

    client: Client | None
    cell: Cell
    methods: dict[str, dict[str, bool]]
    modules: dict[str, list[str]]

    def emit(self, message: dict[str, Any]) -> None: ...


class Refresher:
    def __init__(self, session: Reading) -> None:
        self.session = session
        self._methods_task: asyncio.Task[None] | None = None
        self._methods_again = False
        self._modules_task: asyncio.Task[None] | None = None
        self._modules_again = False

    def cancel(self) -> None:
        for task in (self._methods_task, self._modules_task):
            if task is not None and not task.done():
                task.cancel()

    def executable_changed(self) -> None:
        if self._methods_task is not None and not self._methods_task.done():
            self._methods_again = True
            return
        self._methods_task = asyncio.get_running_loop().create_task(self._methods_loop())

    async def _methods_loop(self) -> None:
        while True:
            self._methods_again = False
            try:
                await self.refresh_methods()
            except Exception as exc:
                log.debug("reading UserExecutable failed: %s", exc)
            if not self._methods_again:
                return

    async def refresh_methods(self) -> None:
        """Read Executable and UserExecutable of every method in this session (its role's answer)."""
        client = self.session.client
        if client is None or not self.session.cell.methods:
            return
        keys = list(self.session.cell.methods)
        params = ua.ReadParameters()
        for key in keys:
            for attr in (ua.AttributeIds.Executable, ua.AttributeIds.UserExecutable):
                params.NodesToRead.append(
                    ua.ReadValueId(NodeId=self.session.cell.methods[key].method, AttributeId=attr)
                )
        results = await client.uaclient.read(params)
        state = {}
        for i, key in enumerate(keys):
            x, u = results[2 * i], results[2 * i + 1]
            state[key] = {
                "executable": bool(x.Value and x.Value.Value),
                "user_executable": bool(u.Value and u.Value.Value),
            }
        changed = {k: v for k, v in state.items() if self.session.methods.get(k) != v}
        self.session.methods.update(state)
        if changed:
            self.session.emit({"type": "methods", "methods": changed})

    def schedule_modules(self) -> None:
        """Browse the TaskModules folders again soon; a request while a browse runs is kept, so a
        module loaded meanwhile is never missed."""
        if not self.session.cell.folders:
            return
        if self._modules_task is not None and not self._modules_task.done():
            self._modules_again = True
            return
        self._modules_task = asyncio.get_running_loop().create_task(self._modules_loop())

    async def _modules_loop(self) -> None:
        while True:
            self._modules_again = False
            await self.refresh_modules()
            if not self._modules_again:
                return

    async def refresh_modules(self) -> None:
        client = self.session.client
        if client is None:
            return
        with contextlib.suppress(Exception):
            for key, folder in self.session.cell.folders.items():
                refs = await Node(client.uaclient, folder).get_children_descriptions()
                self.session.modules[key] = sorted(r.BrowseName.Name for r in refs)
            self.session.emit({"type": "modules", "modules": self.session.modules})
