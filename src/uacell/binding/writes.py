"""Client writes: who may write which node, and nodes whose writes are behaviour.

By default writing needs the ``write`` action of ``uacell.core.roles`` (engineer). A binding can route a
node: its writes then need the role it names and go to its hook, which applies them through the
model and answers the status code (asyncua itself cannot refuse a write per node). Guards (the DI
lock guard of ``uacell.di.locks``) may refuse any item a role allows, with the status code they name.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable

from asyncua import ua

from uacell.core.roles import ACTION_ROLES, Role
from uacell.ua import attributes
from uacell.ua.context import Caller

log = logging.getLogger(__name__)

WriteHook = Callable[[ua.DataValue, Caller], Awaitable[ua.StatusCode]]
# A guard answers a status code to refuse the item, or None to let it through.
WriteGuard = Callable[[Caller, ua.WriteValue], ua.StatusCode | None]
# Told of every answered write item (audit trail): caller, the item, its result.
WriteObserver = Callable[[Caller, ua.WriteValue, ua.StatusCode], None]
_A = ua.AttributeIds


class WriteRouter:
    def __init__(self) -> None:
        self._routes: dict[ua.NodeId, tuple[Role, WriteHook]] = {}
        self.guards: list[WriteGuard] = []
        self.observers: list[WriteObserver] = []

    def route(self, node: ua.NodeId, hook: WriteHook, role: Role = ACTION_ROLES["write"]) -> None:
        """Send client writes of ``node``'s Value to ``hook``; callers need at least ``role``."""
        self._routes[node] = (role, hook)

    def required_role(self, node: ua.NodeId) -> Role:
        route = self._routes.get(node)
        return route[0] if route else ACTION_ROLES["write"]

    async def write(
        self,
        caller: Caller,
        params: ua.WriteParameters,
        write_through: Callable[[ua.WriteParameters], Awaitable[list[ua.StatusCode]]],
    ) -> list[ua.StatusCode]:
        """Answer each item: refused, by a hook, or by ``write_through`` (asyncua's own write)."""
        role = Role.parse(caller.role)
        items = list(params.NodesToWrite or [])
        results: list[ua.StatusCode | None] = [None] * len(items)
        rest: list[int] = []
        for i, item in enumerate(items):
            if role < self.required_role(item.NodeId):
                log.info("write of %s refused for %s (%s)", item.NodeId.to_string(), caller.display_user, role.label)
                results[i] = ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
                continue
            form = attributes.write_refusal(item)  # before a guard or a route sees it (decision 81)
            if form is not None:
                results[i] = ua.StatusCode(form)
                continue
            refusal = next((r for r in (guard(caller, item) for guard in self.guards) if r is not None), None)
            if refusal is not None:
                results[i] = refusal
                continue
            route = self._routes.get(item.NodeId)
            if route is None or item.AttributeId != _A.Value:
                rest.append(i)
                continue
            try:
                results[i] = await route[1](item.Value, caller)
            except Exception:
                log.exception("write hook for %s failed", item.NodeId.to_string())
                results[i] = ua.StatusCode(ua.StatusCodes.BadInternalError)
        if rest:
            sub = ua.WriteParameters()
            sub.NodesToWrite = [items[i] for i in rest]
            for i, status in zip(rest, await write_through(sub), strict=True):
                results[i] = status
        answers = [r if r is not None else ua.StatusCode(ua.StatusCodes.BadInternalError) for r in results]
        for item, status in zip(items, answers, strict=True):
            for observer in self.observers:
                try:
                    observer(caller, item, status)
                except Exception:
                    log.exception("write observer failed")
        return answers
