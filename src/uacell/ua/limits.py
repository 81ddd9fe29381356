"""What clients may hold and send: connections, sessions, subscriptions, monitored items, messages.

``install_limits(app)`` applies the ``[limits]`` configuration (docs/security.md, "Limits") to one
asyncua server before it listens:

- **descriptors**: the soft RLIMIT_NOFILE is raised to the hard one; connections and open files are
  kept below it with ``FD_RESERVE`` descriptors to spare, so the listening socket, durable saves and
  the log never starve (the connection limit is lowered, with a warning, when the system allows less);
- **transport**: the chunk size the server acknowledges (at least 8192 bytes, OPC 10000-6), and the
  maximum message size and chunk count it enforces on requests (Bad_RequestTooLarge); a chunk whose
  declared size exceeds what was negotiated (before a Hello: ``PRE_HELLO_BYTES``, and only a Hello is
  accepted first) closes the connection at once, before anything of it is buffered;
  ``pending_chunks_per_connection`` and ``pending_bytes_per_connection`` bound what waits behind a
  busy connection (beyond them it is closed). The Acknowledge
  announces no message-size or chunk-count limit (0): asyncua clients apply the limits a server
  announces to the *responses* they receive, so announcing the request limit would make them drop any
  large response (a Browse of all DataTypes, say);
- **connections** beyond the limit are closed as soon as they are accepted;
- a request whose body cannot be decoded (a malformed ExtensionObject, invalid UTF-8, a truncated
  array) answers ``Bad_DecodingError`` with one INFO line, instead of asyncua's Bad_InternalError and
  traceback;
- **sessions** (Bad_TooManySessions), **subscriptions** per session and in all
  (Bad_TooManySubscriptions), **monitored items** per subscription and in all
  (Bad_TooManyMonitoredItems, per item), **operations per request** (Bad_TooManyOperations, before
  any is carried out; published in ServerCapabilities/OperationLimits), through ``LimitedSession``,
  which uacell's session class inherits.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import resource
import struct
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from asyncua import ua
from asyncua.common.connection import TransportLimits
from asyncua.common.utils import Buffer, ServiceError
from asyncua.server.binary_server_asyncio import OPCUAProtocol
from asyncua.server.internal_session import InternalSession, SessionState
from asyncua.ua.ua_binary import struct_from_binary

from uacell.core.logs import RefusalLog
from uacell.ua import attributes, door, subscriptions, views
from uacell.ua.door import connection, publishing
from uacell.ua.pipeline import Next, Request

if TYPE_CHECKING:
    from uacell.config import LimitsConfig

log = logging.getLogger(__name__)

#: Descriptors kept free for the listening socket, files the server writes, logs and libraries.
FD_RESERVE = 64
#: The largest first message accepted: a Hello (its EndpointUrl is at most 4096 bytes) and some room.
PRE_HELLO_BYTES = 8192
_HEADER = struct.Struct("<3scI")  # MessageType, ChunkType, MessageSize (OPC 10000-6 7.1.2.2)


@dataclasses.dataclass
class ServerLimits:
    """The limits in force (after the descriptor check) and the sessions they count."""

    connections: int
    sessions: int
    subscriptions_per_session: int
    subscriptions: int
    monitored_items_per_subscription: int
    monitored_items: int
    max_chunk_size: int
    max_message_size: int
    pending_chunks_per_connection: int
    pending_bytes_per_connection: int
    operations_per_request: int
    handshake_timeout: float
    pending_per_address: int
    live_sessions: set[int] = dataclasses.field(default_factory=set)
    # One line per address and kind a minute: a flood of connections must not flood the log.
    refusals: RefusalLog = dataclasses.field(default_factory=lambda: RefusalLog(logger=log))

    @classmethod
    def from_config(cls, cfg: LimitsConfig) -> ServerLimits:
        names = {f.name for f in dataclasses.fields(cls)} - {"live_sessions", "refusals"}
        return cls(**{n: getattr(cfg, n) for n in names})

    @property
    def max_chunk_count(self) -> int:
        return math.ceil(self.max_message_size / self.max_chunk_size)


def raise_descriptor_limit(wanted: int) -> int:
    """Raise the soft RLIMIT_NOFILE towards the hard one (at least ``wanted`` if allowed); the new soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, wanted, 65536)
    if target > soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as exc:  # e.g. a hard limit the kernel caps lower (nr_open)
            log.warning("cannot raise the open-file limit from %d to %d: %s", soft, target, exc)
    return soft


