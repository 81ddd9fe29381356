"""Read and Write as OPC 10000-4 5.11 describes them (decision 81).

asyncua's Attribute services differ from the standard where clients notice:

- Read ignored IndexRange: a client asking for element 2 of an array got the whole array, one asking
  for a range that does not parse or has no data got Good; a negative MaxAge was not refused;
- Write ignored IndexRange too, and wrote the value given *for the range* as the whole value, past the
  behaviour a binding routes a node's writes to: an operator could set a task control's ExecutionMode
  with an IndexRange of "0" and the model never knew; a ServerTimestamp or a StatusCode in the written
  DataValue was stored as given;
- a write of an unknown node, of an attribute other than Value or of a variable whose AccessLevel has
  no CurrentWrite was Bad_UserAccessDenied, whoever asked; an unknown AttributeId made the audit
  trail's observer fail.

Here, Read: Bad_NothingToDo for no nodes, Bad_MaxAgeInvalid for a negative MaxAge,
Bad_TimestampsToReturnInvalid for an invalid TimestampsToReturn, each IndexRange applied to what was
read (``uacell.ua.numeric_range``), and a Value returned with the timestamps TimestampsToReturn names
(asyncua returned both whatever the client asked). Write: Bad_NothingToDo for no nodes; per item,
before anything is written or routed, Bad_AttributeIdInvalid, Bad_IndexRangeInvalid for a range that does not parse and
Bad_WriteNotSupported for one that does (uacell writes whole values), Bad_WriteNotSupported for a
ServerTimestamp or a StatusCode other than Good (a client writes values; the server stamps them);
then for the writes asyncua stores: Bad_NodeIdUnknown, Bad_NotWritable (an attribute other than
Value, a variable without CurrentWrite), Bad_TypeMismatch for a value that is not of the variable's
DataType and ValueRank. What a role may write is checked before all of these (Bad_UserAccessDenied).

uacell's session (``uacell.ua.limits.LimitedSession``) runs the checks; the write rules that come
before a binding's routing are run by ``uacell.binding.writes.WriteRouter``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

from asyncua import ua
from asyncua.common.utils import ServiceError

from uacell.ua import numeric_range

_A = ua.AttributeIds
_SC = ua.StatusCodes
_ATTRIBUTES = frozenset(int(a) for a in ua.AttributeIds)
_T = ua.TimestampsToReturn
_TIMESTAMPS = frozenset({_T.Source, _T.Server, _T.Both, _T.Neither})
_CURRENT_WRITE = ua.AccessLevel.CurrentWrite.mask


def attribute_name(attribute_id: int) -> str:
    """An AttributeId's name ("Value"), or its number when it names no attribute."""
    return ua.AttributeIds(attribute_id).name if attribute_id in _ATTRIBUTES else str(attribute_id)


def check_read(params: ua.ReadParameters) -> None:
    """The Read request's own checks (ServiceError with its code)."""
    if params.MaxAge < 0:
        raise ServiceError(_SC.BadMaxAgeInvalid)
    check_timestamps(params.TimestampsToReturn)


def check_timestamps(stamps: ua.TimestampsToReturn) -> None:
    """A request's TimestampsToReturn (Read, CreateMonitoredItems, ModifyMonitoredItems): one of the four."""
    if stamps not in _TIMESTAMPS:
        raise ServiceError(_SC.BadTimestampsToReturnInvalid)


def shape_results(params: ua.ReadParameters, results: list[ua.DataValue]) -> None:
    """Each read value cut to its item's IndexRange, and a Value given the timestamps the request asks
    for (in place; a result is replaced, not changed: it may be the address space's own DataValue)."""
    stamps = params.TimestampsToReturn
    for i, item in enumerate(params.NodesToRead):
        read = results[i]
        if item.IndexRange:
            read = numeric_range.cut(read, item.IndexRange)
        if stamps != _T.Both and item.AttributeId == _A.Value:
            read = stamped(read, stamps)
        results[i] = read


def stamped(read: ua.DataValue, stamps: ua.TimestampsToReturn) -> ua.DataValue:
    """``read`` with only the timestamps ``stamps`` names (a new DataValue if any is dropped)."""
    drop: dict[str, None] = {}
    if stamps != _T.Server and (read.ServerTimestamp is not None or read.ServerPicoseconds is not None):
        drop.update(ServerTimestamp=None, ServerPicoseconds=None)
    if stamps != _T.Source and (read.SourceTimestamp is not None or read.SourcePicoseconds is not None):
        drop.update(SourceTimestamp=None, SourcePicoseconds=None)
    return dataclasses.replace(read, **drop) if drop else read


def write_refusal(item: ua.WriteValue) -> int | None:
    """What refuses a write item for its form alone, before anything is written or routed; None if nothing."""
    if item.AttributeId not in _ATTRIBUTES:
        return int(_SC.BadAttributeIdInvalid)
    if item.IndexRange:
        try:
            numeric_range.parse(item.IndexRange)
        except numeric_range.RangeError as refused:
            return int(refused.code)
        return int(_SC.BadWriteNotSupported)
    value = item.Value
    if value is None:
        return int(_SC.BadTypeMismatch)
    if value.ServerTimestamp is not None or value.ServerPicoseconds:
        return int(_SC.BadWriteNotSupported)
    if value.StatusCode is not None and value.StatusCode.value != _SC.Good:
        return int(_SC.BadWriteNotSupported)
    return None


class ValueTypes(Protocol):
    """Does a value fit a DataType and ValueRank (``uacell.binding.dispatch.TypeChecker``)?"""

    def accepts(self, variant: ua.Variant, arg: ua.Argument) -> bool: ...


def stored_write_refusal(aspace: Any, item: ua.WriteValue, types: ValueTypes | None) -> int | None:
    """What refuses a write that asyncua would store (no binding routes it); None if nothing."""
    data = aspace.get(item.NodeId)
    if data is None:
        return int(_SC.BadNodeIdUnknown)
    if item.AttributeId != _A.Value:
        return int(_SC.BadNotWritable if item.AttributeId in data.attributes else _SC.BadAttributeIdInvalid)
    level = _attribute(data, _A.AccessLevel)
    if not isinstance(level, int) or not level & _CURRENT_WRITE:
        return int(_SC.BadNotWritable)
    datatype = _attribute(data, _A.DataType)
    if types is not None and isinstance(datatype, ua.NodeId):
        rank = _attribute(data, _A.ValueRank)
        wanted = ua.Argument(DataType=datatype, ValueRank=rank if isinstance(rank, int) else -2)
        if not types.accepts(item.Value.Value or ua.Variant(), wanted):
            return int(_SC.BadTypeMismatch)
    return None


def _attribute(data: Any, attribute: ua.AttributeIds) -> Any:
    stored = data.attributes.get(attribute)
    if stored is None or stored.value is None or stored.value.Value is None:
        return None
    return stored.value.Value.Value
