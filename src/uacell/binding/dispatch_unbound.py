"""Calls of methods no binding declared: the method dispatcher's part that answers them without the
stack's defaults and never past the role table (asyncua's callback runs only for a method of the
object or its type, with its arguments checked, for a caller the table allows)."""

from __future__ import annotations

import logging
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell.binding.calls import call_result
from uacell.core.rights import RoleTable
from uacell.core.roles import Role
from uacell.ua import subscriptions, toolkit
from uacell.ua.context import Caller
from uacell.ua.door.services import asyncua_method_call

log = logging.getLogger("uacell.binding.dispatch")
_A = ua.AttributeIds
_REFRESH = frozenset(
    {ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh), ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh2)}
)


class UnboundCalls:
    """Part of ``MethodDispatcher`` (an asyncua ``MethodService``)."""

    aspace: AddressSpace
    roles: RoleTable
    types: Any  # TypeChecker

    def arguments(self, method_id: ua.NodeId, name: str) -> list[ua.Argument]:
        prop = toolkit.find_child(self.aspace, method_id, name)
        if prop is None:
            return []
        value = self.aspace[prop].attributes[_A.Value].value.Value.Value
        return list(value or [])

    def _belongs(self, object_id: ua.NodeId, method_id: ua.NodeId) -> bool:
        """Is ``method_id`` a method component of the object, or of its type (or a supertype)?"""
        has_component = ua.NodeId(ua.ObjectIds.HasComponent)
        obj = self.aspace.get(object_id)
        if obj is None:
            return False
        holders = [object_id]
        has_type = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
        type_id = next((r.NodeId for r in obj.references if r.IsForward and r.ReferenceTypeId == has_type), None)
        while type_id is not None:
            holders.append(type_id)
            type_id = toolkit.supertype(self.aspace, type_id)
        for holder in holders:
            data = self.aspace.get(holder)
            if data is None:
                continue
            for ref in data.references:
                if ref.IsForward and ref.NodeId == method_id and ref.ReferenceTypeId == has_component:
                    return True
        return False

    def _type_hint(self, object_id: ua.NodeId) -> str:
        """The BrowseName the role table knows the object by: its type's, or its own for a type node."""
        obj = self.aspace[object_id]
        has_type = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
        type_id = next((r.NodeId for r in obj.references if r.IsForward and r.ReferenceTypeId == has_type), None)
        holder = self.aspace.get(type_id) if type_id is not None else obj
        return holder.attributes[_A.BrowseName].value.Value.Value.Name if holder is not None else ""

    async def _unbound(self, request: ua.CallMethodRequest, caller: Caller) -> ua.CallMethodResult:
        """A method no binding declared: never the stack's default answers, never past the role table."""
        try:
            if request.ObjectId not in self.aspace:
                return call_result(ua.StatusCodes.BadNodeIdUnknown)
            method = self.aspace.get(request.MethodId)
            if (
                method is None
                or method.attributes[_A.NodeClass].value.Value.Value != ua.NodeClass.Method
                or not self._belongs(request.ObjectId, request.MethodId)
            ):
                return call_result(ua.StatusCodes.BadMethodInvalid)
            if method.call is None:
                return call_result(ua.StatusCodes.BadNotImplemented)
            name = method.attributes[_A.BrowseName].value.Value.Value.Name
            refused = self._check_arguments(
                list(request.InputArguments or []), self.arguments(request.MethodId, "InputArguments")
            )
            if refused is not None:
                return refused
            if not self.roles.may_call(Role.parse(caller.role), name, self._type_hint(request.ObjectId)):
                return call_result(ua.StatusCodes.BadUserAccessDenied)  # not in the table: admin only
            if request.MethodId in _REFRESH and not subscriptions.owned_by_caller(request.InputArguments[0].Value):
                # OPC 10000-9 5.5.7: a refresh of the caller's own subscription (decision 80)
                return call_result(ua.StatusCodes.BadSubscriptionIdInvalid)
            result = await asyncua_method_call(self, request)
            if result.StatusCode.value == ua.StatusCodes.BadUnexpectedError:
                result.StatusCode = ua.StatusCode(ua.StatusCodes.BadInternalError)
            return result
        except Exception:
            log.exception("call of %s on %s failed unexpectedly", request.MethodId, request.ObjectId)
            return call_result(ua.StatusCodes.BadInternalError)

    def _check_arguments(self, args: list[ua.Variant], inputs: list[ua.Argument]) -> ua.CallMethodResult | None:
        """The refusal for arguments that do not match ``inputs`` (count, then types), or None."""
        if len(args) < len(inputs):
            return call_result(ua.StatusCodes.BadArgumentsMissing)
        if len(args) > len(inputs):
            return call_result(ua.StatusCodes.BadTooManyArguments)
        accepts = self.types.accepts
        if all(accepts(v, a) for v, a in zip(args, inputs, strict=True)):
            return None
        checks = [self.types.check(v, a) for v, a in zip(args, inputs, strict=True)]
        return call_result(ua.StatusCodes.BadTypeMismatch, checks)
