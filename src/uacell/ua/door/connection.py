"""What uacell reads of asyncua's connection objects, in one place (asyncua keeps them private).

A ``UaProcessor`` is one client connection: its secure channel's policy (URI, mode, the client
certificate the channel was opened with) and its transport (to send an Error message before
closing). The internal server's table of client sessions and the per-server attachments uacell
hangs on it are here too, so no module outside the door (``uacell.ua.door``) touches an underscored asyncua name.
"""

from __future__ import annotations

import struct
from typing import Any

from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.crypto.security_policies import CryptographyNone, SecurityPolicyNone
from asyncua.server.address_space import AddressSpace
from asyncua.server.binary_server_asyncio import OPCUAProtocol
from asyncua.server.internal_server import InternalServer
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import uatcp_to_binary


def peer_address(processor: UaProcessor | None) -> str:
    """The client's IP address (``"unknown"`` when there is no connection)."""
    peer = getattr(processor, "name", None)
    if isinstance(peer, tuple) and peer:
        return str(peer[0])
    return str(peer or "unknown")


def channel_policy(processor: UaProcessor | None) -> tuple[str, ua.MessageSecurityMode]:
    """The security policy URI and mode of the processor's secure channel."""
    if processor is None:
        return SecurityPolicyNone.URI, ua.MessageSecurityMode.None_
    policy = processor._connection.security_policy
    return policy.URI, policy.Mode


def peer_certificate(processor: UaProcessor) -> bytes | None:
    """The client certificate the secure channel was opened with (None on SecurityPolicy None)."""
    cert: bytes | None = processor._connection.security_policy.peer_certificate
    return cert


def sent_certificate(processor: UaProcessor | None) -> bytes | None:
    """The server certificate the processor's secure channel sends: the certificate, followed by its CA's
    when it has a chain (door/certificate.py)."""
    if processor is None:
        return None
    cert: bytes | None = processor._connection.security_policy.host_certificate
    return cert


def send_error(processor: UaProcessor, code: int, reason: str) -> None:
    """An Error message (OPC 10000-6 7.1.2.5) to the client; the caller closes the connection."""
    message = ua.ErrorMessage(ua.StatusCode(code), reason)
    processor._transport.write(uatcp_to_binary(ua.MessageType.Error, message))


def permits(processor: UaProcessor, user: Any, typeid: ua.NodeId, body: Any) -> bool:
    """Do the channel's security policy's permissions (asyncua's, if any) let ``user`` make this request?
    A HistoryUpdate is let through as a HistoryRead is (asyncua's rules know no HistoryUpdate): the
    history answers each item itself (Bad_HistoryOperationUnsupported, docs/history.md); a SetTriggering
    as a SetMonitoringMode is (asyncua knows no SetTriggering either), a BrowseNext as a Browse, a Cancel
    (of the session's own requests) as a Read."""
    permissions = processor._connection.security_policy.permissions
    typeid = _AS_ASYNCUA_KNOWS.get(typeid, typeid)
    return permissions is None or permissions.check_validity(user, typeid, body) is not False


# the services asyncua's permission rules do not know, checked as the one they are like
_AS_ASYNCUA_KNOWS = {
    ua.NodeId(ua.ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary): ua.NodeId(
        ua.ObjectIds.HistoryReadRequest_Encoding_DefaultBinary
    ),
    ua.NodeId(ua.ObjectIds.SetTriggeringRequest_Encoding_DefaultBinary): ua.NodeId(
        ua.ObjectIds.SetMonitoringModeRequest_Encoding_DefaultBinary
    ),
    ua.NodeId(ua.ObjectIds.BrowseNextRequest_Encoding_DefaultBinary): ua.NodeId(
        ua.ObjectIds.BrowseRequest_Encoding_DefaultBinary
    ),
    ua.NodeId(ua.ObjectIds.CancelRequest_Encoding_DefaultBinary): ua.NodeId(
        ua.ObjectIds.ReadRequest_Encoding_DefaultBinary
    ),
}


