"""Executable of the bound methods, re-evaluated by scope: the method dispatcher's part that keeps
it current (decision 4). A call or a change touches the scope it concerns; the publisher's idle hook
re-evaluates the touched scopes only, so a call costs the same in a cell of any size."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell.binding.calls import UNKNOWN, UNSCOPED, BoundMethod
from uacell.core.rights import RoleTable
from uacell.core.roles import Role
from uacell.ua.toolkit import write_attribute

log = logging.getLogger("uacell.binding.dispatch")
_A = ua.AttributeIds


class ExecutableRefresh:
    """Part of ``MethodDispatcher``: the bound methods with an ``executable`` by scope, and the scopes
    touched since the last refresh (ordered, by id: scopes are arbitrary model objects)."""

    aspace: AddressSpace
    roles: RoleTable
    methods: dict[ua.NodeId, BoundMethod]
    _scoped: dict[int, list[BoundMethod]]
    _touched: dict[int, None]
    _alias: dict[int, object]  # id(serialize_on) -> its methods' scope
    _scope_of: dict[int, object]  # id(scope) -> the scope
    _inputs: dict[int, Any]  # id(scope) -> its executable_inputs at its last refresh

    def _init_executable(self) -> None:
        self._scoped = {}
        self._touched = {}
        self._alias = {}
        self._scope_of = {}
        self._inputs = {}

    def _track(self, bound: BoundMethod) -> None:
        """A method bound with an ``executable``: re-evaluated with its scope."""
        self._scoped.setdefault(id(bound.scope), []).append(bound)
        self._scope_of[id(bound.scope)] = bound.scope
        self._inputs.pop(id(bound.scope), None)  # a new method: evaluate the scope's next time
        if bound.serialize_on is not None:
            self._alias.setdefault(id(bound.serialize_on), bound.scope)

    def _untrack(self, bound: BoundMethod) -> None:
        peers = self._scoped.get(id(bound.scope))
        if peers is not None and bound in peers:
            peers.remove(bound)
            if not peers:
                del self._scoped[id(bound.scope)]

    def touch(self, scope: object) -> None:
        """Note that the model ``scope`` changed (a scope, or the ``serialize_on`` of methods bound with
        one, e.g. a state machine): the next ``refresh_touched()`` re-evaluates its methods."""
        key = id(scope)
        self._touched[id(self._alias.get(key, scope))] = None

    async def refresh_touched(self) -> None:
        """Re-evaluate Executable of the scopes touched since the last time (the publisher's idle hook).
        A scope whose model says what its methods' Executable depends on (an ``executable_inputs``
        attribute) is skipped while that is what it was at its last evaluation."""
        self._touched[id(UNSCOPED)] = None  # nothing says what they depend on: always
        while self._touched:
            key = next(iter(self._touched))
            del self._touched[key]
            await self._refresh_scope(key, skip_unchanged=True)

    async def refresh_executable(self, scope: object | None = None) -> None:
        """Write Executable wherever it changed (decision 4): of the methods of ``scope``, or of every
        bound method when no scope is given (start-up, tests)."""
        if scope is not None:
            self._touched.pop(id(scope), None)
            await self._refresh_scope(id(scope))
            return
        self._touched.clear()
        for key in list(self._scoped):
            await self._refresh_scope(key)

    async def _refresh_scope(self, key: int, skip_unchanged: bool = False) -> None:
        inputs = getattr(self._scope_of.get(key), "executable_inputs", UNKNOWN)
        if skip_unchanged and inputs is not UNKNOWN and self._inputs.get(key, UNKNOWN) == inputs:
            return
        await self._refresh(self._scoped.get(key, ()))
        if inputs is not UNKNOWN:
            self._inputs[key] = inputs

    async def _refresh(self, group: Sequence[BoundMethod]) -> None:
        for bound in list(group):
            if bound.executable is None:
                continue
            try:
                now = bool(bound.executable())
            except Exception:
                log.exception("executable() of %s failed", bound.name)
                now = False
            if now != bound.last_executable:
                bound.last_executable = now
                dv = ua.DataValue(ua.Variant(now, ua.VariantType.Boolean))
                await write_attribute(self.aspace, bound.method_id, _A.Executable, dv)

    def user_executable(self, method_id: ua.NodeId, role: str) -> bool | None:
        bound = self.methods.get(method_id)
        if bound is None:
            return None
        allowed = self.roles.may_call(Role.parse(role), bound.name, bound.family)
        return allowed and (bound.last_executable is not False)
