"""uacell's written-out encoder of the Call response (ua/codec.py) gives asyncua's bytes, and asyncua
decodes them back to the response."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import pytest
from asyncua import ua
from asyncua.common.utils import Buffer, NotEnoughData
from asyncua.ua.ua_binary import nodeid_from_binary, struct_from_binary, struct_to_binary
from asyncua.ua.uaerrors import UaError
from hypothesis import given, settings
from hypothesis import strategies as st

from uacell.ua.codec import decode_call_parameters, decode_request_header, encode_call_response

S = ua.StatusCodes
CODES = st.sampled_from([S.Good, S.BadInvalidState, S.BadTypeMismatch, S.BadUserAccessDenied, S.GoodClamped])
TEXT = st.text(max_size=12)
VARIANTS = st.one_of(
    st.builds(lambda x: ua.Variant(x, ua.VariantType.Int32), st.integers(-(2**31), 2**31 - 1)),
    st.builds(lambda x: ua.Variant(x, ua.VariantType.Double), st.floats(allow_nan=False)),
    st.builds(lambda x: ua.Variant(x, ua.VariantType.String), TEXT),
    st.builds(lambda x: ua.Variant(x, ua.VariantType.Boolean), st.booleans()),
    st.builds(lambda x: ua.Variant(x, ua.VariantType.Int32, is_array=True), st.lists(st.integers(0, 9), max_size=3)),
    st.just(ua.Variant()),
)
DIAGNOSTICS = st.one_of(
    st.just(ua.DiagnosticInfo()),
    st.builds(lambda text: ua.DiagnosticInfo(AdditionalInfo=text), TEXT),
    st.builds(lambda code: ua.DiagnosticInfo(SymbolicId=3, InnerStatusCode=ua.StatusCode(code)), CODES),
)


def _lists(items: st.SearchStrategy[object]) -> st.SearchStrategy[object]:
    return st.one_of(st.none(), st.lists(items, max_size=4))


RESULTS = st.builds(
    lambda code, inputs, diagnostics, outputs: ua.CallMethodResult(
        StatusCode=ua.StatusCode(code),
        InputArgumentResults=inputs,
        InputArgumentDiagnosticInfos=diagnostics,
        OutputArguments=outputs,
    ),
    CODES,
    _lists(st.builds(ua.StatusCode, CODES)),
    _lists(DIAGNOSTICS),
    _lists(VARIANTS),
)


def _response(results: object, diagnostics: object, handle: int, code: int, head: object, table: object) -> object:
    response = ua.CallResponse()
    response.Results = results
    response.DiagnosticInfos = diagnostics
    h = response.ResponseHeader
    h.RequestHandle, h.ServiceResult, h.ServiceDiagnostics, h.StringTable = handle, ua.StatusCode(code), head, table
    return response


RESPONSES = st.builds(
    _response,
    _lists(RESULTS),
    _lists(DIAGNOSTICS),
    st.integers(0, 2**32 - 1),
    CODES,
    DIAGNOSTICS,
    _lists(st.one_of(st.none(), TEXT)),
)


@settings(max_examples=300, deadline=None)
@given(RESPONSES)
def test_the_call_response_is_encoded_as_asyncua_encodes_it(response: ua.CallResponse) -> None:
    encoded = encode_call_response(response)
    assert encoded == struct_to_binary(response)
    back = struct_from_binary(ua.CallResponse, Buffer(encoded))
    assert back.ResponseHeader.RequestHandle == response.ResponseHeader.RequestHandle
    assert len(back.Results) == len(response.Results or [])


def test_a_response_header_with_content_is_encoded_as_asyncua_encodes_it() -> None:
    response = ua.CallResponse()
    response.ResponseHeader.Timestamp = datetime(2026, 11, 26, 3, 0, tzinfo=UTC)
    response.ResponseHeader.AdditionalHeader = ua.ExtensionObject(TypeId=ua.NodeId(5, 2), Body=b"xyz")
    response.Results = [ua.CallMethodResult(OutputArguments=[ua.Variant(7, ua.VariantType.UInt16)])]
    assert encode_call_response(response) == struct_to_binary(response)


# --- decoding: the request header and the Call parameters, as asyncua decodes them ----------------
NAMESPACES = st.integers(0, 2**16 - 1)
NODE_IDS = st.one_of(
    st.builds(lambda i: ua.NodeId(i, 0, ua.NodeIdType.TwoByte), st.integers(0, 255)),
    st.builds(lambda i, ns: ua.NodeId(i, ns, ua.NodeIdType.FourByte), st.integers(0, 2**16 - 1), st.integers(0, 255)),
    st.builds(lambda i, ns: ua.NodeId(i, ns, ua.NodeIdType.Numeric), st.integers(0, 2**32 - 1), NAMESPACES),
    st.builds(lambda i, ns: ua.NodeId(i, ns, ua.NodeIdType.String), st.text(max_size=20), NAMESPACES),
    st.builds(lambda i, ns: ua.NodeId(i, ns, ua.NodeIdType.ByteString), st.binary(max_size=40), NAMESPACES),
    st.builds(lambda i, ns: ua.NodeId(i, ns, ua.NodeIdType.Guid), st.uuids(), NAMESPACES),
)
SCALARS = st.one_of(
    VARIANTS,
    *(
        st.builds(lambda x, t=vtype: ua.Variant(x, t), values)
        for vtype, values in (
            (ua.VariantType.SByte, st.integers(-128, 127)),
            (ua.VariantType.Byte, st.integers(0, 255)),
            (ua.VariantType.Int16, st.integers(-(2**15), 2**15 - 1)),
            (ua.VariantType.UInt16, st.integers(0, 2**16 - 1)),
            (ua.VariantType.UInt32, st.integers(0, 2**32 - 1)),
            (ua.VariantType.Int64, st.integers(-(2**63), 2**63 - 1)),
            (ua.VariantType.UInt64, st.integers(0, 2**64 - 1)),
            (ua.VariantType.Float, st.floats(width=32, allow_nan=False)),
            (ua.VariantType.String, st.none()),
            (ua.VariantType.NodeId, NODE_IDS),
            (ua.VariantType.DateTime, st.datetimes(timezones=st.just(UTC))),
            (ua.VariantType.ByteString, st.binary(max_size=8)),
        )
    ),
    st.builds(
        lambda d: ua.Variant([d], ua.VariantType.ExtensionObject),
        st.builds(lambda name: ua.KeyValuePair(ua.QualifiedName(name, 1), ua.Variant(1.5)), TEXT),
    ),
)
EXTRA = st.one_of(
    st.just(ua.ExtensionObject()),
    st.builds(lambda body: ua.ExtensionObject(ua.NodeId(4242, 3), body), st.binary(max_size=8)),
)


def _request(token, handle, diagnostics, audit, timeout, extra, calls):
    request = ua.CallRequest()
    h = request.RequestHeader
    h.AuthenticationToken, h.RequestHandle, h.ReturnDiagnostics = token, handle, diagnostics
    h.AuditEntryId, h.TimeoutHint, h.AdditionalHeader = audit, timeout, extra
    request.Parameters.MethodsToCall = [ua.CallMethodRequest(obj, method, inputs) for obj, method, inputs in calls]
    return request


REQUESTS = st.builds(
    _request,
    NODE_IDS,
    st.integers(0, 2**32 - 1),
    st.integers(0, 2**32 - 1),
    st.one_of(st.none(), TEXT),
    st.integers(0, 2**32 - 1),
    EXTRA,
    st.lists(st.tuples(NODE_IDS, NODE_IDS, st.lists(SCALARS, max_size=3)), max_size=3),
)


def _shape(value: object) -> object:
    """Everything a decoded value holds, its types included (asyncua's NodeId equality ignores the
    encoding kind; this does not)."""
    if isinstance(value, list):
        return [_shape(v) for v in value]
    fields = getattr(value, "__dataclass_fields__", None)
    if fields is None:
        return (type(value).__name__, value)
    return (type(value).__name__, {name: _shape(getattr(value, name)) for name in fields})


@settings(max_examples=300, deadline=None)
@given(REQUESTS, st.binary(max_size=3))
def test_a_request_is_decoded_as_asyncua_decodes_it(request: ua.CallRequest, after: bytes) -> None:
    data = struct_to_binary(request) + after
    theirs = Buffer(data)
    expected = (nodeid_from_binary(theirs), struct_from_binary(ua.RequestHeader, theirs))
    expected_parameters = struct_from_binary(ua.CallParameters, theirs)
    ours = Buffer(data)
    decoded = decode_request_header(ours)
    assert _shape(decoded) == _shape(expected)
    assert _shape(decode_call_parameters(ours)) == _shape(expected_parameters)
    assert ours.cur_pos == theirs.cur_pos and len(ours) == len(after)


@settings(max_examples=200, deadline=None)
@given(REQUESTS, st.data())
def test_a_request_cut_short_is_refused_as_asyncua_refuses_it(request: ua.CallRequest, data: st.DataObject) -> None:
    whole = struct_to_binary(request)
    size = data.draw(st.integers(0, len(whole) - 1))
    # the message's bytes cut, or a Buffer that ends before its bytes do
    make = data.draw(st.sampled_from([lambda: Buffer(whole[:size]), lambda: Buffer(whole, 0, size)]))

    def outcome(decode: object) -> str:
        try:
            decode(make())  # type: ignore[operator]
        except NotEnoughData:
            return "cut short"
        except Exception as e:  # asyncua's own refusal of a malformed part, where ours hands it over
            return type(e).__name__
        return "decoded"

    def asyncua_decode(buffer: Buffer) -> None:
        nodeid_from_binary(buffer)
        struct_from_binary(ua.RequestHeader, buffer)
        struct_from_binary(ua.CallParameters, buffer)

    def our_decode(buffer: Buffer) -> None:
        decode_request_header(buffer)
        decode_call_parameters(buffer)

    assert outcome(our_decode) == outcome(asyncua_decode)


def test_a_request_of_an_unknown_kind_is_a_refusal_not_a_server_error() -> None:
    """A NodeId encoding byte no NodeId has: asyncua's decoder raises a ValueError (logged as a server
    error); uacell's says UaError, which the pipeline answers by closing the connection with one line."""
    request = _request(ua.NodeId(1, 0), 7, 0, None, 0, ua.ExtensionObject(), [])
    data = bytearray(struct_to_binary(request))
    data[0] = 0x3F  # the TypeId's encoding byte
    with pytest.raises(ValueError):
        nodeid_from_binary(Buffer(bytes(data)))
    with pytest.raises(UaError) as refused:
        decode_request_header(Buffer(bytes(data)))
    assert not isinstance(refused.value, NotEnoughData)


