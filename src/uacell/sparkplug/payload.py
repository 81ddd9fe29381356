"""Sparkplug B payloads (Eclipse Sparkplug 3.0, chapter 6.4 and its ``sparkplug_b.proto``) with Google's
``protobuf`` runtime.

The message types are described here field by field, as the specification's protobuf definition gives
them (package ``org.eclipse.tahu.protobuf``, proto2), and built once into protobuf message classes: no
generated code, so no protoc at build time and no generated-code/runtime version pairing. Only what an
edge node sends and reads is described (Payload, Metric, PropertySet, PropertyValue, MetaData); the
fields of DataSet and Template metrics, which uacell never sends, are left out: protobuf skips unknown
fields when it reads, and their numbers are kept free here (docs/sparkplug.md, "Payloads").
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any

from uacell.core.extras import MissingExtra

try:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
except ImportError as exc:  # the 'sparkplug' extra
    raise MissingExtra.of("[sparkplug]", exc) from exc

_F = descriptor_pb2.FieldDescriptorProto
_PACKAGE = "org.eclipse.tahu.protobuf"


class DataType(IntEnum):
    """Sparkplug 3.0 ("Data Types"): the datatype of a metric, a property value."""

    Unknown = 0
    Int8 = 1
    Int16 = 2
    Int32 = 3
    Int64 = 4
    UInt8 = 5
    UInt16 = 6
    UInt32 = 7
    UInt64 = 8
    Float = 9
    Double = 10
    Boolean = 11
    String = 12
    DateTime = 13
    Text = 14
    UUID = 15
    DataSet = 16
    Bytes = 17
    File = 18
    Template = 19
    PropertySet = 20
    PropertySetList = 21


# (name, number, label, type, message type or "", oneof index or None)
_Field = tuple[str, int, int, int, str, int | None]
_OPT, _REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED

_METRIC: list[_Field] = [
    ("name", 1, _OPT, _F.TYPE_STRING, "", None),
    ("alias", 2, _OPT, _F.TYPE_UINT64, "", None),
    ("timestamp", 3, _OPT, _F.TYPE_UINT64, "", None),
    ("datatype", 4, _OPT, _F.TYPE_UINT32, "", None),
    ("is_historical", 5, _OPT, _F.TYPE_BOOL, "", None),
    ("is_transient", 6, _OPT, _F.TYPE_BOOL, "", None),
    ("is_null", 7, _OPT, _F.TYPE_BOOL, "", None),
    ("metadata", 8, _OPT, _F.TYPE_MESSAGE, "Payload.MetaData", None),
    ("properties", 9, _OPT, _F.TYPE_MESSAGE, "Payload.PropertySet", None),
    ("int_value", 10, _OPT, _F.TYPE_UINT32, "", 0),
    ("long_value", 11, _OPT, _F.TYPE_UINT64, "", 0),
    ("float_value", 12, _OPT, _F.TYPE_FLOAT, "", 0),
    ("double_value", 13, _OPT, _F.TYPE_DOUBLE, "", 0),
    ("boolean_value", 14, _OPT, _F.TYPE_BOOL, "", 0),
    ("string_value", 15, _OPT, _F.TYPE_STRING, "", 0),
    ("bytes_value", 16, _OPT, _F.TYPE_BYTES, "", 0),
]
_PROPERTY_VALUE: list[_Field] = [
    ("type", 1, _OPT, _F.TYPE_UINT32, "", None),
    ("is_null", 2, _OPT, _F.TYPE_BOOL, "", None),
    ("int_value", 3, _OPT, _F.TYPE_UINT32, "", 0),
    ("long_value", 4, _OPT, _F.TYPE_UINT64, "", 0),
    ("float_value", 5, _OPT, _F.TYPE_FLOAT, "", 0),
    ("double_value", 6, _OPT, _F.TYPE_DOUBLE, "", 0),
    ("boolean_value", 7, _OPT, _F.TYPE_BOOL, "", 0),
    ("string_value", 8, _OPT, _F.TYPE_STRING, "", 0),
    ("propertyset_value", 9, _OPT, _F.TYPE_MESSAGE, "Payload.PropertySet", 0),
]
_PROPERTY_SET: list[_Field] = [
    ("keys", 1, _REP, _F.TYPE_STRING, "", None),
    ("values", 2, _REP, _F.TYPE_MESSAGE, "Payload.PropertyValue", None),
]
_META_DATA: list[_Field] = [
    ("is_multi_part", 1, _OPT, _F.TYPE_BOOL, "", None),
    ("content_type", 2, _OPT, _F.TYPE_STRING, "", None),
    ("size", 3, _OPT, _F.TYPE_UINT64, "", None),
    ("seq", 4, _OPT, _F.TYPE_UINT64, "", None),
    ("description", 8, _OPT, _F.TYPE_STRING, "", None),
]
_PAYLOAD: list[_Field] = [
    ("timestamp", 1, _OPT, _F.TYPE_UINT64, "", None),
    ("metrics", 2, _REP, _F.TYPE_MESSAGE, "Payload.Metric", None),
    ("seq", 3, _OPT, _F.TYPE_UINT64, "", None),
    ("uuid", 4, _OPT, _F.TYPE_STRING, "", None),
    ("body", 5, _OPT, _F.TYPE_BYTES, "", None),
]


def _message(proto: descriptor_pb2.DescriptorProto, name: str, fields: list[_Field], oneof: bool) -> None:
    proto.name = name
    if oneof:
        proto.oneof_decl.add(name="value")
    for fname, number, label, ftype, type_name, index in fields:
        f = proto.field.add(name=fname, number=number, label=label, type=ftype)
        if type_name:
            f.type_name = f".{_PACKAGE}.{type_name}"
        if index is not None:
            f.oneof_index = index


def _build() -> Any:
    file = descriptor_pb2.FileDescriptorProto(name="uacell/sparkplug_b.proto", package=_PACKAGE, syntax="proto2")
    payload = file.message_type.add()
    _message(payload, "Payload", _PAYLOAD, False)
    payload.extension_range.add(start=6, end=536870912)
    for name, fields, oneof in (
        ("Metric", _METRIC, True),
        ("PropertyValue", _PROPERTY_VALUE, True),
        ("PropertySet", _PROPERTY_SET, False),
        ("MetaData", _META_DATA, False),
    ):
        _message(payload.nested_type.add(), name, fields, oneof)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PACKAGE}.Payload"))


Payload: Any = _build()

# Which value field a datatype's value goes into (3.0, "Data Types", and the proto's comments).
_INT = (DataType.Int8, DataType.Int16, DataType.Int32, DataType.UInt8, DataType.UInt16, DataType.UInt32)
_LONG = (DataType.Int64, DataType.UInt64, DataType.DateTime)
_BITS = {DataType.Int8: 8, DataType.Int16: 16, DataType.Int32: 32, DataType.Int64: 64}


def value_field(datatype: DataType) -> str:
    if datatype in _INT:
        return "int_value"
    if datatype in _LONG:
        return "long_value"
    if datatype is DataType.Float:
        return "float_value"
    if datatype is DataType.Double:
        return "double_value"
    if datatype is DataType.Boolean:
        return "boolean_value"
    if datatype in (DataType.Bytes, DataType.File):
        return "bytes_value"
    return "string_value"


def set_value(target: Any, datatype: DataType, value: Any) -> None:
    """``value`` into a Metric or PropertyValue: signed integers as two's complement in the unsigned
    field of their width (Sparkplug 3.0, "Data Types"), None (or a value the datatype cannot hold) as
    ``is_null``."""
    if value is None:
        target.is_null = True
        return
    field = value_field(datatype)
    try:
        if datatype in _BITS and int(value) < 0:
            value = int(value) + (1 << _BITS[datatype])
        setattr(target, field, value)
    except (TypeError, ValueError):
        target.is_null = True


def get_value(source: Any, datatype: DataType) -> Any:
    """The value of a Metric or PropertyValue (signed integers back from two's complement); None
    when it is null or carries no value."""
    if source.is_null:
        return None
    field = value_field(datatype)
    if source.WhichOneof("value") != field:
        return None
    value = getattr(source, field)
    bits = _BITS.get(datatype)
    if bits is not None and value >= 1 << (bits - 1):
        value -= 1 << bits
    return value


def decode(data: bytes) -> Any:
    """A Payload from its bytes; protobuf's DecodeError for anything else."""
    payload = Payload()
    payload.ParseFromString(data)
    return payload
