"""OPC UA values as JSON in the VerboseEncoding of OPC 10000-6 v1.05 §5.4, the encoding OPC 10000-14
v1.05 §7.2.5.4.2 recommends for DataSetMessages (docs/pubsub.md, "The JSON encoding"). Pure.

- numbers as JSON numbers; Int64/UInt64 as strings (§5.4.2.3); NaN and the infinities as the strings
  "NaN", "Infinity", "-Infinity" (§5.4.2.4); DateTime as ISO 8601 UTC (§5.4.2.6); ByteString as base64;
- NodeId and ExpandedNodeId as the string of §5.1.12, with ``nsu=<namespace URI>`` (never an index);
- QualifiedName as the string of §5.1.12 (``nsu=<URI>;<name>`` outside namespace 0);
- LocalizedText as ``{"Locale", "Text"}``, each left out when null or empty (§5.4.2.15);
- StatusCode as ``{"Code", "Symbol"}``, both left out when Good (§5.4.2.12);
- Enumerations as ``"<name>_<value>"`` (§5.4.4.2);
- a Variant whose type is not known from the context as ``{"UaType", "Value"}`` (§5.4.2.17);
- Structures as objects of all their fields, null ones as JSON null (§5.4.2.1, §5.4.6).
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import math
import uuid
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from typing import Any

from asyncua import ua

MIN_DATE = datetime(1601, 1, 1, tzinfo=UTC)
_SYMBOLS = {v: k for k, v in vars(ua.StatusCodes).items() if isinstance(v, int) and not k.startswith("_")}
_WIDE = {"Int64": ua.VariantType.Int64, "UInt64": ua.VariantType.UInt64}  # structure fields sent as strings
_INFO_BITS = 0x0000FFFF  # the InfoBits and sub-code: ignored when looking up the symbol (§5.4.2.12)


JSON_NULL_TIME = "0001-01-01T00:00:00Z"  # DateTime.MinValue in JSON, a null DateTime (§5.4.2.6)


def iso(t: datetime) -> str:
    """``2026-11-25T18:02:14.123456Z``; DateTime.MinValue (1601-01-01 and before, §5.1.4) as
    ``0001-01-01T00:00:00Z``."""
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    if t <= MIN_DATE:
        return JSON_NULL_TIME
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")


def _valid_time(t: datetime | None) -> bool:
    return t is not None and t > MIN_DATE.replace(tzinfo=None if t.tzinfo is None else UTC)


class JsonEncoder:
    """Encodes Variants and DataValues; ``namespaces`` is the server's NamespaceArray."""

    def __init__(self, namespaces: Sequence[str] | Callable[[], Sequence[str]]) -> None:
        self._namespaces = namespaces

    def uri(self, index: int) -> str | None:
        ns = self._namespaces() if callable(self._namespaces) else self._namespaces
        return ns[index] if 0 < index < len(ns) else None

    def node_id(self, node: ua.NodeId) -> str:
        text: str = node.to_string()  # "ns=3;s=Robot1" or "i=2253"
        if node.NamespaceIndex == 0:
            return text
        uri = getattr(node, "NamespaceUri", None) or self.uri(node.NamespaceIndex)
        if uri is None:
            return text
        return f"nsu={uri};{text.split(';', 1)[1]}"

    def qualified_name(self, name: ua.QualifiedName) -> str:
        uri = self.uri(name.NamespaceIndex) if name.NamespaceIndex else None
        if name.NamespaceIndex and uri is None:
            return f"{name.NamespaceIndex}:{name.Name}"
        return f"nsu={uri};{name.Name}" if uri else str(name.Name or "")

    def variant(self, variant: ua.Variant | None) -> Any:
        """A Variant's value where its type is known from the context (collapsed, OPC 10000-14 §7.2.5.4.2)."""
        if variant is None:
            return None
        return self.value(variant.Value, variant.VariantType)

    def typed(self, variant: ua.Variant | None) -> dict[str, Any] | None:
        """A Variant where its type is not known from the context: ``{"UaType", "Value"}`` (§5.4.2.17)."""
        if variant is None or variant.Value is None:
            return None
        return {"UaType": variant.VariantType.value, "Value": self.value(variant.Value, variant.VariantType)}

    def value(self, value: Any, vtype: ua.VariantType | None = None) -> Any:
        if value is None:
            return None
        if isinstance(value, list | tuple):
            return [self.value(v, vtype) for v in value]
        if isinstance(value, bool):
            return value
        if isinstance(value, enum.Flag):  # an OptionSet: its number
            return int(value.value)
        if isinstance(value, enum.Enum):
            return f"{value.name}_{int(value.value)}"  # §5.4.4.2 (IntFlag option sets are ints too)
        if isinstance(value, int):
            if vtype in (ua.VariantType.Int64, ua.VariantType.UInt64):
                return str(value)
            return value
        if isinstance(value, float):
            if math.isnan(value):
                return "NaN"
            if math.isinf(value):
                return "Infinity" if value > 0 else "-Infinity"
            return value
        if isinstance(value, str):
            return value
        if isinstance(value, datetime):
            return iso(value)
        if isinstance(value, bytes | bytearray):
            return base64.b64encode(bytes(value)).decode("ascii")
        if isinstance(value, uuid.UUID):
            return str(value)
        if isinstance(value, ua.NodeId):  # ExpandedNodeId is one too
            return self.node_id(value)
        if isinstance(value, ua.QualifiedName):
            return self.qualified_name(value)
        if isinstance(value, ua.LocalizedText):
            return self.localized_text(value)
        if isinstance(value, ua.StatusCode):
            return self.status(value)
        if isinstance(value, ua.Variant):
            return self.typed(value)
        if isinstance(value, ua.DataValue):
            return self.data_value(value, typed=True)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return {
                f.name: self.value(getattr(value, f.name), _WIDE.get(str(f.type).strip("'").removeprefix("ua.")))
                for f in dataclasses.fields(value)
                if f.init
            }
        return str(value)

    def enumeration(self, value: Any, names: Mapping[int, str]) -> Any:
        """An Enumeration held as its number: ``<name>_<value>`` (§5.4.4.2), the number alone if unnamed."""
        if isinstance(value, list | tuple):
            return [self.enumeration(v, names) for v in value]
        if isinstance(value, int) and not isinstance(value, bool):
            number = int(value)
            return f"{names[number]}_{number}" if number in names else str(number)
        return self.value(value)

    @staticmethod
    def localized_text(text: ua.LocalizedText) -> dict[str, str]:
        out: dict[str, str] = {}
        if text.Locale:
            out["Locale"] = text.Locale
        if text.Text:
            out["Text"] = text.Text
        return out

    @staticmethod
    def status(code: ua.StatusCode | int) -> dict[str, Any]:
        value = code.value if isinstance(code, ua.StatusCode) else int(code)
        if value == 0:
            return {}
        symbol = _SYMBOLS.get(value & ~_INFO_BITS)
        return {"Code": value, "Symbol": symbol} if symbol else {"Code": value}

    def data_value(
        self, dv: ua.DataValue, *, typed: bool = False, names: Mapping[int, str] | None = None
    ) -> dict[str, Any]:
        """A DataSet field as a DataValue (DataSetFieldContentMask StatusCode | SourceTimestamp, §5.4.2.18):
        ``Value`` (JSON null when null, VerboseEncoding §5.4.2.1), ``Status`` unless Good, ``SourceTimestamp``
        unless unknown. ``typed``: the field's DataType is abstract, so the Variant keeps its ``UaType``;
        ``names``: the field's DataType is an Enumeration with these names (a verbose ``<name>_<value>``)."""
        variant = dv.Value
        out: dict[str, Any] = {}
        if typed and variant is not None and variant.Value is not None:
            out["UaType"] = variant.VariantType.value
        out["Value"] = (
            self.enumeration(variant.Value, names) if names and variant is not None else self.variant(variant)
        )
        code = dv.StatusCode.value if dv.StatusCode is not None else 0
        if code != 0:
            out["Status"] = self.status(code)
        t = dv.SourceTimestamp or dv.ServerTimestamp
        if t is not None and _valid_time(t):
            out["SourceTimestamp"] = iso(t)
        return out