# --- framing: a response on its secure channel ---------------------------------------------------------


class _Transport:
    """Keeps what is written, as a transport that is still open; ``closed`` is one the peer has gone from
    (uvloop's raises on a write then)."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []
        self.closed = False

    def is_closing(self) -> bool:
        return self.closed

    def write(self, data: bytes) -> None:
        if self.closed:
            raise RuntimeError("unable to perform operation: the handler is closed")
        self.sent.append(bytes(data))


def _channel(policy: Any, max_send: int = 65535, sequence: int = 0) -> Any:
    from asyncua.common.connection import SecureConnection, TransportLimits

    conn = SecureConnection(policy, TransportLimits(max_recv_buffer=65535, max_send_buffer=max_send))
    conn.security_token.ChannelId, conn.security_token.TokenId = 7, 3
    conn._sequence_number = sequence
    return conn


class _Processor:
    def __init__(self, conn: Any) -> None:
        self._connection = conn
        self._transport = _Transport()


@settings(max_examples=60, deadline=None)
@given(
    body=st.binary(min_size=1, max_size=20_000),
    max_send=st.sampled_from([8192, 16384, 65535]),
    request_id=st.integers(0, 2**32 - 1),
    sequence=st.sampled_from([0, 41, 2**32 - 2, 2**32 - 1]),
)
def test_a_response_is_framed_as_asyncua_frames_it(body: bytes, max_send: int, request_id: int, sequence: int) -> None:
    """One chunk on SecurityPolicy None framed from the fixed layout, a larger body in asyncua's chunks:
    the bytes asyncua's ``message_to_binary`` sends, and the channel's sequence number where asyncua
    leaves it (wrapping to 1 after 2**32 - 1, OPC 10000-6 6.7.2.4)."""
    from asyncua.crypto.security_policies import SecurityPolicyNone

    from uacell.ua.door.connection import send_response

    theirs = _channel(SecurityPolicyNone(), max_send, sequence)
    expected = theirs.message_to_binary(body, message_type=ua.MessageType.SecureMessage, request_id=request_id)
    processor = _Processor(_channel(SecurityPolicyNone(), max_send, sequence))
    send_response(processor, request_id, body)
    assert processor._transport.sent == [expected]
    assert processor._connection._sequence_number == theirs._sequence_number


def test_a_response_to_a_client_that_went_is_not_written() -> None:
    """Decision 105: the client closed its connection while its request ran; its answer goes nowhere."""
    from asyncua.crypto.security_policies import SecurityPolicyNone

    from uacell.ua.door.connection import send_response

    processor = _Processor(_channel(SecurityPolicyNone()))
    processor._transport.closed = True
    send_response(processor, 5, b"body")
    assert processor._transport.sent == []


def test_a_signed_channel_is_framed_by_asyncua() -> None:
    """A channel whose symmetric cryptography is not None's (signing, encrypting) is never framed here."""
    from asyncua.crypto.security_policies import CryptographyNone, SecurityPolicyNone

    class Signing(CryptographyNone):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
        def signature_size(self) -> int:
            return 4

        def signature(self, data: bytes) -> bytes:
            return b"SIGN"

    policy = SecurityPolicyNone()
    policy.symmetric_cryptography = Signing()
    theirs = _channel(policy)
    expected = theirs.message_to_binary(b"body", message_type=ua.MessageType.SecureMessage, request_id=5)
    assert expected.endswith(b"SIGN")
    processor = _Processor(_channel(policy))
    from uacell.ua.door.connection import send_response

    send_response(processor, 5, b"body")
    assert processor._transport.sent == [expected]


