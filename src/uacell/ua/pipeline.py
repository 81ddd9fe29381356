"""The declared stages each request passes, and the guards of a connection and a secure channel.

asyncua offers no middleware, so the door (``uacell.ua.door.processing``) wraps its entry points once,
process-wide, and hands each to the pipeline of the server a connection reached:

- a new connection (``OPCUAProtocol.connection_made``): the server's ``admission`` (``ua/limits.py``:
  room made by closing the oldest connection without a session, a deadline for the handshake);
- a connection's bytes (``OPCUAProtocol.data_received``): the server's ``bytes_guard``
  (``ua/limits.py``: chunk sizes and buffers checked before asyncua buffers them); a message asyncua
  parsed runs at once when its connection has nothing under way, else it waits in the connection's
  queue for asyncua's task (``OPCUAProtocol._process_one_msg``), one message after the other (decision 51);
- the opening of a secure channel (``UaProcessor.process`` for an OpenSecureChannel message, and
  ``UaProcessor.open_secure_channel``): the server's ``channel_guard`` (``security/policy.py``: only the
  policies and modes the endpoints offer); a message asyncua refuses there or in its chunk handling
  goes to the server's ``refused`` (one INFO line, an Error message) and closes the connection;
- each service request (``UaProcessor.process_message``, its TypeId and header decoded by
  ``ua/codec.py``; ``UaProcessor._process_message``): the server's ``stages``, in order; a
  Call runs apart (up to ``CALLS_APART`` per connection): at once, and in a task of its own from its
  first wait on, so one that waits for equipment does not hold up the connection's other requests;
- a session's Call, Read and HistoryRead (``InternalSession``): the session known while they run, and
  the read hooks (``ua/context.py``).

What runs belongs to the server a connection reached (``Pipeline.of(iserver)``), so servers in one
process keep their own stages; an asyncua server without a pipeline runs asyncua's processing alone.
``uacell.server`` declares the stages, outermost first:

    published    what earlier calls changed is in the address space before the request is served
                 (a call is answered first and published after, decision 56)
    context      the request's processor, ReturnDiagnostics and AuditEntryId for the code below
    diagnostics  ServerDiagnostics counters (services/diagnostics.py)
    security     the service allowed on this channel and for this session; ActivateSession throttled,
                 checked off the event loop and audited (security/policy.py)
    decoding     a request asyncua cannot decode answers Bad_DecodingError (ua/limits.py)
    (service)    the service itself: Call and Read as asyncua runs them, found by one dictionary
                 lookup (``SERVICES``; asyncua compares the request's type with up to 40 NodeIds it
                 builds for each request, decision 48); a Call goes on to the one method dispatcher
                 (binding/dispatch.py); every other service is asyncua's own processing

A stage is any object with ``async __call__(request, call_next)``: it may answer itself, raise a
``ServiceError``, or ``await call_next(request)`` and look at the answer. Adding a cross-cutting
stage is one entry in that list.
"""

from __future__ import annotations

import asyncio
import contextvars
import functools
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from asyncua import ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.server.binary_server_asyncio import OPCUAProtocol
from asyncua.server.internal_session import InternalSession
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary

from uacell.core.background import eager
from uacell.ua import channel, context
from uacell.ua.codec import decode_call_parameters, encode_call_response
from uacell.ua.door import connection, processing
from uacell.ua.door.processing import fault

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Request:
    """One service request, its TypeId and header decoded (``ua/codec.py``; the body is still encoded)."""

    processor: UaProcessor
    typeid: ua.NodeId
    header: Any  # ua.RequestHeader
    seqhdr: Any
    body: Buffer


Next = Callable[[Request], Awaitable[Any]]


class Stage(Protocol):
    """One job done around every service request."""

    async def __call__(self, request: Request, call_next: Next) -> Any: ...


class ChannelGuard(Protocol):
    """Checks a secure channel's opening and the renewals of its token (``security.Security``)."""

    async def opening(self, processor: UaProcessor, header: ua.Header, body: Buffer, proceed: Next0) -> Any: ...

    def open(self, processor: UaProcessor, algohdr: Any, body: Buffer) -> None: ...

    async def renewing(self, processor: UaProcessor, header: ua.Header, body: Buffer, proceed: Next0) -> Any: ...

    def renew(self, processor: UaProcessor, algohdr: Any, body: Buffer) -> None: ...

    async def closing(self, processor: UaProcessor, proceed: Next0) -> Any: ...


Next0 = Callable[[], Awaitable[Any]]
BytesGuard = Callable[[OPCUAProtocol, bytes, Callable[[OPCUAProtocol, bytes], None]], None]
# Runs when a connection is accepted, in place of asyncua's connection_made (which it calls).
Admission = Callable[[OPCUAProtocol, Any, Callable[[OPCUAProtocol, Any], None]], None]
# Told about a message asyncua refused below the request stages (it answers and logs; the connection closes).
Refused = Callable[[UaProcessor, Exception], None]


