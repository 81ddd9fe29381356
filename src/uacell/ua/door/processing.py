"""asyncua's request path, wrapped once per process (``attach``): the entry points of a connection,
a secure channel and a session, each handing over to the pipeline of the server a connection reached
(``uacell.ua.pipeline``: its stages and guards, ``install``). An asyncua server without a pipeline
runs asyncua's processing alone. What each wrapper replaces: inventory.py, docs/asyncua.md."""

from __future__ import annotations

import asyncio
import contextvars
import logging
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from asyncua import ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.server.binary_server_asyncio import OPCUAProtocol
from asyncua.server.internal_session import InternalSession
from asyncua.server.uaprocessor import UaProcessor

from uacell.core.background import eager
from uacell.ua import context
from uacell.ua.codec import decode_request_header
from uacell.ua.door import check_versions, connection, enums, monitoring, patch, publishing, record

log = logging.getLogger(__name__)


class Hooks(Protocol):
    """What a server's pipeline offers the wrapped entry points (``uacell.ua.pipeline.Pipeline``)."""

    admission: Any  # (protocol, transport, asyncua's connection_made) -> None
    bytes_guard: Any  # (protocol, data, received) -> None
    channel_guard: Any  # ua.pipeline.ChannelGuard: .opening/.renewing, .open/.renew, .closing
    refused: Any  # (processor, exception) -> None

    async def message(self, processor: UaProcessor, typeid: ua.NodeId, header: Any, seqhdr: Any, body: Buffer) -> Any:
        """One service request, its TypeId and header decoded."""


def hooks_of(iserver: Any) -> Hooks | None:
    hooks: Hooks | None = getattr(iserver, "_uacell_pipeline", None)
    return hooks


def install(iserver: Any, hooks: Hooks) -> None:
    """Run ``hooks`` for every connection to ``iserver`` (an asyncua InternalServer)."""
    attach()
    iserver._uacell_pipeline = hooks


# asyncua's own entry points, as they were before ``attach()``.
_P = "asyncua.server.uaprocessor.UaProcessor."
_T = "asyncua.server.binary_server_asyncio.OPCUAProtocol."
_S = "asyncua.server.internal_session.InternalSession."
_ORIGINAL_PROCESS_MESSAGE = UaProcessor._process_message
_ORIGINAL_PROCESS_SECURE_MESSAGE = UaProcessor.process_message
_ORIGINAL_PROCESS = UaProcessor.process
_ORIGINAL_OPEN = UaProcessor.open_secure_channel
_ORIGINAL_SEND = UaProcessor.send_response
_ORIGINAL_DATA_RECEIVED = OPCUAProtocol.data_received
_ORIGINAL_PROCESS_ONE_MSG = OPCUAProtocol._process_one_msg
_ORIGINAL_CONNECTION_MADE = OPCUAProtocol.connection_made
_ORIGINAL_CALL = InternalSession.call
_ORIGINAL_READ = InternalSession.read
_ORIGINAL_HISTORY_READ = InternalSession.history_read


def asyncua_process_message(
    processor: UaProcessor, typeid: ua.NodeId, header: Any, seqhdr: Any, body: Buffer
) -> Awaitable[Any]:
    """asyncua's own processing of a service request (``UaProcessor._process_message``)."""
    return _ORIGINAL_PROCESS_MESSAGE(processor, typeid, header, seqhdr, body)  # type: ignore[no-any-return]


def fault(processor: UaProcessor, header: Any, seqhdr: Any, code: int) -> None:
    """A ServiceFault with ``code`` for the request."""
    response = ua.ServiceFault()
    response.ResponseHeader.ServiceResult = ua.StatusCode(code)
    processor.send_response(header.RequestHandle, seqhdr, response)


async def _process_secure_message(self: UaProcessor, seqhdr: Any, body: Buffer) -> Any:
    """asyncua's ``process_message`` (a request's TypeId and header decoded, then the request handled,
    a refusal answered with a ServiceFault), the header decoded by ``ua/codec.py`` (decision 50)."""
    if hooks_of(self.iserver) is None:
        return await _ORIGINAL_PROCESS_SECURE_MESSAGE(self, seqhdr, body)
    typeid, header = decode_request_header(body)
    try:
        return await self._process_message(typeid, header, seqhdr, body)
    except (ServiceError, ua.UaStatusCodeError) as exc:
        code = exc.code
    except Exception:
        log.exception("a %s request failed", typeid)
        code = ua.StatusCodes.BadInternalError
    fault(self, header, seqhdr, code)
    return True