def _request_chunk(channel: int, token: int, sequence: int, request_id: int, body: bytes, chunk: bytes = b"F") -> bytes:
    import struct

    return struct.pack("<3scIIIII", b"MSG", chunk, 24 + len(body), channel, token, sequence, request_id) + body


def _received(data: bytes) -> tuple[ua.Header, Buffer]:
    from asyncua.ua.ua_binary import header_from_binary

    buffer = Buffer(data)
    return header_from_binary(buffer), buffer


def _open_channel(policy: Any = None, peer: int | None = 40, max_message: int = 0) -> Any:
    from asyncua.crypto.security_policies import SecurityPolicyNone

    conn = _channel(policy or SecurityPolicyNone())
    conn._open = True
    conn._peer_sequence_number = peer
    conn._limits.max_message_size = max_message
    return conn


@settings(max_examples=60, deadline=None)
@given(
    body=st.binary(min_size=1, max_size=4000),
    request_id=st.integers(0, 2**32 - 1),
    peer=st.sampled_from([None, 0, 40, 2**32 - 2]),
    trailing=st.binary(max_size=16),
)
def test_a_one_chunk_request_is_read_as_asyncua_reads_it(
    body: bytes, request_id: int, peer: int | None, trailing: bytes
) -> None:
    """A one-chunk SecureMessage on SecurityPolicy None read from the fixed layout: the sequence header
    and body asyncua's ``receive_from_header_and_body`` gives, the buffer advanced as far, and the
    client's sequence number where asyncua leaves it."""
    from uacell.ua.door.connection import plain_message

    sequence = 1 if peer is None else peer + 1
    data = _request_chunk(7, 3, sequence, request_id, body) + trailing
    theirs = _open_channel(peer=peer)
    header, buffer = _received(data)
    message = theirs.receive_from_header_and_body(header, buffer)
    ours = _Processor(_open_channel(peer=peer))
    header2, buffer2 = _received(data)
    read = plain_message(ours, header2, buffer2)
    assert read is not None
    seqhdr, got = read
    assert seqhdr == message.SequenceHeader()
    assert bytes(got) == bytes(message.body()) == body
    assert buffer2.cur_pos == buffer.cur_pos and len(buffer2) == len(buffer) == len(trailing)
    assert ours._connection._peer_sequence_number == theirs._peer_sequence_number == sequence