class ContextStage:
    """The request's processor, ReturnDiagnostics and AuditEntryId, known to everything below."""

    async def __call__(self, request: Request, call_next: Next) -> Any:
        header = request.header
        processor = context.set_processor(request.processor)
        diagnostics = context.set_return_diagnostics(int(getattr(header, "ReturnDiagnostics", 0) or 0))
        audit_entry = context.set_audit_entry_id(str(getattr(header, "AuditEntryId", "") or ""))
        try:
            return await call_next(request)
        finally:
            context.reset_audit_entry_id(audit_entry)
            context.reset_return_diagnostics(diagnostics)
            context.reset_processor(processor)


class Settling(Protocol):
    """What publishes the changes of answered calls (``uacell.binding.publisher.Publisher``)."""

    @property
    def pending(self) -> bool: ...

    async def flush(self, timeout: float | None = None) -> None: ...


PUBLISHED_WAIT = 5.0  # seconds a request waits for a publishing that itself waits, then is served


class PublishedStage:
    """A request is served only once what earlier calls changed is in the address space. A call is
    answered before its changes are published (decision 56); they are published on the event loop's
    next turn, and a request that comes first (or while publishing waits) waits for them here. A
    publishing that is still waiting after ``wait`` seconds (a job stuck on something: a bug) holds
    up no request longer: it is served, and a warning says so."""

    def __init__(self, publisher: Settling, wait: float = PUBLISHED_WAIT) -> None:
        self._publisher = publisher
        self._wait = wait

    async def __call__(self, request: Request, call_next: Next) -> Any:
        if self._publisher.pending:
            try:
                await self._publisher.flush(self._wait)
            except TimeoutError:
                log.warning("publishing has waited more than %.1f s: a request is served before it", self._wait)
        return await call_next(request)


class Pipeline:
    """One server's stages and guards (the door's wrappers, ``door/processing.py``, run them)."""

    def __init__(
        self,
        stages: Sequence[Stage],
        *,
        bytes_guard: BytesGuard | None = None,
        channel_guard: ChannelGuard | None = None,
        refused: Refused | None = None,
        admission: Admission | None = None,
    ) -> None:
        self.stages = tuple(stages)
        self.admission = admission
        self.bytes_guard = bytes_guard
        self.channel_guard = channel_guard
        self.refused = refused
        self._entry = _compose(self.stages, _service)

    @staticmethod
    def of(iserver: Any) -> Pipeline | None:
        pipeline = processing.hooks_of(iserver)
        return pipeline if isinstance(pipeline, Pipeline) else None

    def install(self, iserver: Any) -> None:
        """Run this pipeline for every connection to ``iserver`` (an asyncua InternalServer)."""
        processing.install(iserver, self)

    def names(self) -> list[str]:
        """The stages in order, by class name (for logs and tests)."""
        return [type(s).__name__ for s in self.stages]

    async def request(self, request: Request) -> Any:
        return await self._entry(request)

    async def message(self, processor: UaProcessor, typeid: ua.NodeId, header: Any, seqhdr: Any, body: Buffer) -> Any:
        """One service request from the door (``UaProcessor._process_message``), its TypeId and header
        decoded: through the stages."""
        request = Request(processor, typeid, header, seqhdr, body)
        if typeid in _APART:
            # A call may wait for equipment (a PLC confirming a command), a history read works through
            # a page in slices (docs/history.md): each runs apart, so the connection keeps answering its
            # other requests (a client's keep-alive Read) meanwhile; its response goes out when it is
            # done (OPC UA matches responses by RequestHandle).
            running = connection.calls_apart(processor)
            if len(running) < CALLS_APART:
                # at once, in a context of its own; a task only from its first wait on (most never wait)
                task = eager(_call_apart(self, request), contextvars.copy_context())
                if task is not None:
                    running.add(task)
                    task.add_done_callback(running.discard)
                    if typeid != _CALL:  # a history read, which a Cancel may end (a call's behaviour may not)
                        cancellable = connection.cancellable(processor)
                        handle = request.header.RequestHandle
                        cancellable[handle] = task
                        task.add_done_callback(lambda _: cancellable.pop(handle, None))
                return True
        return await self._entry(request)


def _compose(stages: Sequence[Stage], endpoint: Next) -> Next:
    """The stages as one chain: each link hands the request to its stage with the next link (no
    coroutine of its own: a request passes one coroutine per stage, not two)."""
    handler = endpoint
    for stage in reversed(stages):
        handler = functools.partial(_link, stage, handler)
    return handler


def _link(stage: Stage, call_next: Next, request: Request) -> Awaitable[Any]:
    return stage(request, call_next)


async def _service(request: Request) -> Any:
    """The service a request asks for: one of ``SERVICES``, else asyncua's processing."""
    service = SERVICES.get(request.typeid)
    if service is None:
        return await processing.asyncua_process_message(
            request.processor, request.typeid, request.header, request.seqhdr, request.body
        )
    processor = request.processor
    session = processor.session
    # asyncua's checks for a service of an activated session, in its order and with its status codes
    if session is None:
        raise ua.uaerrors.BadUserAccessDenied
    if not channel.permits(processor, session.user, request.typeid, request.body):
        raise ua.uaerrors.BadUserAccessDenied
    processor.session_last_activity = time.monotonic()
    session.touch()
    if not session.is_activated():
        raise ServiceError(ua.StatusCodes.BadSessionNotActivated)
    decode, response_type, field, run, encode = service
    response = response_type()
    answer = await run(session, decode(request.body))
    if field is not None:
        setattr(response, field, answer)
    response.ResponseHeader.RequestHandle = request.header.RequestHandle
    channel.send_response(processor, request.seqhdr.RequestId, encode(response))
    return True