def fit_descriptors(limits: ServerLimits, file_handles: int, soft: int) -> None:
    """Lower ``limits.connections`` so that connections + file handles + FD_RESERVE fit in ``soft``."""
    room = soft - file_handles - FD_RESERVE
    if limits.connections > room:
        fitted = max(1, room)
        log.warning(
            "open-file limit %d leaves room for %d connections (configured %d): lowering the limit",
            soft,
            fitted,
            limits.connections,
        )
        limits.connections = fitted


def install_limits(app: Any) -> ServerLimits:
    """Apply ``app.config.limits`` to ``app.server`` (call before the server starts listening)."""
    cfg = app.config.limits
    limits = ServerLimits.from_config(cfg)
    soft = raise_descriptor_limit(limits.connections + cfg.file_handles + FD_RESERVE)
    fit_descriptors(limits, cfg.file_handles, soft)
    server = app.server
    iserver = server.iserver
    door.tag(iserver, "limits", limits)
    door.configure(iserver, "InternalServer.max_connections", limits.connections)
    door.configure(iserver, "InternalServer.max_subscriptions", limits.subscriptions)
    door.configure(iserver, "InternalServer.max_pending_activation_seconds", cfg.activation_timeout)
    door.configure(iserver, "InternalServer.max_pending_messages_per_connection", limits.pending_chunks_per_connection)
    transport = ServerTransportLimits(
        max_recv_buffer=limits.max_chunk_size,
        max_send_buffer=limits.max_chunk_size,
        max_chunk_count=limits.max_chunk_count,
        max_message_size=limits.max_message_size,
    )
    door.configure(server, "Server.limits", transport)
    _demote_expected_refusals()
    log.info(
        "limits: %d connections, %d sessions, %d subscriptions, %d monitored items, requests up to %d bytes "
        "in chunks of %d; open-file limit %d",
        limits.connections,
        limits.sessions,
        limits.subscriptions,
        limits.monitored_items,
        limits.max_message_size,
        limits.max_chunk_size,
        soft,
    )
    return limits


def _limits_of(iserver: Any) -> ServerLimits | None:
    limits: ServerLimits | None = door.tagged(iserver, "limits")
    return limits


# --- transport -------------------------------------------------------------------------------------
MIN_BUFFER = 8192  # the smallest chunk OPC 10000-6 allows


@door.subclass("asyncua.common.connection.TransportLimits")
class ServerTransportLimits(TransportLimits):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
    """One connection's limits (asyncua copies the server's per connection): the chunk sizes follow
    the Hello; the message size and chunk count stay the server's, enforced, and are announced as 0."""

    max_recv_buffer: int
    max_send_buffer: int

    def create_acknowledge_and_set_limits(self, msg: ua.Hello) -> ua.Acknowledge:
        ack = ua.Acknowledge()
        # asyncua's reading of the fields, which its clients share: ReceiveBufferSize is what the
        # server sends in, SendBufferSize what it receives in. Never below the minimum chunk.
        ack.ReceiveBufferSize = max(MIN_BUFFER, min(msg.ReceiveBufferSize, self.max_send_buffer))
        ack.SendBufferSize = max(MIN_BUFFER, min(msg.SendBufferSize, self.max_recv_buffer))
        ack.MaxMessageSize = 0
        ack.MaxChunkCount = 0
        self.max_send_buffer = ack.ReceiveBufferSize
        self.max_recv_buffer = ack.SendBufferSize
        return ack


def _refuse_chunk(protocol: OPCUAProtocol, reason: str) -> None:
    log.warning("closing connection from %s: %s", protocol.peer_name, reason)
    connection.set_received(protocol, b"")
    if protocol.transport is not None:
        protocol.transport.abort()