@pytest.mark.parametrize(
    ("case", "refused_by_asyncua"),
    [
        ("another token", True),
        ("another channel", True),
        ("a sequence number that is not the next", True),
        ("the next token (a renewal)", False),
        ("a wrapped sequence number", False),
        ("an intermediate chunk", False),
        ("a message under way", False),
        ("a closed channel", False),
        ("a signing channel", False),
        ("larger than max_message_size", True),
    ],
)
def test_anything_else_is_left_to_asyncua(case: str, refused_by_asyncua: bool) -> None:
    """Every message but the plain common case goes asyncua's way, untouched: nothing read, the buffer
    and the channel's state as they were (asyncua then accepts it, revolves a token or refuses it)."""
    from asyncua.crypto.security_policies import CryptographyNone, SecurityPolicyNone

    from uacell.ua.door.connection import plain_message

    class Signing(CryptographyNone):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
        def signature_size(self) -> int:
            return 4

    policy = SecurityPolicyNone()
    if case == "a signing channel":
        policy.symmetric_cryptography = Signing()
    peer = 2**32 - 1 if case == "a wrapped sequence number" else 40
    conn = _open_channel(policy, peer=peer, max_message=100 if case == "larger than max_message_size" else 0)
    conn.next_security_token.ChannelId, conn.next_security_token.TokenId = 7, 4
    channel, token, sequence, chunk = 7, 3, 41, b"F"
    if case == "another token":
        token = 9
    elif case == "the next token (a renewal)":
        token = 4
    elif case == "another channel":
        channel = 8
    elif case == "a sequence number that is not the next":
        sequence = 43
    elif case == "a wrapped sequence number":
        sequence = 1
    elif case == "an intermediate chunk":
        chunk = b"C"
    elif case == "a message under way":
        conn._incoming_parts = [object()]
    elif case == "a closed channel":
        conn._open = False
    header, buffer = _received(_request_chunk(channel, token, sequence, 5, b"x" * 200, chunk))
    assert plain_message(_Processor(conn), header, buffer) is None
    assert buffer.cur_pos == 12 and conn._peer_sequence_number == peer and conn.security_token.TokenId == 3
    if case in ("a message under way", "a closed channel", "a signing channel"):
        return
    if refused_by_asyncua:
        with pytest.raises((UaError, ua.UaStatusCodeError)):
            conn.receive_from_header_and_body(header, buffer)
    else:
        conn.receive_from_header_and_body(header, buffer)  # accepted (a chunk kept, a token revolved)