# A SecureMessage of one chunk (OPC 10000-6 6.7.2): MessageType "MSG", ChunkType "F", MessageSize,
# SecureChannelId; the symmetric security header's TokenId; the sequence header's SequenceNumber and
# RequestId. 24 bytes before the body.
_SINGLE_MSG = struct.Struct("<3scIIIII")
_SINGLE_MSG_OVERHEAD = _SINGLE_MSG.size


def send_response(processor: UaProcessor, request_id: int, body: bytes) -> None:
    """A service response, already encoded, on the processor's secure channel (asyncua's
    ``send_response`` with uacell's encoder).

    On a channel without signing or encryption (SecurityPolicy None) a response that fits one chunk
    is framed here from the fixed layout, the same bytes asyncua's ``message_to_binary`` makes
    (tests/test_codec.py compares them), without its chunk objects; anything else is asyncua's."""
    if gone(processor):
        return  # nothing to answer (decision 105)
    conn = processor._connection
    if (
        type(conn.security_policy.symmetric_cryptography) is CryptographyNone
        and len(body) + _SINGLE_MSG_OVERHEAD <= conn._limits.max_send_buffer
    ):
        sequence = conn._sequence_number + 1
        if sequence >= 1 << 32:
            sequence = 1
        conn._sequence_number = sequence
        token = conn.security_token
        size = _SINGLE_MSG_OVERHEAD + len(body)
        header = _SINGLE_MSG.pack(b"MSG", b"F", size, token.ChannelId, token.TokenId, sequence, request_id)
        processor._transport.write(header + body)
        return
    message = ua.MessageType.SecureMessage
    data = conn.message_to_binary(body, message_type=message, request_id=request_id)
    processor._transport.write(data)


# A SecureMessage chunk's symmetric security header (TokenId) and sequence header (SequenceNumber,
# RequestId), after the 12 bytes of the message header.
_SYMMETRIC = struct.Struct("<III")


def plain_message(processor: UaProcessor, header: ua.Header, body: Buffer) -> tuple[Any, Buffer] | None:
    """A SecureMessage of one chunk on an open channel without signing or encryption (SecurityPolicy
    None), read from the fixed layout: its sequence header and its body, as asyncua's
    ``receive_from_header_and_body`` gives them, without its chunk objects, and ``body`` advanced past
    it. None for anything else, and for everything asyncua would refuse or act on (another token, a
    sequence number that is not the next, a chunk of a longer message, a size beyond the limits):
    asyncua's own path then handles the message (tests/test_codec.py compares the two)."""
    conn = processor._connection
    size = header.body_size
    if (
        header.ChunkType != ua.ChunkType.Single
        or conn._incoming_parts
        or type(conn.security_policy.symmetric_cryptography) is not CryptographyNone
        or not conn.is_open()
        or not _SYMMETRIC.size <= size <= len(body)
    ):
        return None
    limits, length = conn._limits, size - _SYMMETRIC.size
    if header.packet_size > limits.max_recv_buffer or not 0 < length <= (limits.max_message_size or length):
        return None
    token = conn.security_token
    token_id, sequence, request_id = _SYMMETRIC.unpack_from(body._data, body._cur_pos)
    peer = conn._peer_sequence_number
    if header.ChannelId != token.ChannelId or token_id != token.TokenId or (peer is not None and sequence != peer + 1):
        return None
    conn._peer_sequence_number = sequence
    # the message's own bytes (the buffer may go on with the next message's), as asyncua makes them
    message = Buffer(body.read(size)[_SYMMETRIC.size :])
    return ua.SequenceHeader(SequenceNumber=sequence, RequestId=request_id), message


def session_count(iserver: InternalServer) -> int:
    """Client sessions the server holds now (created, activated or not)."""
    return len(iserver._external_sessions)


