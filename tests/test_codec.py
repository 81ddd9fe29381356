"""uacell's written-out encoder of the Call response (ua/codec.py) gives asyncua's bytes, and asyncua
decodes them back to the response."""

from __future__ import annotations

from datetime import UTC, datetime

from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary
from hypothesis import given, settings
from hypothesis import strategies as st

from uacell.ua.codec import encode_call_response

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
