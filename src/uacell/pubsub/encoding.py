"""OPC UA values as JSON, the way OPC 10000-6 5.4 (v1.05, non-reversible "verbose" form) writes them
for PubSub JSON messages (OPC 10000-14 7.2.5): numbers as numbers (Int64/UInt64 as strings, NaN and
the infinities as strings), DateTime as ISO 8601 UTC, ByteString as base64, NodeIds as
``nsu=<namespace URI>;<id>`` strings, LocalizedText as ``{"Locale", "Text"}``, structures as objects
of their fields. Pure.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import math
import uuid
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import Any

from asyncua import ua

MIN_DATE = datetime(1601, 1, 1, tzinfo=UTC)
_SYMBOLS = {v: k for k, v in vars(ua.StatusCodes).items() if isinstance(v, int) and not k.startswith("_")}


def iso(t: datetime) -> str:
    """``2026-11-25T18:02:14.123456Z``."""
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")


class JsonEncoder:
    """Encodes Variants and DataValues; ``namespaces`` is the server's NamespaceArray."""

    def __init__(self, namespaces: Sequence[str] | Callable[[], Sequence[str]]) -> None:
        self._namespaces = namespaces

    def _uri(self, index: int) -> str | None:
        ns = self._namespaces() if callable(self._namespaces) else self._namespaces
        return ns[index] if 0 < index < len(ns) else None

    def node_id(self, node: ua.NodeId) -> str:
        text: str = node.to_string()  # "ns=3;s=Robot1" or "i=2253"
        uri = self._uri(node.NamespaceIndex)
        if uri is None:
            return text
        return f"nsu={uri};{text.split(';', 1)[1]}"

    def variant(self, variant: ua.Variant | None) -> Any:
        if variant is None:
            return None
        return self.value(variant.Value, variant.VariantType)

    def value(self, value: Any, vtype: ua.VariantType | None = None) -> Any:
        if value is None:
            return None
        if isinstance(value, list | tuple):
            return [self.value(v, vtype) for v in value]
        if isinstance(value, bool):
            return value
        if isinstance(value, enum.Enum):
            return int(value.value)
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
            return value.Name if value.NamespaceIndex == 0 else f"{value.NamespaceIndex}:{value.Name}"
        if isinstance(value, ua.LocalizedText):
            return {"Locale": value.Locale or "", "Text": value.Text or ""}
        if isinstance(value, ua.StatusCode):
            return self.status(value)
        if isinstance(value, ua.Variant):
            return self.variant(value)
        if isinstance(value, ua.DataValue):
            return self.data_value(value)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return {f.name: self.value(getattr(value, f.name)) for f in dataclasses.fields(value)}
        return str(value)

    def status(self, code: ua.StatusCode | int) -> dict[str, Any]:
        value = code.value if isinstance(code, ua.StatusCode) else int(code)
        symbol = _SYMBOLS.get(value, "")
        return {"Code": value, "Symbol": symbol} if symbol else {"Code": value}

    def data_value(self, dv: ua.DataValue) -> dict[str, Any]:
        """A field of a DataSetMessage (DataSetFieldContentMask StatusCode | SourceTimestamp)."""
        out: dict[str, Any] = {"Value": self.variant(dv.Value)}
        code = dv.StatusCode.value if dv.StatusCode is not None else 0
        if code != 0:
            out["StatusCode"] = self.status(code)
        t = dv.SourceTimestamp or dv.ServerTimestamp
        if t is not None and t > MIN_DATE.replace(tzinfo=None if t.tzinfo is None else UTC):
            out["SourceTimestamp"] = iso(t)
        return out
