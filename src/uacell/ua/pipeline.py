"""The one place uacell attaches to asyncua's processing, and the declared stages each request passes.

asyncua offers no middleware, so uacell wraps its entry points once, here, process-wide:

- a new connection (``OPCUAProtocol.connection_made``): the server's ``admission`` (``ua/limits.py``:
  room made by closing the oldest connection without a session, a deadline for the handshake);
- a connection's bytes (``OPCUAProtocol.data_received``): the server's ``bytes_guard``
  (``ua/limits.py``: chunk sizes and buffers checked before asyncua buffers them); a message asyncua
  parsed runs at once when its connection has nothing under way, else it waits in the connection's
  queue for asyncua's task (``OPCUAProtocol._process_one_msg``), one message after the other (decision 51);
- the opening of a secure channel (``UaProcessor.process`` for an OpenSecureChannel message, and
  ``UaProcessor.open_secure_channel``): the server's ``channel_guard`` (``security.py``: only the
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
    diagnostics  ServerDiagnostics counters (ua/diagnostics.py)
    security     the service allowed on this channel and for this session; ActivateSession throttled,
                 checked off the event loop and audited (security.py)
    decoding     a request asyncua cannot decode answers Bad_DecodingError (ua/limits.py)
    (service)    the service itself: Call and Read as asyncua runs them, found by one dictionary
                 lookup (``SERVICES``; asyncua compares the request's type with up to 40 NodeIds it
                 builds for each request, decision 48); a Call goes on to the one method dispatcher
                 (ua/dispatch.py); every other service is asyncua's own processing

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

from uacell.background import eager
from uacell.ua import channel, context
from uacell.ua.codec import decode_call_parameters, decode_request_header, encode_call_response

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
    """Checks a secure channel's opening (``security.Security``)."""

    async def opening(self, processor: UaProcessor, header: ua.Header, body: Buffer, proceed: Next0) -> Any: ...

    def open(self, processor: UaProcessor, algohdr: Any, body: Buffer) -> None: ...


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
    """What publishes the changes of answered calls (``uacell.ua.publisher.Publisher``)."""

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
    """One server's stages and guards (``attach()`` runs them)."""

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
        pipeline: Pipeline | None = getattr(iserver, "_uacell_pipeline", None)
        return pipeline

    def install(self, iserver: Any) -> None:
        """Run this pipeline for every connection to ``iserver`` (an asyncua InternalServer)."""
        attach()
        iserver._uacell_pipeline = self

    def names(self) -> list[str]:
        """The stages in order, by class name (for logs and tests)."""
        return [type(s).__name__ for s in self.stages]

    async def request(self, request: Request) -> Any:
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


# asyncua's own entry points, as they were before ``attach()``.
_ORIGINAL_PROCESS_MESSAGE = UaProcessor._process_message
_ORIGINAL_PROCESS_SECURE_MESSAGE = UaProcessor.process_message
_ORIGINAL_PROCESS = UaProcessor.process
_ORIGINAL_OPEN = UaProcessor.open_secure_channel
_ORIGINAL_DATA_RECEIVED = OPCUAProtocol.data_received
_ORIGINAL_PROCESS_ONE_MSG = OPCUAProtocol._process_one_msg
_ORIGINAL_CONNECTION_MADE = OPCUAProtocol.connection_made
_ORIGINAL_CALL = InternalSession.call
_ORIGINAL_READ = InternalSession.read
_ORIGINAL_HISTORY_READ = InternalSession.history_read


async def _service(request: Request) -> Any:
    """The service a request asks for: one of ``SERVICES``, else asyncua's processing."""
    service = SERVICES.get(request.typeid)
    if service is None:
        return await _ORIGINAL_PROCESS_MESSAGE(
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
    decode, response_type, run, encode = service
    response = response_type()
    response.Results = await run(session, decode(request.body))
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


Service = tuple[Callable[[Buffer], Any], type, Callable[[InternalSession, Any], Awaitable[Any]], Callable[[Any], bytes]]
# The services uacell runs as asyncua does, by request type: (the parameters' decoder, the response,
# what runs, the response's encoder: the Call's are written out, ua/codec.py)
SERVICES: dict[ua.NodeId, Service] = {
    ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary): (
        decode_call_parameters, ua.CallResponse, _call_service, encode_call_response,
    ),
    ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.ReadParameters), ua.ReadResponse, _read_service, struct_to_binary,
    ),
    ua.NodeId(ua.ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary): (
        functools.partial(struct_from_binary, ua.HistoryUpdateParameters), ua.HistoryUpdateResponse,
        _history_update_service, struct_to_binary,
    ),
}  # fmt: skip


