"""The binary encodings uacell meets on every call, written out (decisions 49 and 50).

asyncua encodes and decodes every structure through per-field closures built from its dataclasses;
for what every call carries that was about a fifth of a call's server time:

- ``encode_call_response``: the Call response, the same bytes as asyncua's ``struct_to_binary``;
- ``decode_request_header``: a request's TypeId and RequestHeader (every request has them);
- ``decode_call_parameters``: the Call request's parameters.

Both decoders give objects equal to asyncua's ``nodeid_from_binary``/``struct_from_binary`` and
leave the buffer where asyncua would; what varies in kind and is rare in a request (Guid or
expanded NodeIds, arrays, extension objects with a body, Variants of other than the numbers,
Booleans and Strings) is handed to asyncua's own decoders. tests/test_codec.py checks all three
against asyncua on generated messages (OPC 10000-6 5.2).
"""

from __future__ import annotations

import struct
from typing import Any

from asyncua import ua
from asyncua.common.utils import Buffer, NotEnoughData
from asyncua.ua.ua_binary import (
    extensionobject_from_binary,
    extensionobject_to_binary,
    nodeid_from_binary,
    nodeid_to_binary,
    struct_to_binary,
    variant_from_binary,
    variant_to_binary,
)
from asyncua.ua.uaerrors import UaError

from uacell.ua.door.connection import buffer_bytes

_INT32 = struct.Struct("<i")
_UINT32 = struct.Struct("<I")
_HEADER = struct.Struct("<qII")  # Timestamp, RequestHandle, ServiceResult
_EMPTY_LIST = _INT32.pack(0)
_NULL_LIST = _INT32.pack(-1)
_EMPTY_DIAGNOSTIC = b"\x00"  # a DiagnosticInfo with no field: its encoding mask alone
_CALL_RESPONSE_TYPE_ID = ua.CallResponse().TypeId
_CALL_RESPONSE_TYPE = nodeid_to_binary(_CALL_RESPONSE_TYPE_ID)
_NO_HEADER = ua.ResponseHeader().AdditionalHeader  # asyncua's default: one shared empty ExtensionObject
_NO_HEADER_BYTES = extensionobject_to_binary(_NO_HEADER)


def _diagnostic(d: Any) -> bytes:
    if (
        d.SymbolicId is None
        and d.NamespaceURI is None
        and d.Locale is None
        and d.LocalizedText is None
        and d.AdditionalInfo is None
        and d.InnerStatusCode is None
        and d.InnerDiagnosticInfo is None
    ):
        return _EMPTY_DIAGNOSTIC
    encoded: bytes = struct_to_binary(d)
    return encoded


def _diagnostics(items: list[Any] | None) -> bytes:
    if items is None:
        return _NULL_LIST
    if not items:
        return _EMPTY_LIST
    return _INT32.pack(len(items)) + b"".join(_diagnostic(d) for d in items)


def _status_codes(items: list[ua.StatusCode] | None) -> bytes:
    if items is None:
        return _NULL_LIST
    return _INT32.pack(len(items)) + b"".join(_UINT32.pack(s.value) for s in items)


def _variants(items: list[ua.Variant] | None) -> bytes:
    if items is None:
        return _NULL_LIST
    return _INT32.pack(len(items)) + b"".join(variant_to_binary(v) for v in items)


def _strings(items: list[str] | None) -> bytes:
    if items is None:
        return _NULL_LIST
    out = [_INT32.pack(len(items))]
    for s in items:
        if s is None:
            out.append(_NULL_LIST)
        else:
            data = s.encode("utf-8")
            out.append(_INT32.pack(len(data)) + data)
    return b"".join(out)


def _method_result(r: ua.CallMethodResult) -> bytes:
    return b"".join(
        (
            _UINT32.pack(r.StatusCode.value),
            _status_codes(r.InputArgumentResults),
            _diagnostics(r.InputArgumentDiagnosticInfos),
            _variants(r.OutputArguments),
        )
    )


