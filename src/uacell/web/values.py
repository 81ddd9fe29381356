"""The web HMI's values in JSON and back: an OPC UA value as the page gets it (``jsonable``), a JSON
value as the Variant a method argument asks for (``to_variant``; ValueError says what does not fit)."""

from __future__ import annotations

import dataclasses
import enum
import math
from datetime import datetime
from typing import Any

from asyncua import ua


def jsonable(value: Any) -> Any:
    """An OPC UA value as JSON: texts as strings, NodeIds as strings, structures as objects."""
    if value is None or isinstance(value, bool | int | str):
        return value.value if isinstance(value, enum.Enum) else value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, ua.LocalizedText):
        return value.Text
    if isinstance(value, ua.QualifiedName):
        return value.Name
    if isinstance(value, ua.NodeId):
        return value.to_string()
    if isinstance(value, ua.StatusCode):
        return value.name
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if dataclasses.is_dataclass(value):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return str(value)


_ALIASES = {290: ua.VariantType.Double, 294: ua.VariantType.DateTime, 884: ua.VariantType.ExtensionObject}


def to_variant(argument: ua.Argument, value: Any) -> ua.Variant:
    """A JSON value as the Variant ``argument`` asks for (ValueError says what does not fit)."""
    if argument.ValueRank >= 1:
        if not isinstance(value, list):
            raise ValueError(f"{argument.Name} must be a list")
        items = [_scalar(argument, v) for v in value]
        return ua.Variant(items, _variant_type(argument.DataType), is_array=True)
    return ua.Variant(_scalar(argument, value), _variant_type(argument.DataType))


def _variant_type(data_type: ua.NodeId) -> ua.VariantType:
    if data_type.NamespaceIndex == 0 and isinstance(data_type.Identifier, int):
        if 1 <= data_type.Identifier <= 25:
            return ua.VariantType(data_type.Identifier)
        if data_type.Identifier in _ALIASES:
            return _ALIASES[data_type.Identifier]
    if data_type in ua.enums_by_datatype or data_type == ua.NodeId(ua.ObjectIds.Enumeration):
        return ua.VariantType.Int32
    return ua.VariantType.ExtensionObject


def _scalar(argument: ua.Argument, value: Any) -> Any:
    vt = _variant_type(argument.DataType)
    name = argument.Name
    try:
        if vt == ua.VariantType.Boolean:
            if not isinstance(value, bool):
                raise ValueError
            return value
        if vt == ua.VariantType.Float:
            single = float(value)
            if not abs(single) <= FLOAT_MAX:  # also NaN: what a Float cannot hold is refused here
                raise ValueError
            return single
        if vt == ua.VariantType.Double:
            return float(value)
        if vt.name in _INT_RANGES:
            return _whole(vt.name, value)
        if vt == ua.VariantType.String:
            return str(value)
        if vt == ua.VariantType.LocalizedText:
            return ua.LocalizedText(str(value))
        if vt == ua.VariantType.ByteString:
            return bytes.fromhex(str(value))
        if vt == ua.VariantType.NodeId:
            return ua.NodeId.from_string(str(value))
        cls = ua.extension_objects_by_datatype.get(argument.DataType)
        if cls is None or not isinstance(value, dict):
            raise ValueError
        return _structure(cls, value)
    except (ValueError, TypeError, ua.UaError) as exc:
        reason = str(exc) if isinstance(exc, ValueError) and str(exc) else f"{value!r} is not a valid {vt.name}"
        raise ValueError(f"{name}: {reason}") from exc


FLOAT_MAX = 3.4028234663852886e38  # the largest finite single-precision number

_INT_RANGES = {
    name: (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else (0, 2**bits - 1)
    for name, bits, signed in (
        ("SByte", 8, True),
        ("Byte", 8, False),
        ("Int16", 16, True),
        ("UInt16", 16, False),
        ("Int32", 32, True),
        ("UInt32", 32, False),
        ("Int64", 64, True),
        ("UInt64", 64, False),
    )
}


def _whole(type_name: str, item: Any) -> int:
    """A JSON number as a whole number that fits ``type_name`` (ValueError names the range)."""
    low, high = _INT_RANGES[type_name]
    try:
        whole = int(item) if isinstance(item, int) else int(float(item))
        fits = not isinstance(item, bool) and float(item) == whole
    except (ValueError, TypeError, OverflowError):
        fits = False
    if not fits:
        raise ValueError(f"{item!r} is not a whole number")
    if not low <= whole <= high:
        raise ValueError(f"{item!r} is outside {low}..{high} ({type_name})")
    return whole


def _structure(cls: type, value: dict[str, Any]) -> Any:
    """A structure from a JSON object, field by field (names compared without case)."""
    obj = cls()
    fields = {f.name.lower(): f for f in dataclasses.fields(obj)}
    for key, item in value.items():
        f = fields.get(str(key).lower())
        if f is None:
            raise ValueError(f"no field {key}")
        setattr(obj, f.name, _field(str(f.type), item))
    return obj


def _field(type_name: str, item: Any) -> Any:
    base = type_name.rsplit(".", 1)[-1].strip("'\"")
    if base in _INT_RANGES:
        return _whole(base, item)
    if base in ("Float", "Double"):
        return float(item)
    if base == "Boolean":
        if not isinstance(item, bool):
            raise ValueError(f"{item!r} is not true or false")
        return item
    if base == "String":
        return str(item)
    if base == "LocalizedText":
        return ua.LocalizedText(str(item))
    if base == "EUInformation" and isinstance(item, str):  # a unit given by its name, e.g. "ml"
        return ua.EUInformation(DisplayName=ua.LocalizedText(item), Description=ua.LocalizedText(item))
    cls = getattr(ua, base, None)
    if isinstance(cls, type) and dataclasses.is_dataclass(cls) and isinstance(item, dict):
        return _structure(cls, item)
    raise ValueError(f"{item!r} does not fit {base}")