async def _process_secure_message(self: UaProcessor, seqhdr: Any, body: Buffer) -> Any:
    """asyncua's ``process_message`` (a request's TypeId and header decoded, then the request handled,
    a refusal answered with a ServiceFault), the header decoded by ``ua/codec.py`` (decision 50)."""
    if Pipeline.of(self.iserver) is None:
        return await _ORIGINAL_PROCESS_SECURE_MESSAGE(self, seqhdr, body)
    typeid, header = decode_request_header(body)
    try:
        return await self._process_message(typeid, header, seqhdr, body)
    except (ServiceError, ua.UaStatusCodeError) as exc:
        code = exc.code
    except Exception:
        log.exception("a %s request failed", typeid)
        code = ua.StatusCodes.BadInternalError
    _fault(self, header, seqhdr, code)
    return True


async def _process_message(self: UaProcessor, typeid: ua.NodeId, requesthdr: Any, seqhdr: Any, body: Buffer) -> Any:
    pipeline = Pipeline.of(self.iserver)
    if pipeline is None:
        return await _ORIGINAL_PROCESS_MESSAGE(self, typeid, requesthdr, seqhdr, body)
    request = Request(self, typeid, requesthdr, seqhdr, body)
    if typeid in _APART:
        # A call may wait for equipment (a PLC confirming a command), a history read works through
        # a page in slices (docs/history.md): each runs apart, so the connection keeps answering its
        # other requests (a client's keep-alive Read) meanwhile; its response goes out when it is
        # done (OPC UA matches responses by RequestHandle).
        running: set[asyncio.Task[None]] | None = self.__dict__.get("_uacell_calls")
        if running is None:
            running = self.__dict__["_uacell_calls"] = set()
        if len(running) < CALLS_APART:
            # at once, in a context of its own; a task only from its first wait on (most never wait)
            task = eager(_call_apart(pipeline, request), contextvars.copy_context())
            if task is not None:
                running.add(task)
                task.add_done_callback(running.discard)
            return True
    return await pipeline.request(request)


_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_APART = frozenset({_CALL, ua.NodeId(ua.ObjectIds.HistoryReadRequest_Encoding_DefaultBinary)})
CALLS_APART = 16  # calls and history reads of one connection under way at once; more wait their turn


async def _call_apart(pipeline: Pipeline, request: Request) -> None:
    """One Call (or HistoryRead) request, as asyncua's ``process_message`` would run it, in a task of its own."""
    processor = request.processor
    try:
        if await pipeline.request(request) is False:
            processor._transport.close()
    except (ServiceError, ua.UaStatusCodeError) as exc:
        _fault(processor, request.header, request.seqhdr, exc.code)
    except Exception:
        log.exception("a %s request failed", request.typeid)
        _fault(processor, request.header, request.seqhdr, ua.StatusCodes.BadInternalError)


def _fault(processor: UaProcessor, header: Any, seqhdr: Any, code: int) -> None:
    response = ua.ServiceFault()
    response.ResponseHeader.ServiceResult = ua.StatusCode(code)
    processor.send_response(header.RequestHandle, seqhdr, response)


async def _process(self: UaProcessor, header: ua.Header, body: Buffer) -> Any:
    pipeline = Pipeline.of(self.iserver)
    if pipeline is None:
        return await _ORIGINAL_PROCESS(self, header, body)
    guard = pipeline.channel_guard
    try:
        if guard is None or header.MessageType != ua.MessageType.SecureOpen or self._connection.is_open():
            return await _ORIGINAL_PROCESS(self, header, body)
        return await guard.opening(self, header, body, lambda: _ORIGINAL_PROCESS(self, header, body))
    except (ua.UaError, ServiceError) as exc:
        # What a client's message provoked below the request stages (asyncua would log a traceback
        # at ERROR and keep the connection): refused in one line, and the connection closed.
        if pipeline.refused is not None:
            pipeline.refused(self, exc)
        return False


def _open_secure_channel(self: UaProcessor, algohdr: Any, seqhdr: Any, body: Buffer) -> Any:
    pipeline = Pipeline.of(self.iserver)
    guard = pipeline.channel_guard if pipeline is not None else None
    if guard is not None and not self._connection.is_open():
        guard.open(self, algohdr, body)
    return _ORIGINAL_OPEN(self, algohdr, seqhdr, body)


def _connection_made(self: OPCUAProtocol, transport: Any) -> None:
    pipeline = Pipeline.of(self.iserver)
    if pipeline is None or pipeline.admission is None:
        _ORIGINAL_CONNECTION_MADE(self, transport)
        return
    pipeline.admission(self, transport, _ORIGINAL_CONNECTION_MADE)