def encode_call_response(response: ua.CallResponse) -> bytes:
    """``struct_to_binary(response)``, the same bytes."""
    if response.TypeId != _CALL_RESPONSE_TYPE_ID:  # never so; asyncua's encoder says what it means
        encoded: bytes = struct_to_binary(response)
        return encoded
    h = response.ResponseHeader
    extra = h.AdditionalHeader
    results = response.Results
    return b"".join(
        (
            _CALL_RESPONSE_TYPE,
            _HEADER.pack(ua.datetime_to_win_epoch(h.Timestamp), h.RequestHandle, h.ServiceResult.value),
            _diagnostic(h.ServiceDiagnostics),
            _strings(h.StringTable),
            _NO_HEADER_BYTES if extra is _NO_HEADER else extensionobject_to_binary(extra),
            _NULL_LIST if results is None else _INT32.pack(len(results)) + b"".join(map(_method_result, results)),
            _diagnostics(response.DiagnosticInfos),
        )
    )


# --- decoding -------------------------------------------------------------------------------------
_FOUR_BYTE = struct.Struct("<BH")
_NUMERIC = struct.Struct("<HI")
_STRINGLIKE = struct.Struct("<Hi")  # namespace, length
_REQUEST = struct.Struct("<qII")  # Timestamp, RequestHandle, ReturnDiagnostics
_NO_EXTENSION = b"\x00\x00\x00"  # a null ExtensionObject: null TypeId, no body
_KIND = ua.NodeIdType
_new_node_id = ua.NodeId.__new__
# Variant encoding byte -> (its reader, VariantType): the scalars a method's arguments mostly are
_SCALARS: dict[int, tuple[struct.Struct, ua.VariantType]] = {
    t.value: (struct.Struct("<" + code), t)
    for t, code in (
        (ua.VariantType.Boolean, "?"),
        (ua.VariantType.SByte, "b"),
        (ua.VariantType.Byte, "B"),
        (ua.VariantType.Int16, "h"),
        (ua.VariantType.UInt16, "H"),
        (ua.VariantType.Int32, "i"),
        (ua.VariantType.UInt32, "I"),
        (ua.VariantType.Int64, "q"),
        (ua.VariantType.UInt64, "Q"),
        (ua.VariantType.Float, "f"),
        (ua.VariantType.Double, "d"),
    )
}
_STRING = ua.VariantType.String.value


def _node_id(identifier: Any, namespace: int, kind: ua.NodeIdType) -> ua.NodeId:
    """A NodeId whose identifier is of its kind by construction (asyncua's constructor checks that)."""
    node: ua.NodeId = _new_node_id(ua.NodeId)
    node.Identifier, node.NamespaceIndex, node.NodeIdType = identifier, namespace, kind
    return node


def _text(data: bytes, pos: int) -> tuple[str | None, int]:
    """A String at ``pos`` (null for a length of -1) and the position after it."""
    (length,) = _INT32.unpack_from(data, pos)
    pos += 4
    if length == -1:
        return None, pos
    end = pos + length
    if length < 0 or end > len(data):
        raise NotEnoughData(f"a String of {length} bytes where {len(data) - pos} are left")
    return data[pos:end].decode("utf-8", errors="surrogateescape"), end


def _with_asyncua(decode: Any, data: bytes, pos: int) -> tuple[Any, int]:
    """asyncua's ``decode`` of what is at ``pos``, and the position after it."""
    buffer = Buffer(data, pos)
    return decode(buffer), buffer.cur_pos


def _decoded_node_id(data: bytes, pos: int) -> tuple[ua.NodeId, int]:
    encoding = data[pos]
    if encoding == 0:  # TwoByte
        return _node_id(data[pos + 1], 0, _KIND.TwoByte), pos + 2
    if encoding == 1:
        namespace, identifier = _FOUR_BYTE.unpack_from(data, pos + 1)
        return _node_id(identifier, namespace, _KIND.FourByte), pos + 4
    if encoding == 2:
        namespace, identifier = _NUMERIC.unpack_from(data, pos + 1)
        return _node_id(identifier, namespace, _KIND.Numeric), pos + 7
    if encoding in (3, 5):
        namespace, length = _STRINGLIKE.unpack_from(data, pos + 1)
        start, end = pos + 7, pos + 7 + length
        if length >= 0 and end <= len(data):
            raw = data[start:end]
            if encoding == 3:
                return _node_id(raw.decode("utf-8", errors="surrogateescape"), namespace, _KIND.String), end
            return _node_id(raw, namespace, _KIND.ByteString), end
    # a Guid, an expanded NodeId, a null or cut identifier: asyncua decodes (or refuses) it
    node: ua.NodeId
    node, pos = _with_asyncua(nodeid_from_binary, data, pos)
    return node, pos