async def _call_service(session: InternalSession, params: Any) -> Any:
    return await session.call(params.MethodsToCall)


async def _read_service(session: InternalSession, params: Any) -> Any:
    return await session.read(params)


async def _history_update_service(session: InternalSession, params: Any) -> Any:
    """HistoryUpdate (asyncua has no processing for it): the history manager answers each item."""
    return await session.history_update(params)


async def _browse_next_service(session: InternalSession, params: Any) -> Any:
    """BrowseNext (asyncua has no processing for it): the session's continuation points (ua/views.py)."""
    return await session.browse_next(params)


async def _register_nodes_service(session: InternalSession, params: Any) -> Any:
    """RegisterNodes through the session (asyncua's processing answered without it)."""
    return ua.RegisterNodesResult(RegisteredNodeIds=await session.register_nodes(params.NodesToRegister))


async def _unregister_nodes_service(session: InternalSession, params: Any) -> Any:
    """UnregisterNodes through the session (asyncua's processing answered without it)."""
    return await session.unregister_nodes(params.NodesToUnregister)


CANCELLED_BY_CLIENT = "cancelled by the client"  # the message of a task a Cancel ends


async def _cancel_service(session: InternalSession, params: Any) -> Any:
    """Cancel (OPC 10000-4 5.7.5; asyncua: Bad_ServiceUnsupported): the connection's history read under
    way with that RequestHandle ends, answered Bad_RequestCancelledByClient; a Call is not cancelled (its
    behaviour is under way and cannot be half undone), nor a request already answered. CancelCount says
    how many were."""
    task = connection.cancellable(context.current_processor()).pop(params.RequestHandle, None)
    if task is None or task.done():
        return ua.CancelResult(CancelCount=0)
    task.cancel(CANCELLED_BY_CLIENT)
    return ua.CancelResult(CancelCount=1)


async def _set_triggering_service(session: InternalSession, params: Any) -> Any:
    """SetTriggering (asyncua has no processing for it): the session links the items (ua/subscriptions.py)."""
    return await session.set_triggering(params)


Service = tuple[
    Callable[[Buffer], Any], type, str | None, Callable[[InternalSession, Any], Awaitable[Any]], Callable[[Any], bytes]
]
# The services uacell runs itself or as asyncua does, by request type: (the parameters' decoder, the
# response, its field for the answer (None: the response has none), what runs, the response's encoder:
# the Call's are written out, ua/codec.py)
SERVICES: dict[ua.NodeId, Service] = {
    ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary): (
        decode_call_parameters, ua.CallResponse, "Results", _call_service, encode_call_response,
    ),
    ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.ReadParameters), ua.ReadResponse, "Results", _read_service,
        struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.HistoryUpdateParameters), ua.HistoryUpdateResponse, "Results",
        _history_update_service, struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.BrowseNextRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.BrowseNextParameters), ua.BrowseNextResponse, "Parameters",
        _browse_next_service, struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.RegisterNodesRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.RegisterNodesParameters), ua.RegisterNodesResponse, "Parameters",
        _register_nodes_service, struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.UnregisterNodesRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.UnregisterNodesParameters), ua.UnregisterNodesResponse, None,
        _unregister_nodes_service, struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.CancelRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.CancelParameters), ua.CancelResponse, "Parameters",
        _cancel_service, struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.SetTriggeringRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.SetTriggeringParameters), ua.SetTriggeringResponse, "Parameters",
        _set_triggering_service, struct_to_binary,
    ),
}  # fmt: skip


_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_APART = frozenset({_CALL, ua.NodeId(ua.ObjectIds.HistoryReadRequest_Encoding_DefaultBinary)})
CALLS_APART = 16  # calls and history reads of one connection under way at once; more wait their turn


async def _call_apart(pipeline: Pipeline, request: Request) -> None:
    """One Call (or HistoryRead) request, as asyncua's ``process_message`` would run it, in a task of its own."""
    processor = request.processor
    try:
        if await pipeline.request(request) is False:
            connection.close(processor)
    except asyncio.CancelledError as cancelled:
        if cancelled.args != (CANCELLED_BY_CLIENT,):
            raise  # the connection closing, the server stopping
        fault(processor, request.header, request.seqhdr, ua.StatusCodes.BadRequestCancelledByClient)
    except (ServiceError, ua.UaStatusCodeError) as exc:
        fault(processor, request.header, request.seqhdr, exc.code)
    except Exception:
        log.exception("a %s request failed", request.typeid)
        fault(processor, request.header, request.seqhdr, ua.StatusCodes.BadInternalError)