def guard_bytes(self: OPCUAProtocol, data: bytes, original: Callable[[OPCUAProtocol, bytes], None]) -> None:
    """The bytes guard (``ua/pipeline.py``): each chunk's declared size checked before asyncua buffers
    it (asyncua buffers whatever is declared); complete chunks go on to ``original``."""
    limits = _limits_of(self.iserver)
    if limits is None:
        original(self, data)
        return
    pending = connection.take_received(self, data)
    while pending:
        if len(pending) < _HEADER.size:
            connection.set_received(self, pending)
            return
        kind, _, size = _HEADER.unpack_from(pending)
        hello_seen = door.tagged(self, "hello", False)
        if not hello_seen:
            if kind != b"HEL":
                _refuse_chunk(self, f"first message is {kind!r}, not a Hello")
                return
            allowed = PRE_HELLO_BYTES
        else:
            # The negotiated receive buffer (the configured one until the Hello is processed).
            allowed = min(connection.receive_buffer(self), limits.max_chunk_size)
        if size > allowed or size < _HEADER.size:
            _refuse_chunk(self, f"a {kind!r} chunk declares {size} bytes (at most {allowed} accepted)")
            return
        if len(pending) < size:
            connection.set_received(self, pending)
            return
        if kind == b"HEL":
            door.tag(self, "hello", True)
        queued = connection.queued_bytes(self)
        if queued + size > limits.pending_bytes_per_connection:
            _refuse_chunk(self, f"{queued} bytes wait unprocessed (at most {limits.pending_bytes_per_connection})")
            return
        # One complete chunk: asyncua parses and queues it (and closes on a full queue).
        original(self, pending[:size])
        if self.transport is None or self.transport.is_closing():
            connection.set_received(self, b"")
            return
        connection.set_received(self, b"")
        pending = pending[size:]


def _activated(protocol: OPCUAProtocol) -> bool:
    session = getattr(protocol.processor, "session", None)
    return session is not None and bool(session.is_activated())


def _peer(protocol: OPCUAProtocol) -> str:
    peer = getattr(protocol, "peer_name", None)
    return str(peer[0]) if isinstance(peer, tuple) and peer else "?"


def admit(protocol: OPCUAProtocol, transport: Any, original: Callable[[OPCUAProtocol, Any], None]) -> None:
    """The admission guard (``ua/pipeline.py``), when a connection is accepted: room is made for it.

    Connections that have not activated a session are the cheap ones to hold open (no Hello, a Hello
    dribbled in, a channel never used). A new connection closes the oldest of them from its own
    address once that address holds ``pending_per_address``, or the oldest of anyone's once all
    ``connections`` are taken; connections with an activated session are never closed for this.
    A connection must open its secure channel within ``handshake_timeout`` seconds."""
    limits = _limits_of(protocol.iserver)
    if limits is None:
        original(protocol, transport)
        return
    peername = transport.get_extra_info("peername")
    address = str(peername[0]) if isinstance(peername, tuple) and peername else "?"
    clients: list[OPCUAProtocol] = protocol.clients
    pending = [c for c in clients if not _activated(c)]
    mine = [c for c in pending if _peer(c) == address]
    victim = None
    if len(mine) >= limits.pending_per_address:
        victim = mine[0]
    elif len(clients) >= limits.connections and pending:
        victim = pending[0]
    if victim is not None:
        clients.remove(victim)  # its place is free now; connection_lost follows
        if victim.transport is not None:
            victim.transport.abort()
        limits.refusals.report(
            _peer(victim),
            "evicted",
            f"closed the oldest connection without a session from {_peer(victim)} to admit one from {address}",
        )
    original(protocol, transport)
    if protocol.processor is not None:  # when the activation deadline started (uacell.security.policy)
        door.tag(protocol.processor, "connected", time.monotonic())
    if protocol.transport is not None:  # admitted: it has handshake_timeout to open its channel
        late = asyncio.get_running_loop().call_later(limits.handshake_timeout, _handshake_late, protocol)
        door.tag(protocol, "handshake", late)


HANDSHAKE_GRACE = 0.01  # seconds: a look at the sockets between the deadline and the closing


def _handshake_late(protocol: OPCUAProtocol, looked: bool = False) -> None:
    processor = protocol.processor
    transport = protocol.transport
    if processor is None or transport is None or transport.is_closing():
        return
    if connection.channel_open(processor):
        return
    if not looked:
        # The deadline is the client's, not the server's: what arrived while the loop was busy past it
        # is read first. uvloop runs the timers that fell due before it reads the sockets (and a timer or
        # callback scheduled now, before it reads them too), so after a long callback this runs before
        # an OpenSecureChannel that came in time is even read: look again once the loop has read its
        # sockets (the channel opens as its request is read: nothing in between waits).
        late = asyncio.get_running_loop().call_later(HANDSHAKE_GRACE, _handshake_late, protocol, True)
        door.tag(protocol, "handshake", late)
        return
    limits = _limits_of(protocol.iserver)
    if limits is not None:
        address = _peer(protocol)
        message = (
            f"closed a connection from {address} that opened no secure channel within {limits.handshake_timeout:g} s"
        )
        limits.refusals.report(address, "handshake", message)
    transport.abort()


