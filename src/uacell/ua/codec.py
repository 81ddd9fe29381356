"""The binary encoding of the Call service's response, written out (decision 49).

asyncua encodes every structure through per-field closures built from its dataclasses; for the
response uacell sends most (a Call's) that was about a twentieth of a call's server time.
``encode_call_response`` produces the same bytes (OPC 10000-6 5.2) with asyncua's own encoders for
what varies in kind (Variants, DiagnosticInfos with content, extension objects); tests/test_codec.py
checks it against asyncua's ``struct_to_binary`` on generated responses.
"""

from __future__ import annotations

import struct
from typing import Any

from asyncua import ua
from asyncua.ua.ua_binary import extensionobject_to_binary, nodeid_to_binary, struct_to_binary, variant_to_binary

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