def _process_message(
    self: UaProcessor, typeid: ua.NodeId, requesthdr: Any, seqhdr: Any, body: Buffer
) -> Awaitable[Any]:
    hooks = hooks_of(self.iserver)
    if hooks is None:
        return _ORIGINAL_PROCESS_MESSAGE(self, typeid, requesthdr, seqhdr, body)  # type: ignore[no-any-return]
    return hooks.message(self, typeid, requesthdr, seqhdr, body)


async def _process(self: UaProcessor, header: ua.Header, body: Buffer) -> Any:
    hooks = hooks_of(self.iserver)
    if hooks is None:
        return await _ORIGINAL_PROCESS(self, header, body)
    guard = hooks.channel_guard
    try:
        if header.MessageType == ua.MessageType.SecureMessage:
            plain = connection.plain_message(self, header, body)
            if plain is not None:  # the common case read from its fixed layout
                return await self.process_message(*plain)
        if guard is not None and header.MessageType == ua.MessageType.SecureClose:
            return await guard.closing(self, lambda: _ORIGINAL_PROCESS(self, header, body))
        if guard is None or header.MessageType != ua.MessageType.SecureOpen:
            return await _ORIGINAL_PROCESS(self, header, body)
        checked = guard.renewing if self._connection.is_open() else guard.opening
        return await checked(self, header, body, lambda: _ORIGINAL_PROCESS(self, header, body))
    except (ua.UaError, ServiceError) as exc:
        # What a client's message provoked below the request stages (asyncua would log a traceback
        # at ERROR and keep the connection): refused in one line, and the connection closed.
        if hooks.refused is not None:
            hooks.refused(self, exc)
        return False


def _open_secure_channel(self: UaProcessor, algohdr: Any, seqhdr: Any, body: Buffer) -> Any:
    hooks = hooks_of(self.iserver)
    guard = hooks.channel_guard if hooks is not None else None
    if guard is not None:
        (guard.renew if self._connection.is_open() else guard.open)(self, algohdr, body)
    return _ORIGINAL_OPEN(self, algohdr, seqhdr, body)


def _send_response(
    self: UaProcessor, requesthandle: Any, seqhdr: Any, response: Any, msgtype: Any = ua.MessageType.SecureMessage
) -> None:
    """asyncua's ``send_response``; nothing once the connection is gone (decision 105): a client that went
    while its request ran gets no answer, and under uvloop the write would raise."""
    if connection.gone(self):
        return
    _ORIGINAL_SEND(self, requesthandle, seqhdr, response, msgtype)


def _connection_made(self: OPCUAProtocol, transport: Any) -> None:
    hooks = hooks_of(self.iserver)
    if hooks is None or hooks.admission is None:
        _ORIGINAL_CONNECTION_MADE(self, transport)
        return
    hooks.admission(self, transport, _ORIGINAL_CONNECTION_MADE)


def _data_received(self: OPCUAProtocol, data: bytes) -> None:
    hooks = hooks_of(self.iserver)
    if hooks is None or self.processor is None:
        _ORIGINAL_DATA_RECEIVED(self, data)
    elif hooks.bytes_guard is None:
        _received(self, data)
    else:
        hooks.bytes_guard(self, data, _received)


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
    """Check the installed asyncua, then wrap its entry points (once per process; each looks up its
    server's pipeline)."""
    if UaProcessor._process_message is _process_message:
        return
    check_versions()
    patch(_P + "_process_message", _process_message)
    patch(_P + "process_message", _process_secure_message)
    patch(_P + "process", _process)
    patch(_P + "open_secure_channel", _open_secure_channel)
    patch(_P + "send_response", _send_response)
    patch(_T + "data_received", _data_received)
    patch(_T + "_process_one_msg", _process_one_msg)
    patch(_T + "connection_made", _connection_made)
    patch(_S + "call", _call)
    patch(_S + "read", _read)
    patch(_S + "history_read", _history_read)
    publishing.install()  # a client's 0 ms subscription: one publication per event-loop turn
    monitoring.install()  # monitored items report by the standards (decision 78)
    enums.install()  # an enumeration's unknown number refused by its service, not by the decoder
    record(_T + "messages")  # swapped by _received for each parse