class _ExpectedRefusals(logging.Filter):
    """asyncua logs a request over the message limits as an ERROR; it is the client's doing, so uacell
    says it at INFO instead (asyncua's echo of every service fault is dropped by ``uacell.security.policy``)."""

    PREFIXES = ("Message size:", "Number of message chunks:")

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.ERROR and not record.exc_info and str(record.msg).startswith(self.PREFIXES):
            log.info("refused a request: %s", record.getMessage())
            return False
        return True


def _demote_expected_refusals() -> None:
    logger = logging.getLogger("asyncua.uaprotocol")
    if not any(isinstance(f, _ExpectedRefusals) for f in logger.filters):
        logger.addFilter(_ExpectedRefusals())


class DecodingStage:
    """The decoding stage (``ua/pipeline.py``): a request asyncua cannot decode answers
    Bad_DecodingError (asyncua: Bad_InternalError)."""

    async def __call__(self, request: Request, call_next: Next) -> Any:
        try:
            return await call_next(request)
        except (ServiceError, ua.UaStatusCodeError):
            raise
        except Exception as exc:
            if _decodes(request.typeid, request.body):
                raise  # not the request's fault: asyncua answers Bad_InternalError and logs it
            log.info("a request from %s cannot be decoded (%s): Bad_DecodingError", request.processor.name, exc)
            raise ServiceError(ua.StatusCodes.BadDecodingError) from None


def _decodes(typeid: Any, body: Buffer) -> bool:
    """Does the whole request (from its TypeId on) decode? Decided again only when a request failed."""
    cls = ua.extension_objects_by_typeid.get(typeid)
    if cls is None:
        return False
    try:
        struct_from_binary(cls, Buffer(connection.buffer_bytes(body)))
    except Exception:
        return False
    return True


# --- sessions, subscriptions, monitored items, operations ------------------------------------------------
#: ServerCapabilities/OperationLimits properties that ``operations_per_request`` sets.
_OPERATION_LIMITS = (
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerRead,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerWrite,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerMethodCall,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerBrowse,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerRegisterNodes,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerTranslateBrowsePathsToNodeIds,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxMonitoredItemsPerCall,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerHistoryReadData,
    ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerHistoryReadEvents,
)


async def publish_operation_limits(server: Any, limits: ServerLimits) -> None:
    """Write ``operations_per_request`` into ServerCapabilities/OperationLimits (where the nodes exist),
    and the continuation points a session may hold into MaxBrowseContinuationPoints."""
    values = [(ident, ua.Variant(limits.operations_per_request, ua.VariantType.UInt32)) for ident in _OPERATION_LIMITS]
    values.append((
        ua.ObjectIds.Server_ServerCapabilities_MaxBrowseContinuationPoints,
        ua.Variant(views.MAX_BROWSE_CONTINUATION_POINTS, ua.VariantType.UInt16),
    ))  # fmt: skip
    for ident, value in values:
        node = server.get_node(ua.NodeId(ident))
        try:
            await node.write_value(value)
        except ua.UaError:
            log.debug("no ServerCapabilities node %s", ident)


def check_operations(iserver: Any, count: int, service: str) -> None:
    """A client's request of ``count`` operations: Bad_NothingToDo for none (OPC 10000-4 7.38, every
    service with a list of operations), Bad_TooManyOperations above ``[limits]``."""
    if count == 0:
        raise ServiceError(ua.StatusCodes.BadNothingToDo)
    limits = _limits_of(iserver)
    if limits is not None and count > limits.operations_per_request:
        log.info("refused %s of %d operations (at most %d)", service, count, limits.operations_per_request)
        raise ServiceError(ua.StatusCodes.BadTooManyOperations)


