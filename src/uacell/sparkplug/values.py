"""OPC UA values as Sparkplug metric values (docs/sparkplug.md, "Metrics"): the datatype a variable's
VariantType maps to, and its value in that datatype. Pure."""

from __future__ import annotations

import dataclasses
import json
from datetime import UTC, datetime
from enum import Enum
from typing import Any

from asyncua import ua

from uacell.sparkplug.payload import DataType

_V = ua.VariantType
_TYPES: dict[ua.VariantType, DataType] = {
    _V.Boolean: DataType.Boolean,
    _V.SByte: DataType.Int8,
    _V.Byte: DataType.UInt8,
    _V.Int16: DataType.Int16,
    _V.UInt16: DataType.UInt16,
    _V.Int32: DataType.Int32,
    _V.UInt32: DataType.UInt32,
    _V.Int64: DataType.Int64,
    _V.UInt64: DataType.UInt64,
    _V.Float: DataType.Float,
    _V.Double: DataType.Double,
    _V.String: DataType.String,
    _V.DateTime: DataType.DateTime,
    _V.Guid: DataType.UUID,
    _V.ByteString: DataType.Bytes,
    _V.StatusCode: DataType.UInt32,
}
# Sparkplug datatypes a command metric's value is called with (the method's argument type decides
# whether the call takes it: Bad_TypeMismatch otherwise, as for any client).
VARIANTS: dict[DataType, ua.VariantType] = {d: v for v, d in _TYPES.items() if v is not _V.StatusCode}
VARIANTS[DataType.Text] = _V.String
# A value the equipment cannot give: its metric is null until it can again.
UNREACHABLE = (ua.StatusCodes.BadNoCommunication, ua.StatusCodes.BadCommunicationError)


def datatype_of(vtype: ua.VariantType | None, array: bool) -> DataType:
    """Scalars map one to one; LocalizedText, NodeIds, structures and arrays are text (String; JSON
    for structures and arrays)."""
    if array or vtype is None:
        return DataType.String
    return _TYPES.get(vtype, DataType.String)


def millis(t: datetime | None) -> int:
    if t is None:
        return int(datetime.now(UTC).timestamp() * 1000)
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return int(t.timestamp() * 1000)


def value_of(dv: ua.DataValue, datatype: DataType) -> Any:
    """The value of ``dv`` as a ``datatype`` metric's; None (is_null) when it is bad or empty."""
    if dv.StatusCode is not None and not dv.StatusCode.is_good():
        return None
    variant = dv.Value
    if variant is None or variant.Value is None:
        return None
    value = variant.Value
    if datatype is DataType.DateTime and isinstance(value, datetime):
        return millis(value)
    if datatype is DataType.UUID:
        return str(value)
    if datatype is DataType.UInt32 and isinstance(value, ua.StatusCode):
        return int(value.value)
    if datatype is DataType.String:
        return text(value)
    if isinstance(value, Enum):
        return int(value.value)
    return value


def text(value: Any) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, ua.LocalizedText):
        return str(value.Text or "")
    if isinstance(value, ua.NodeId | ua.QualifiedName):
        return str(value.to_string())
    return str(json.dumps(plain(value), separators=(",", ":")))


def plain(value: Any) -> Any:
    """A value as JSON-able data: structures as objects of their fields, lists as lists."""
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, bool | int | float | str) or value is None:
        return value
    if isinstance(value, Enum):
        return int(value.value)
    if isinstance(value, ua.LocalizedText):
        return value.Text
    if isinstance(value, datetime):
        return value.isoformat()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return str(value)


def unreachable(dv: ua.DataValue) -> bool:
    """Does ``dv`` say its equipment cannot be reached (as the gateway writes it, docs/equipment.md)?"""
    return dv.StatusCode is not None and dv.StatusCode.value in UNREACHABLE
