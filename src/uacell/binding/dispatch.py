"""The one method dispatcher every uacell method call passes through.

For each call it answers, in this order:

1. ``Bad_NodeIdUnknown`` for an unknown object, ``Bad_MethodInvalid`` for a method that is not
   one of the object's (or not a method at all);
2. the input arguments against the method's ``InputArguments``: ``Bad_ArgumentsMissing``,
   ``Bad_TooManyArguments``, ``Bad_TypeMismatch`` with ``InputArgumentResults`` naming the argument;
3. the caller's role (``Bad_UserAccessDenied``) from the one table (``uacell.core.rights.RoleTable``);
4. guards such as DI locks (``Bad_ResourceUnavailable``);
5. the behaviour, serialized per state machine; its ``CallError`` becomes the status code and
   argument results, its outputs are typed from ``OutputArguments``. Any other exception is logged
   and answered with ``Bad_InternalError``: nothing ever reaches the stack.

A method uacell does not bind answers ``Bad_MethodInvalid`` unless it is a component of the object
(or of its type); one that is answers ``Bad_NotImplemented`` when nobody implements it, and otherwise
goes to asyncua's callback (e.g. ConditionRefresh) after the same argument checks and only for a
caller the role table allows (admin by default), with the same ``Bad_InternalError`` guarantee. Once
the server is closing, calls answer ``Bad_Shutdown``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import Any

from asyncua import Node, Server, ua
from asyncua.server.address_space import MethodService

from uacell.binding.calls import UNSCOPED, BoundMethod, Handler, call_result
from uacell.binding.dispatch_unbound import UnboundCalls
from uacell.binding.executable import ExecutableRefresh
from uacell.core.errors import CallError
from uacell.core.rights import RoleTable
from uacell.core.roles import Family, Role
from uacell.ua import context, door, toolkit
from uacell.ua.context import Caller
from uacell.ua.door import processing

__all__ = ["BoundMethod", "Handler", "MethodDispatcher", "TypeChecker", "add_method_node"]

log = logging.getLogger(__name__)

Guard = Callable[[Caller, BoundMethod], None]
# Told of every answered call (audit trail, metrics): caller, request, method name, result, seconds taken.
CallObserver = Callable[[Caller, ua.CallMethodRequest, str, ua.CallMethodResult, float], None]
_A = ua.AttributeIds
# ReturnDiagnostics bits for operation-level SymbolicId, LocalizedText, AdditionalInfo, InnerStatusCode,
# InnerDiagnostics (OPC 10000-4 DiagnosticsMask)
_OPERATION_DIAGNOSTICS = 0x20 | 0x40 | 0x80 | 0x100 | 0x200


@door.subclass("asyncua.server.address_space.MethodService")
class MethodDispatcher(ExecutableRefresh, UnboundCalls, MethodService):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
    """Replaces asyncua's MethodService; install with ``MethodDispatcher.install(server)``."""

    def __init__(self, server: Server, roles: RoleTable) -> None:
        super().__init__(server.iserver.aspace)
        self.roles = roles  # who may call what (the composition root's, of the companions it serves)
        self.aspace = server.iserver.aspace
        self.server = server
        self.methods: dict[ua.NodeId, BoundMethod] = {}
        self.guards: list[Guard] = []
        self.after_call: list[Callable[[], None]] = []  # run when a call is done (not awaited)
        self.observers: list[CallObserver] = []
        self._locks: dict[int, asyncio.Lock] = {}
        self.types = TypeChecker(server)
        # instance method -> its declaration in the type (set by the server once the cell exists),
        # so that a call naming the type's method (e.g. Acknowledge, i=9111) on an object works too
        self._declarations: dict[ua.NodeId, ua.NodeId] = {}
        self._by_decl: dict[tuple[ua.NodeId, ua.NodeId], BoundMethod] | None = None  # built on first use
        self._init_executable()  # Executable by scope (binding/executable.py)
        self._closing = False
        self._running = 0  # calls whose behaviour is under way
        self._idle = asyncio.Event()
        self._idle.set()

    @property
    def declarations(self) -> dict[ua.NodeId, ua.NodeId]:
        return self._declarations

    @declarations.setter
    def declarations(self, value: dict[ua.NodeId, ua.NodeId]) -> None:
        self._declarations = value
        self._by_decl = None

    @classmethod
    def install(cls, server: Server, roles: RoleTable) -> MethodDispatcher:
        processing.attach()  # the session known while its calls run
        dispatcher = cls(server, roles)
        door.swap(server.iserver, "InternalServer.method_service", dispatcher)
        return dispatcher

    # --- registration -----------------------------------------------------------------------
    def bind(
        self,
        object_id: ua.NodeId,
        method_id: ua.NodeId,
        family: Family,
        handler: Handler,
        *,
        executable: Callable[[], bool] | None = None,
        serialize_on: object | None = None,
        element: object | None = None,
        file_mode_argument: int | None = None,
        scope: object | None = None,
    ) -> BoundMethod:
        """Bind ``method_id`` of ``object_id`` to ``handler``. ``executable()`` is re-evaluated after a
        call of any method of the same ``scope`` (default ``serialize_on``), and whenever a binding
        calls ``touch(scope)`` or ``refresh_executable(scope)`` for a change made outside calls."""
        name = self.aspace[method_id].attributes[_A.BrowseName].value.Value.Value.Name
        bound = BoundMethod(
            object_id,
            method_id,
            name,
            family,
            handler,
            self.arguments(method_id, "InputArguments"),
            self.arguments(method_id, "OutputArguments"),
            executable,
            serialize_on,
            element,
            file_mode_argument,
        )
        if method_id in self.methods:
            self.unbind(method_id)
        bound.scope = scope if scope is not None else (serialize_on if serialize_on is not None else UNSCOPED)
        self.methods[method_id] = bound
        if executable is not None:
            self._track(bound)
        self._by_decl = None
        return bound

    async def add_method(
        self,
        object_id: ua.NodeId,
        nodeid: ua.NodeId,
        name: ua.QualifiedName,
        inputs: Sequence[tuple[str, ua.VariantType, str]],
        family: Family,
        handler: Handler,
        **options: Any,
    ) -> BoundMethod:
        """Create a server-specific method (scalar inputs: name, type, description) and bind it."""
        await add_method_node(self.server.get_node(object_id), nodeid, name, inputs)
        return self.bind(object_id, nodeid, family, handler, **options)

    def unbind(self, method_id: ua.NodeId) -> None:
        """Forget a method whose node is being deleted."""
        bound = self.methods.pop(method_id, None)
        if bound is None:
            return
        if bound.serialize_on is None:
            self._locks.pop(id(bound), None)  # its own serialization lock goes with it
        self._untrack(bound)
        self._by_decl = None

    def method_of(self, object_id: ua.NodeId, name: str) -> ua.NodeId:
        for ref in self.aspace[object_id].references:
            if ref.IsForward and ref.BrowseName.Name == name and ref.NodeClass == ua.NodeClass.Method:
                return ref.NodeId
        raise KeyError(f"{object_id} has no method {name}")

    # --- the call ------------------------------------------------------------------------------
    async def call(self, methods: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        return [await self.dispatch(m) for m in methods]

    def _by_declaration(self, object_id: ua.NodeId, method_id: ua.NodeId) -> BoundMethod | None:
        """The method bound on ``object_id`` whose declaration is ``method_id`` (OPC 10000-4 Call lets a
        client name the MethodDeclaration of the object's type): one look-up in an index built once."""
        if self._by_decl is None:
            index: dict[tuple[ua.NodeId, ua.NodeId], BoundMethod] = {}
            for bound in self.methods.values():
                declaration = self._declarations.get(bound.method_id)
                if declaration is not None:
                    index.setdefault((bound.object_id, declaration), bound)
            self._by_decl = index
        return self._by_decl.get((object_id, method_id))

    async def dispatch(self, request: ua.CallMethodRequest, caller: Caller | None = None) -> ua.CallMethodResult:
        if self._closing:
            return call_result(ua.StatusCodes.BadShutdown)
        try:
            caller = caller or context.current_caller()
        except Exception:
            log.exception("resolving the caller of %s failed unexpectedly", request.MethodId)
            return call_result(ua.StatusCodes.BadInternalError)
        self._running += 1
        self._idle.clear()
        started = time.perf_counter()
        try:
            result = await self._answer(request, caller)
        finally:
            self._running -= 1
            if self._running == 0:
                self._idle.set()
        if self.observers:  # told once the answer is out (the event loop's next turn), as publishing is
            asyncio.get_running_loop().call_soon(self._observe, caller, request, result, time.perf_counter() - started)
        return result

    def method_name(self, method_id: ua.NodeId) -> str:
        """The BrowseName of a bound or unbound method ("" for an unknown node)."""
        bound = self.methods.get(method_id)
        if bound is not None:
            return bound.name
        data = self.aspace.get(method_id)
        name = data.attributes.get(_A.BrowseName) if data is not None else None
        return str(name.value.Value.Value.Name) if name is not None else ""

    def _observe(self, who: Caller, request: ua.CallMethodRequest, result: ua.CallMethodResult, seconds: float) -> None:
        if not self.observers:
            return
        try:
            name = self.method_name(request.MethodId)
        except Exception:
            log.exception("describing a call of %s failed", request.MethodId)
            return
        for observer in self.observers:
            try:
                observer(who, request, name, result, seconds)
            except Exception:
                log.exception("call observer failed")

    async def _answer(self, request: ua.CallMethodRequest, caller: Caller) -> ua.CallMethodResult:
        try:
            bound = self.methods.get(request.MethodId) or self._by_declaration(request.ObjectId, request.MethodId)
        except Exception:
            log.exception("resolving a call of %s failed unexpectedly", request.MethodId)
            return call_result(ua.StatusCodes.BadInternalError)
        if bound is None:
            return await self._unbound(request, caller)
        try:
            return await self._dispatch(bound, request, caller)
        except Exception:
            log.exception("%s on %s failed unexpectedly", bound.name, request.ObjectId.to_string())
            self._after(bound)
            return call_result(ua.StatusCodes.BadInternalError)

    async def close(self, timeout: float = 5.0) -> None:
        """Refuse new calls (Bad_Shutdown) and wait, up to ``timeout`` s, for those under way."""
        self._closing = True
        try:
            await asyncio.wait_for(self._idle.wait(), timeout)
        except TimeoutError:
            log.warning("shutting down with %d method call(s) still running", self._running)

    async def _dispatch(self, bound: BoundMethod, request: ua.CallMethodRequest, caller: Caller) -> ua.CallMethodResult:
        if request.ObjectId != bound.object_id:
            code = (
                ua.StatusCodes.BadMethodInvalid if request.ObjectId in self.aspace else ua.StatusCodes.BadNodeIdUnknown
            )
            return call_result(code)
        args = list(request.InputArguments or [])
        n = len(bound.inputs)
        refused = self._check_arguments(args, bound.inputs)
        if refused is not None:
            return refused
        values = [v.Value for v in args]
        mode = values[bound.file_mode_argument] if bound.file_mode_argument is not None else None
        if not self.roles.may_call(Role.parse(caller.role), bound.name, bound.family, file_mode=mode):
            return call_result(ua.StatusCodes.BadUserAccessDenied, n=n)
        try:
            for guard in self.guards:
                guard(caller, bound)
            key = id(bound.serialize_on or bound)
            lock = self._locks.get(key)
            if lock is None:
                lock = self._locks[key] = asyncio.Lock()
            async with lock:
                # Transitions the behaviour causes are the caller's (AuditUpdateStateEvents).
                call = context.MethodCall(
                    caller, bound.object_id, bound.method_id, bound.name, tuple(args), datetime.now(UTC),
                    context.audit_entry_id(),
                )  # fmt: skip
                token = context.enter_call(call)
                try:
                    outputs = await bound.handler(caller, *values)
                finally:
                    context.leave_call(token)
        except CallError as err:
            log.info("%s refused for %s: %s", bound.name, caller.display_user, err.message)
            results = None
            if err.argument is not None and 0 <= err.argument < n:
                results = [ua.StatusCode(ua.StatusCodes.Good)] * n
                results[err.argument] = ua.StatusCode(getattr(ua.StatusCodes, err.argument_status))
            result = call_result(getattr(ua.StatusCodes, err.status), results, n=n)
            diagnostics = context.return_diagnostics() & _OPERATION_DIAGNOSTICS
            if results is not None and err.argument is not None and diagnostics:
                # The reason, for clients that ask for operation-level diagnostics (OPC 10000-4 Call).
                infos = [ua.DiagnosticInfo() for _ in range(n)]
                infos[err.argument] = ua.DiagnosticInfo(AdditionalInfo=err.message)
                result.InputArgumentDiagnosticInfos = infos
            self._after(bound)
            return result
        self._after(bound)
        result = call_result(ua.StatusCodes.Good, n=n)
        result.OutputArguments = [self.types.variant(v, a) for v, a in zip(outputs or [], bound.outputs, strict=False)]
        return result

    def _after(self, bound: BoundMethod) -> None:
        """Have what the behaviour changed and Executable of the call's scope published once the call is
        answered (``after_call``: the server's publisher drains on the loop's next turn, before another
        request is served, decision 56); a failure here is logged, never turned into the call's answer
        (the behaviour has already happened)."""
        try:
            self.touch(bound.scope)
            for hook in self.after_call:
                hook()
        except Exception:
            log.exception("publishing after a call failed")


# Built-in DataType ids (ns=0;i=1..25) have the same number as their VariantType.
_ABSTRACT_NUMBERS = {26: "Number", 27: "Integer", 28: "UInteger", 29: "Enumeration"}
_INTEGERS = {
    ua.VariantType.SByte,
    ua.VariantType.Byte,
    ua.VariantType.Int16,
    ua.VariantType.UInt16,
    ua.VariantType.Int32,
    ua.VariantType.UInt32,
    ua.VariantType.Int64,
    ua.VariantType.UInt64,
}
_UNSIGNED = {ua.VariantType.Byte, ua.VariantType.UInt16, ua.VariantType.UInt32, ua.VariantType.UInt64}


_UNSEEN: Any = object()


class TypeChecker:
    """Does a Variant match an Argument's DataType and ValueRank?"""

    def __init__(self, server: Server) -> None:
        self.aspace = server.iserver.aspace
        self._builtin: dict[ua.NodeId, ua.VariantType | None] = {}
        # DataType -> the one VariantType a scalar argument of it is, or None when a value needs the full
        # check (structures, abstract types, BaseDataType); as many as the DataTypes of arguments called
        self._plain: dict[ua.NodeId, ua.VariantType | None] = {}

    def accepts(self, variant: ua.Variant, arg: ua.Argument) -> bool:
        """``check(variant, arg)`` is Good: a non-null scalar of the one builtin type a scalar argument
        takes is told at once, anything else by ``check``."""
        if arg.ValueRank == -1:
            value = variant.Value
            if value is not None and not variant.is_array and not isinstance(value, list):
                datatype = arg.DataType
                plain = self._plain.get(datatype, _UNSEEN)
                if plain is _UNSEEN:
                    plain = self._plain[datatype] = self._plain_type(datatype)
                if plain is not None and variant.VariantType is plain:
                    return True
        return bool(self.check(variant, arg).is_good())

    def _plain_type(self, datatype: ua.NodeId) -> ua.VariantType | None:
        """The VariantType whose non-null scalars ``check`` finds Good for a scalar argument of
        ``datatype`` without looking at the value (a concrete builtin type), else None."""
        if datatype == ua.NodeId(ua.ObjectIds.BaseDataType):
            return None
        expected = self.builtin_of(datatype)
        if expected is None or expected in (ua.VariantType.ExtensionObject, ua.VariantType.Null):
            return None
        return expected

    def builtin_of(self, datatype: ua.NodeId) -> ua.VariantType | None:
        """The VariantType a DataType is encoded as (enumerations -> Int32, structures -> ExtensionObject)."""
        if datatype in self._builtin:
            return self._builtin[datatype]
        node: ua.NodeId | None = datatype
        found: ua.VariantType | None = None
        while node is not None:
            if node.NamespaceIndex == 0 and isinstance(node.Identifier, int):
                i = node.Identifier
                if 1 <= i <= 25:
                    found = ua.VariantType(i)
                    break
                if i == 29:
                    found = ua.VariantType.Int32
                    break
                if i == 22:
                    found = ua.VariantType.ExtensionObject
                    break
                if i in _ABSTRACT_NUMBERS:
                    found = None
                    break
            node = toolkit.supertype(self.aspace, node)
        self._builtin[datatype] = found
        return found

    def _is_subtype(self, node: ua.NodeId | None, base: ua.NodeId) -> bool:
        while node is not None:
            if node == base:
                return True
            node = toolkit.supertype(self.aspace, node)
        return False

    def _scalar_ok(self, value: Any, vtype: ua.VariantType, arg: ua.Argument, expected: ua.VariantType | None) -> bool:
        dt = arg.DataType
        if expected is None:  # abstract Number / Integer / UInteger
            name = _ABSTRACT_NUMBERS.get(dt.Identifier) if dt.NamespaceIndex == 0 else None
            if name == "Integer":
                return vtype in _INTEGERS
            if name == "UInteger":
                return vtype in _UNSIGNED
            return vtype in _INTEGERS or vtype in (ua.VariantType.Float, ua.VariantType.Double)
        if dt == ua.NodeId(ua.ObjectIds.BaseDataType):
            return True
        if vtype != expected:
            return False
        if expected == ua.VariantType.ExtensionObject:
            type_id = _datatype_of(value)
            return type_id is not None and self._is_subtype(type_id, dt)
        return True

    def check(self, variant: ua.Variant, arg: ua.Argument) -> ua.StatusCode:
        good, bad = ua.StatusCode(ua.StatusCodes.Good), ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
        expected = self.builtin_of(arg.DataType)
        vtype = variant.VariantType
        is_array = variant.is_array or isinstance(variant.Value, list)
        if arg.DataType == ua.NodeId(ua.ObjectIds.BaseDataType) and arg.ValueRank == -2:
            return good
        if arg.ValueRank == -1 or (arg.ValueRank in (-3, -2) and not is_array):
            if (
                is_array
                or vtype == ua.VariantType.Null
                or (variant.Value is None and vtype not in (ua.VariantType.String, ua.VariantType.ByteString))
            ):
                return bad
            return good if self._scalar_ok(variant.Value, vtype, arg, expected) else bad
        # arrays (ValueRank >= 1, or -3 with an array, or 0 = one or more dimensions)
        if not is_array:
            return bad
        items = variant.Value or []
        if not items:
            return good if vtype in (expected, ua.VariantType.Null) or expected is None else bad
        return good if all(self._scalar_ok(v, vtype, arg, expected) for v in items) else bad

    def variant(self, value: Any, arg: ua.Argument) -> ua.Variant:
        if isinstance(value, ua.Variant):
            return value
        vtype = self.builtin_of(arg.DataType) or ua.VariantType.Variant
        return ua.Variant(value, vtype, is_array=arg.ValueRank >= 0 or isinstance(value, list))


def _datatype_of(value: Any) -> ua.NodeId | None:
    """The DataType NodeId of a decoded structure value (or of an undecoded ExtensionObject)."""
    if isinstance(value, ua.ExtensionObject):
        return None  # the server could not decode it: not a structure it knows
    cls = type(value)
    data_type = getattr(cls, "data_type", None)
    if isinstance(data_type, ua.NodeId):
        return data_type
    # asyncua's generated classes are registered by their encoding ids
    for nodeid, known in ua.extension_objects_by_datatype.items():
        if known is cls:
            return nodeid
    return None


async def add_method_node(
    parent: Node, nodeid: ua.NodeId, name: ua.QualifiedName, inputs: Sequence[tuple[str, ua.VariantType, str]]
) -> None:
    """A server-specific method node below ``parent`` with its InputArguments (scalar inputs: name,
    type, description), unbound: ``Dispatcher.add_method`` (or ``bind``) binds it."""
    arguments = []
    for arg_name, vtype, text in inputs:
        arg = ua.Argument()
        arg.Name = arg_name
        arg.DataType = ua.NodeId(vtype.value)
        arg.ValueRank = -1
        arg.ArrayDimensions = []
        arg.Description = ua.LocalizedText(text)
        arguments.append(arg)

    async def unused(parent: Any, *args: Any) -> list[ua.StatusCode]:  # never called: the dispatcher answers
        return [ua.StatusCode(ua.StatusCodes.BadInternalError)]

    method = await parent.add_method(nodeid, name, unused)
    if arguments:  # with a NodeId derived from the method's, as served and exported (not a counter's)
        prop = await method.add_property(
            ua.NodeId(f"{nodeid.Identifier}.InputArguments", nodeid.NamespaceIndex),
            ua.QualifiedName("InputArguments", 0),
            arguments,
            varianttype=ua.VariantType.ExtensionObject,
            datatype=ua.ObjectIds.Argument,
        )
        await prop.write_value_rank(ua.ValueRank.OneDimension)  # as OPC 10000-3 declares InputArguments
        await prop.set_modelling_rule(True)