@door.subclass("asyncua.server.internal_session.InternalSession")
class LimitedSession(views.StandardViews, subscriptions.OwnSubscriptions, InternalSession):  # type: ignore[misc]  # asyncua is untyped here
    """A session counted against ``[limits]``; subscriptions, monitored items and operations too. Its
    subscription services see its own subscriptions only (``uacell.ua.subscriptions``); the View and
    Attribute services answer as OPC 10000-4 says (``uacell.ua.views``, ``uacell.ua.attributes``)."""

    async def read(self, params: ua.ReadParameters) -> list[ua.DataValue]:
        check_operations(self.iserver, len(params.NodesToRead or ()), "Read")
        attributes.check_read(params)
        results = cast("list[ua.DataValue]", await super().read(params))
        attributes.shape_results(params, results)
        return results

    async def write(self, params: ua.WriteParameters) -> list[ua.StatusCode]:
        """The writes asyncua stores, each checked first: the node known, writable, given a value of its
        type. The request (its count, ``check_operations``), the roles, each item's form and the routes
        come before, in uacell's session (``security/policy.py``, ``binding/writes.py``)."""
        items = list(params.NodesToWrite or ())
        aspace = self.iserver.aspace
        types = getattr(self.iserver.method_service, "types", None)
        results: list[ua.StatusCode | None] = []
        passed: list[ua.WriteValue] = []
        for item in items:
            refusal = attributes.stored_write_refusal(aspace, item, types)
            results.append(ua.StatusCode(refusal) if refusal is not None else None)
            if refusal is None:
                passed.append(item)
        if passed:
            written = iter(cast("list[ua.StatusCode]", await super().write(ua.WriteParameters(NodesToWrite=passed))))
            results = [status if status is not None else next(written) for status in results]
        return cast("list[ua.StatusCode]", results)

    async def browse(self, params: ua.BrowseParameters) -> list[ua.BrowseResult]:
        check_operations(self.iserver, len(params.NodesToBrowse or ()), "Browse")
        return await super().browse(params)

    async def browse_next(self, params: ua.BrowseNextParameters) -> ua.BrowseNextResult:
        check_operations(self.iserver, len(params.ContinuationPoints or ()), "BrowseNext")
        return await super().browse_next(params)

    async def call(self, params: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        check_operations(self.iserver, len(params or ()), "Call")
        return cast("list[ua.CallMethodResult]", await super().call(params))

    async def translate_browsepaths_to_nodeids(self, params: list[ua.BrowsePath]) -> list[ua.BrowsePathResult]:
        check_operations(self.iserver, len(params or ()), "TranslateBrowsePathsToNodeIds")
        return await super().translate_browsepaths_to_nodeids(params)

    async def register_nodes(self, nodes: list[ua.NodeId]) -> list[ua.NodeId]:
        check_operations(self.iserver, len(nodes or ()), "RegisterNodes")
        return cast("list[ua.NodeId]", await super().register_nodes(nodes))

    async def unregister_nodes(self, nodes: list[ua.NodeId]) -> Any:
        check_operations(self.iserver, len(nodes or ()), "UnregisterNodes")
        return await super().unregister_nodes(nodes)

    async def history_read(self, params: ua.HistoryReadParameters) -> list[ua.HistoryReadResult]:
        check_operations(self.iserver, len(params.NodesToRead or ()), "HistoryRead")
        return cast("list[ua.HistoryReadResult]", await super().history_read(params))

    async def history_update(self, params: ua.HistoryUpdateParameters) -> list[ua.HistoryUpdateResult]:
        check_operations(self.iserver, len(params.HistoryUpdateDetails or ()), "HistoryUpdate")
        return cast("list[ua.HistoryUpdateResult]", await super().history_update(params))

    # the subscription services with a list of operations (the subscriptions' own rules: OwnSubscriptions)
    async def modify_monitored_items(self, params: ua.ModifyMonitoredItemsParameters) -> Any:
        check_operations(self.iserver, len(params.ItemsToModify or ()), "ModifyMonitoredItems")
        return await super().modify_monitored_items(params)

    async def delete_monitored_items(self, params: ua.DeleteMonitoredItemsParameters) -> Any:
        check_operations(self.iserver, len(params.MonitoredItemIds or ()), "DeleteMonitoredItems")
        return await super().delete_monitored_items(params)

    async def set_monitoring_mode(self, params: ua.SetMonitoringModeParameters) -> Any:
        check_operations(self.iserver, len(params.MonitoredItemIds or ()), "SetMonitoringMode")
        return await super().set_monitoring_mode(params)

    async def delete_subscriptions(self, ids: list[int]) -> list[ua.StatusCode]:
        if self.state != SessionState.Closed:  # a client's request, not a closing session's own clean-up
            check_operations(self.iserver, len(ids or ()), "DeleteSubscriptions")
        return await super().delete_subscriptions(ids)

    async def set_publishing_mode(self, params: ua.SetPublishingModeParameters) -> list[ua.StatusCode]:
        check_operations(self.iserver, len(params.SubscriptionIds or ()), "SetPublishingMode")
        return await super().set_publishing_mode(params)

    async def transfer_subscriptions(self, params: ua.TransferSubscriptionsParameters, callback: Any) -> Any:
        check_operations(self.iserver, len(params.SubscriptionIds or ()), "TransferSubscriptions")
        return await super().transfer_subscriptions(params, callback)

    async def create_session(self, params: ua.CreateSessionParameters, sockname: Any = None) -> Any:
        limits = _limits_of(self.iserver)
        if limits is not None:
            if len(limits.live_sessions) >= limits.sessions:
                log.warning("refused a session: %d sessions is the limit", limits.sessions)
                raise ServiceError(ua.StatusCodes.BadTooManySessions)
            limits.live_sessions.add(id(self))
        self.note_channel()
        if math.isnan(params.RequestedSessionTimeout):
            # asyncua's clamp lets NaN through, and a session whose timeout is NaN never times out
            params = dataclasses.replace(params, RequestedSessionTimeout=0.0)  # the server's shortest
        try:
            return await super().create_session(params, sockname=sockname)
        except BaseException:
            if limits is not None:
                limits.live_sessions.discard(id(self))
            raise

    async def close_session(self, delete_subs: bool = True) -> None:
        limits = _limits_of(self.iserver)
        try:
            await super().close_session(delete_subs)
        finally:
            if limits is not None:
                limits.live_sessions.discard(id(self))

    def room_for_subscriptions(self) -> int:
        limits = _limits_of(self.iserver)
        if limits is None:
            return super().room_for_subscriptions()
        return limits.subscriptions_per_session - len(self._own_subscriptions())

    async def create_subscription(
        self, params: ua.CreateSubscriptionParameters, callback: Any, request_callback: Any = None
    ) -> ua.CreateSubscriptionResult:
        if self.room_for_subscriptions() <= 0:
            log.info("refused a subscription: the session has as many as [limits] allows")
            raise ServiceError(ua.StatusCodes.BadTooManySubscriptions)
        # OPC 10000-4 5.14.2.2: a request of 0 (or below the fastest interval) is revised to the fastest
        # the server supports. asyncua kept 0 and ran no loop for it: no keep-alive, no lifetime (decision 79).
        interval, at_once = subscriptions.revised_interval(params.RequestedPublishingInterval)
        lifetime, keep_alive = self.revise_counts(params.RequestedLifetimeCount, params.RequestedMaxKeepAliveCount)
        params = dataclasses.replace(
            params,
            RequestedPublishingInterval=interval,
            RequestedLifetimeCount=lifetime,
            RequestedMaxKeepAliveCount=keep_alive,
        )
        result: ua.CreateSubscriptionResult = await super().create_subscription(
            params, callback, request_callback=request_callback
        )
        sub = self.subscription_service.subscriptions.get(result.SubscriptionId)
        if sub is not None:
            publishing.publish_at_once(sub, at_once)  # its changes still go out at once (decision 76)
            publishing.limit_notifications(sub, params.MaxNotificationsPerPublish)
            door.tag(sub, "owner", subscriptions.identity(self))
        return result

    async def create_monitored_items(
        self, params: ua.CreateMonitoredItemsParameters
    ) -> list[ua.MonitoredItemCreateResult]:
        check_operations(self.iserver, len(params.ItemsToCreate or ()), "CreateMonitoredItems")
        limits = _limits_of(self.iserver)
        sub = self._subscription(params.SubscriptionId)
        items = list(params.ItemsToCreate or [])
        room = len(items)
        if limits is not None:
            every_sub = self.subscription_service.subscriptions.values()
            in_sub = connection.monitored_items(sub)
            in_all = sum(connection.monitored_items(s) for s in every_sub)
            room = max(0, min(limits.monitored_items_per_subscription - in_sub, limits.monitored_items - in_all))
        if len(items) <= room:
            return cast("list[ua.MonitoredItemCreateResult]", await super().create_monitored_items(params))
        log.info("refused %d monitored item(s): limit reached", len(items) - room)
        created: list[ua.MonitoredItemCreateResult] = []
        if room:
            created = await super().create_monitored_items(dataclasses.replace(params, ItemsToCreate=items[:room]))
        refused = ua.MonitoredItemCreateResult(StatusCode=ua.StatusCode(ua.StatusCodes.BadTooManyMonitoredItems))
        return [*created, *(dataclasses.replace(refused) for _ in items[room:])]