def _data_received(self: OPCUAProtocol, data: bytes) -> None:
    pipeline = Pipeline.of(self.iserver)
    if pipeline is None or self.processor is None:
        _ORIGINAL_DATA_RECEIVED(self, data)
    elif pipeline.bytes_guard is None:
        _received(self, data)
    else:
        pipeline.bytes_guard(self, data, _received)


class _Inbox:
    """Stands in for a connection's message queue while asyncua parses received bytes: collects what
    asyncua would queue, full where the queue would be."""

    def __init__(self, queue: asyncio.Queue[Any]) -> None:
        self.queue = queue
        self.items: list[tuple[Any, Any]] = []

    def put_nowait(self, item: tuple[Any, Any]) -> None:
        limit = self.queue.maxsize
        if limit > 0 and self.queue.qsize() + len(self.items) >= limit:
            raise asyncio.QueueFull
        self.items.append(item)


def _received(protocol: OPCUAProtocol, data: bytes) -> None:
    """asyncua's ``data_received``; a message it parsed runs at once when the connection has nothing
    under way or waiting (asyncua would wake the connection's task for it: a task switch and a future
    a request), else it waits in the connection's queue as before. One message at a time, in order:
    one that waits (an ActivateSession checked off the loop) holds back the next (``_process_one_msg``)."""
    queue = protocol.messages
    inbox = _Inbox(queue)
    protocol.messages = inbox
    try:
        _ORIGINAL_DATA_RECEIVED(protocol, data)
    finally:
        protocol.messages = queue
    state = protocol.__dict__
    for item in inbox.items:
        if state.get("_uacell_claimed", 0) or not queue.empty():
            queue.put_nowait(item)  # within the room the inbox checked
            continue
        state["_uacell_claimed"] = 1
        ctx = state.get("_uacell_context")
        if ctx is None:  # the connection's own, as its task has one
            ctx = state["_uacell_context"] = contextvars.copy_context()
        task = eager(_run_one(protocol, *item), ctx)
        if task is not None:
            state["_uacell_waiting"] = task


async def _run_one(protocol: OPCUAProtocol, header: Any, buf: Any) -> None:
    """One message, as the connection's task runs it (``_process_received_message_loop``)."""
    try:
        await _ORIGINAL_PROCESS_ONE_MSG(protocol, header, buf)  # False: it closed the connection
    except Exception:
        log.exception("a message from %s failed", protocol.peer_name)
    finally:
        protocol.__dict__["_uacell_claimed"] -= 1


async def _process_one_msg(self: OPCUAProtocol, header: Any, buf: Any) -> bool:
    """asyncua's, run by the connection's task: after the message run at once before it, if that one
    waits. ``_uacell_claimed`` counts the messages taken and not done (run at once, or taken from the
    queue by the task): none may run at once meanwhile, not even while this one waits its turn."""
    state = self.__dict__
    state["_uacell_claimed"] = state.get("_uacell_claimed", 0) + 1
    try:
        waiting = state.pop("_uacell_waiting", None)
        if waiting is not None and not waiting.done():
            await asyncio.wait([waiting])
        result: bool = await _ORIGINAL_PROCESS_ONE_MSG(self, header, buf)
        return result
    finally:
        state["_uacell_claimed"] -= 1


def _with_session(original: Callable[[InternalSession, Any], Awaitable[Any]]) -> Callable[..., Awaitable[Any]]:
    """A session's service with the session known (``context.current_caller``) while it runs."""

    async def service(self: InternalSession, params: Any) -> Any:
        token = context.set_session(self)
        try:
            return await original(self, params)
        finally:
            context.reset_session(token)

    return service


_call = _with_session(_ORIGINAL_CALL)
_history_read = _with_session(_ORIGINAL_HISTORY_READ)


async def _read(self: InternalSession, params: Any) -> Any:
    results = await _ORIGINAL_READ(self, params)
    if self.external:
        context.run_read_hooks(self, params, results)
    return results


def attach() -> None:
    """Wrap asyncua's entry points (once per process; each looks up its server's pipeline)."""
    if UaProcessor._process_message is _process_message:
        return
    UaProcessor._process_message = _process_message
    UaProcessor.process_message = _process_secure_message
    UaProcessor.process = _process
    UaProcessor.open_secure_channel = _open_secure_channel
    OPCUAProtocol.data_received = _data_received
    OPCUAProtocol._process_one_msg = _process_one_msg
    OPCUAProtocol.connection_made = _connection_made
    InternalSession.call = _call
    InternalSession.read = _read
    InternalSession.history_read = _history_read
