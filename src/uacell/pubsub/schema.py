"""What a consumer needs besides the fields' names to decode a DataSet, read from the address space:
the DataTypeSchemaHeader of its DataSetMetaData (OPC 10000-14 v1.05 §6.2.3.2.2: ``Namespaces``, the
``StructureDataTypes`` and ``EnumDataTypes`` of its fields' DataTypes outside namespace 0, nested ones
too), and the PubSubConnectionDataType of the ``ua-connection`` message (§7.2.5.5.6, CompactEncoding).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell.pubsub.encoding import JsonEncoder
from uacell.pubsub.messages import (
    DATASET_MESSAGE_CONTENT_MASK,
    NETWORK_MESSAGE_CONTENT_MASK,
    Publisher,
    Topics,
    Writer,
)

_A = ua.AttributeIds
MQTT_JSON_PROFILE = "http://opcfoundation.org/UA-Profile/Transport/pubsub-mqtt-json"
# The header layout of OPC 10000-14 A.3.4 (JSON-NetworkMessage): NetworkMessage header, an array of
# DataSetMessages with their headers, header fields and field encoding as the content masks say.
HEADER_LAYOUT_URI = "http://opcfoundation.org/UA/PubSub-Layouts/JSON-NetworkMessage"
_QOS = {0: 1, 1: 2, 2: 4}  # MQTT QoS -> BrokerTransportQualityOfService (BestEffort, AtLeastOnce, ExactlyOnce)


class SchemaCollector:
    def __init__(self, aspace: AddressSpace, encoder: JsonEncoder) -> None:
        self.aspace = aspace
        self.encoder = encoder

    def _read(self, node: ua.NodeId, attribute: int) -> Any:
        dv = self.aspace.read_attribute_value(node, attribute)
        if dv.StatusCode is not None and not dv.StatusCode.is_good():
            return None
        return dv.Value.Value if dv.Value is not None else None

    def is_abstract(self, data_type: ua.NodeId) -> bool:
        return bool(self._read(data_type, _A.IsAbstract))

    def enum_names(self, data_type: ua.NodeId) -> tuple[tuple[int, str], ...]:
        """An Enumeration's (value, name) pairs; none for any other DataType."""
        definition = self._read(data_type, _A.DataTypeDefinition)
        if not isinstance(definition, ua.EnumDefinition):
            return ()
        return tuple((int(f.Value), str(f.Name)) for f in definition.Fields or [])

    def describe(self, data_types: Iterable[ua.NodeId | None]) -> Schema:
        """The structures and enumerations outside namespace 0 that fields of these DataTypes use."""
        field_types = tuple(data_types)
        structures: dict[ua.NodeId, ua.StructureDescription] = {}
        enums: dict[ua.NodeId, ua.EnumDescription] = {}
        todo = [dt for dt in field_types if dt is not None]
        seen: set[ua.NodeId] = set()
        while todo:
            dt = todo.pop()
            if dt in seen or dt.NamespaceIndex == 0:
                continue
            seen.add(dt)
            definition = self._read(dt, _A.DataTypeDefinition)
            name = self._read(dt, _A.BrowseName)
            if not isinstance(name, ua.QualifiedName):
                continue
            if isinstance(definition, ua.StructureDefinition):
                structures[dt] = ua.StructureDescription(DataTypeId=dt, Name=name, StructureDefinition=definition)
                todo += [f.DataType for f in definition.Fields or [] if isinstance(f.DataType, ua.NodeId)]
            elif isinstance(definition, ua.EnumDefinition):
                enums[dt] = ua.EnumDescription(DataTypeId=dt, Name=name, EnumDefinition=definition, BuiltInType=6)
        used = {dt.NamespaceIndex for dt in seen}
        for d in structures.values():
            definition = d.StructureDefinition
            used |= {n.NamespaceIndex for n in (definition.DefaultEncodingId, definition.BaseDataType) if n}
        return Schema(tuple(sorted(used - {0})), tuple(structures.values()), tuple(enums.values()), field_types)

    def header(self, schema: Schema) -> dict[str, Any]:
        """``Namespaces``, ``StructureDataTypes`` and ``EnumDataTypes`` in JSON (NodeIds name their URI)."""
        return {
            "Namespaces": [u for u in (self.encoder.uri(i) for i in schema.namespaces) if u],
            "StructureDataTypes": [self.encoder.value(d) for d in schema.structures],
            "EnumDataTypes": [self.encoder.value(d) for d in schema.enums],
        }