_ATTACHED = "_uacell_attached"


def attach(iserver: InternalServer, key: str, value: Any) -> None:
    """Hang ``value`` on the internal server under ``key``, for code that has only asyncua's objects
    (a session reaches its server's uacell security set-up this way)."""
    attached = iserver.__dict__.setdefault(_ATTACHED, {})
    attached[key] = value


def attached(iserver: InternalServer, key: str) -> Any:
    """What ``attach`` hung under ``key``, or None."""
    return iserver.__dict__.get(_ATTACHED, {}).get(key)


# --- private state read for uacell's guards (inventory: "private name read") ------------------------
def connection(processor: UaProcessor | None) -> Any:
    """The processor's secure connection (its policy, token, open state), or None."""
    return getattr(processor, "_connection", None)


def channel_id(processor: UaProcessor | None) -> str:
    """The processor's SecureChannelId as audit events name it ("" when there is none)."""
    token = getattr(connection(processor), "security_token", None)
    return str(token.ChannelId) if token is not None else ""


def channel_open(processor: UaProcessor) -> bool:
    """Has the processor's secure channel been opened?"""
    return bool(processor._connection.is_open())


def gone(processor: UaProcessor) -> bool:
    """Has the processor's connection closed (or begun to)? Nothing may be written to it then: uvloop's
    transports raise on such a write, asyncio's drop it (decision 105)."""
    return bool(processor._transport.is_closing())


def close(processor: UaProcessor) -> None:
    """Close the processor's connection."""
    processor._transport.close()


def external_sessions(iserver: InternalServer) -> list[Any]:
    """The client sessions the server holds now."""
    return list(iserver._external_sessions.values())


def last_activity(session: Any, default: float) -> float:
    """When (``time.monotonic()``) the session last served a request."""
    return float(getattr(session, "_last_activity", default))


def buffer_bytes(body: Buffer) -> Any:
    """The bytes a Buffer reads from (asyncua builds a message's body as one Buffer over them)."""
    return body._data


def take_received(protocol: OPCUAProtocol, data: bytes) -> bytes:
    """What the connection had received and not parsed, followed by ``data``; none is kept now."""
    pending: bytes = protocol._buffer + data
    protocol._buffer = b""
    return pending


def set_received(protocol: OPCUAProtocol, data: bytes) -> None:
    protocol._buffer = data


def receive_buffer(protocol: OPCUAProtocol) -> int:
    """The connection's receive buffer (negotiated by the Hello; the configured one before)."""
    return int(protocol.processor._limits.max_recv_buffer)


def queued_bytes(protocol: OPCUAProtocol) -> int:
    """Bytes of the messages waiting in the connection's queue."""
    return sum(len(item[1]) for item in protocol.messages._queue if item[1] is not None)


def monitored_items(subscription: Any) -> int:
    """Monitored items of a subscription."""
    return len(subscription.monitored_item_srv._monitored_items)


def nodes(aspace: AddressSpace) -> Any:
    """The address space's node table (NodeId -> NodeData)."""
    return aspace._nodes


def set_nodes(aspace: AddressSpace, table: Any) -> None:
    """Replace the address space's node table (a snapshot's, restored)."""
    aspace._nodes = table


def calls_apart(processor: UaProcessor) -> set[Any]:
    """The calls (and history reads) of the connection running apart (``uacell.ua.pipeline``)."""
    running: set[Any] | None = processor.__dict__.get("_uacell_calls")
    if running is None:
        running = processor.__dict__["_uacell_calls"] = set()
    return running


def cancellable(processor: UaProcessor) -> dict[int, Any]:
    """The requests of the connection that a Cancel may end, by RequestHandle (their tasks)."""
    tasks: dict[int, Any] | None = processor.__dict__.get("_uacell_cancellable")
    if tasks is None:
        tasks = processor.__dict__["_uacell_cancellable"] = {}
    return tasks