def _extension_object(data: bytes, pos: int) -> tuple[Any, int]:
    if data[pos : pos + 3] == _NO_EXTENSION:
        return ua.ExtensionObject(), pos + 3
    return _with_asyncua(extensionobject_from_binary, data, pos)


def _variant(data: bytes, pos: int) -> tuple[ua.Variant, int]:
    encoding = data[pos]
    scalar = _SCALARS.get(encoding)
    if scalar is not None:
        reader, vtype = scalar
        return ua.Variant(reader.unpack_from(data, pos + 1)[0], vtype, None, is_array=False), pos + 1 + reader.size
    if encoding == _STRING:
        text, pos = _text(data, pos + 1)
        return ua.Variant(text, ua.VariantType.String, None, is_array=False), pos
    variant: ua.Variant
    variant, pos = _with_asyncua(variant_from_binary, data, pos)
    return variant, pos


def _decoding(decode: Any, body: Buffer) -> Any:
    """Run ``decode(data, pos)`` at the buffer's position, move the buffer past what it read; a message
    cut short is asyncua's NotEnoughData, one with a value of no known kind a UaError (asyncua's own
    decoders raise a ValueError there, which asyncua logs as a server error)."""
    data = buffer_bytes(body)  # asyncua builds a message's body as one Buffer over its bytes
    if type(data) is not bytes:
        data = bytes(data)
    start = body.cur_pos
    try:
        value, end = decode(data, start)
    except (struct.error, IndexError) as e:
        raise NotEnoughData(f"a request cut short: {e}") from None
    except ValueError as e:  # asyncua's decoders meeting an unknown kind (a NodeId's encoding byte, say)
        raise UaError(f"a malformed request: {e}") from None
    body.skip(end - start)  # NotEnoughData when that is past the buffer's end
    return value


def _request_header(data: bytes, pos: int) -> tuple[tuple[ua.NodeId, ua.RequestHeader], int]:
    typeid, pos = _decoded_node_id(data, pos)
    token, pos = _decoded_node_id(data, pos)
    epoch, handle, diagnostics = _REQUEST.unpack_from(data, pos)
    audit_entry, pos = _text(data, pos + _REQUEST.size)
    (timeout,) = _UINT32.unpack_from(data, pos)
    extra, pos = _extension_object(data, pos + 4)
    header = ua.RequestHeader(token, ua.win_epoch_to_datetime(epoch), handle, diagnostics, audit_entry, timeout, extra)
    return (typeid, header), pos


def decode_request_header(body: Buffer) -> tuple[ua.NodeId, ua.RequestHeader]:
    """A request's TypeId and RequestHeader: asyncua's ``nodeid_from_binary(body)`` then
    ``struct_from_binary(ua.RequestHeader, body)``."""
    decoded: tuple[ua.NodeId, ua.RequestHeader] = _decoding(_request_header, body)
    return decoded


def _call_parameters(data: bytes, pos: int) -> tuple[ua.CallParameters, int]:
    (count,) = _INT32.unpack_from(data, pos)
    pos += 4
    methods = []
    for _ in range(count):
        obj, pos = _decoded_node_id(data, pos)
        method, pos = _decoded_node_id(data, pos)
        (n,) = _INT32.unpack_from(data, pos)
        pos += 4
        inputs = []
        for _ in range(n):
            variant, pos = _variant(data, pos)
            inputs.append(variant)
        methods.append(ua.CallMethodRequest(obj, method, inputs))
    return ua.CallParameters(methods), pos


def decode_call_parameters(body: Buffer) -> ua.CallParameters:
    """The Call request's parameters: asyncua's ``struct_from_binary(ua.CallParameters, body)``."""
    params: ua.CallParameters = _decoding(_call_parameters, body)
    return params