@dataclass(frozen=True)
class Schema:
    """A DataSet's DataTypeSchemaHeader, with the server's namespace indexes."""

    namespaces: tuple[int, ...]  # the server's namespace indexes; the header's Namespaces in this order
    structures: tuple[ua.StructureDescription, ...]
    enums: tuple[ua.EnumDescription, ...]
    field_types: tuple[ua.NodeId | None, ...] = ()  # each field's DataType

    def local(self, node: ua.NodeId) -> ua.NodeId:
        """``node`` with the NamespaceIndex the header's Namespaces give it (its first entry is 1)."""
        if node.NamespaceIndex == 0 or node.NamespaceIndex not in self.namespaces:
            return node
        return dataclasses.replace(node, NamespaceIndex=self.namespaces.index(node.NamespaceIndex) + 1)

    def local_name(self, name: ua.QualifiedName) -> ua.QualifiedName:
        if name.NamespaceIndex == 0 or name.NamespaceIndex not in self.namespaces:
            return name
        return ua.QualifiedName(name.Name, self.namespaces.index(name.NamespaceIndex) + 1)

    def local_structures(self) -> list[ua.StructureDescription]:
        out = []
        for d in self.structures:
            definition = d.StructureDefinition
            fields = [dataclasses.replace(f, DataType=self.local(f.DataType)) for f in definition.Fields or []]
            local = dataclasses.replace(
                definition,
                DefaultEncodingId=self.local(definition.DefaultEncodingId),
                BaseDataType=self.local(definition.BaseDataType),
                Fields=fields,
            )
            out.append(ua.StructureDescription(self.local(d.DataTypeId), self.local_name(d.Name), local))
        return out

    def local_enums(self) -> list[ua.EnumDescription]:
        return [
            ua.EnumDescription(self.local(d.DataTypeId), self.local_name(d.Name), d.EnumDefinition, d.BuiltInType)
            for d in self.enums
        ]


class _Settings(Protocol):
    publishing_interval: float
    keep_alive: int
    qos: int
    topic_prefix: str


def connection_config(publisher: Publisher, cfg: _Settings, writers: Sequence[Writer]) -> dict[str, Any]:
    """The PubSubConnectionDataType (§6.2.7.5.1) in the CompactEncoding (default values left out), without
    Address, ReaderGroups and configuration properties (§7.2.5.5.6)."""
    topics = Topics(cfg.topic_prefix, publisher.publisher_id, publisher.writer_group)
    qos = _QOS.get(cfg.qos, 0)
    group: dict[str, Any] = {
        "Name": publisher.writer_group,
        "Enabled": True,
        "SecurityMode": ua.MessageSecurityMode.None_.value,
        "WriterGroupId": 1,
        "PublishingInterval": cfg.publishing_interval * 1000.0,
        "KeepAliveTime": cfg.keep_alive * 1000.0,
        "HeaderLayoutUri": HEADER_LAYOUT_URI,
        "MessageSettings": {
            "UaTypeId": f"i={ua.ObjectIds.JsonWriterGroupMessageDataType}",
            "NetworkMessageContentMask": NETWORK_MESSAGE_CONTENT_MASK,
        },
        "DataSetWriters": [_writer(w, topics, qos) for w in writers],
    }
    return {
        "Name": "MQTT",
        "Enabled": True,
        "PublisherId": {"UaType": ua.VariantType.String.value, "Value": publisher.publisher_id},
        "TransportProfileUri": MQTT_JSON_PROFILE,
        "WriterGroups": [group],
    }


def _writer(w: Writer, topics: Topics, qos: int) -> dict[str, Any]:
    out: dict[str, Any] = {"Name": w.name, "Enabled": True, "DataSetWriterId": w.writer_id}
    if w.field_content_mask:
        out["DataSetFieldContentMask"] = w.field_content_mask
    if not w.events:
        out["KeyFrameCount"] = w.keyframe_count
    out["DataSetName"] = w.name
    out["TransportSettings"] = {
        "UaTypeId": f"i={ua.ObjectIds.BrokerDataSetWriterTransportDataType}",
        "QueueName": topics.data(w.name),
        "MetaDataQueueName": topics.metadata(w.name),
        **({"RequestedDeliveryGuarantee": qos} if qos else {}),
    }
    out["MessageSettings"] = {
        "UaTypeId": f"i={ua.ObjectIds.JsonDataSetWriterMessageDataType}",
        "DataSetMessageContentMask": DATASET_MESSAGE_CONTENT_MASK,
    }
    return out
