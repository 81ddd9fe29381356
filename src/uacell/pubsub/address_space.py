"""The PubSub configuration where OPC 10000-14 9.1 puts it, read-only: below Server/PublishSubscribe
one PubSubConnection (``MQTT``: PublisherId, the transport profile, the broker URL), its WriterGroup
and a DataSetWriter per writer, and per writer a PublishedDataItems in PublishedDataSets (its fields'
metadata, version and source variables) linked to the writer by DataSetToWriter. The Status/State of
connection, group and writers follows the broker connection (Operational or Error). The content masks
(the group's and each writer's MessageSettings, each writer's DataSetFieldContentMask) and the
HeaderLayoutUri are the ones the messages are built with (messages.py, schema.py).
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell.pubsub.messages import DATASET_MESSAGE_CONTENT_MASK, NETWORK_MESSAGE_CONTENT_MASK, Writer
from uacell.pubsub.schema import HEADER_LAYOUT_URI, MQTT_JSON_PROFILE, Schema
from uacell.ua import toolkit
from uacell.ua.instantiate import Instantiator

_A = ua.AttributeIds
_V = ua.VariantType
_ZERO = ua.QualifiedName("MessageSettings", 0)


class PubSubNodes:
    def __init__(self, aspace: AddressSpace, instantiator: Instantiator) -> None:
        self.aspace = aspace
        self.inst = instantiator
        self.states: list[ua.NodeId] = []  # every Status/State, written together
        self.connected: bool | None = None

    async def build(
        self,
        publisher_id: str,
        broker_url: str,
        group: str,
        publishing_interval: float,
        keep_alive: float,
        writers: Sequence[Writer],
        sources: dict[int, list[ua.NodeId]],
        schemas: Mapping[int, Schema] | None = None,
    ) -> ua.NodeId:
        ids = ua.ObjectIds
        conn = self.inst.create(
            ua.NodeId(ids.PublishSubscribe),
            ua.NodeId(ids.PubSubConnectionType),
            "MQTT",
            reference_type=ids.HasPubSubConnection,
            path="PubSub.MQTT",
        )
        await self._set(conn, "PublisherId", publisher_id, _V.String)
        await self._set(conn, "TransportProfileUri", MQTT_JSON_PROFILE, _V.String)
        await self._set(conn, "Address/NetworkInterface", "", _V.String)
        properties = [ua.KeyValuePair(Key=ua.QualifiedName("BrokerUrl"), Value=ua.Variant(broker_url, _V.String))]
        await self._set(conn, "ConnectionProperties", properties, _V.ExtensionObject)
        wg = self.inst.create(
            conn, ua.NodeId(ids.WriterGroupType), group, reference_type=ids.HasWriterGroup, path="PubSub.MQTT.Group"
        )
        await self._set(wg, "WriterGroupId", 1, _V.UInt16)
        await self._set(wg, "PublishingInterval", publishing_interval * 1000.0, _V.Double)
        await self._set(wg, "KeepAliveTime", keep_alive * 1000.0, _V.Double)
        await self._set(wg, "Priority", 0, _V.Byte)
        await self._set(wg, "LocaleIds", [], _V.String)
        await self._set(wg, "HeaderLayoutUri", HEADER_LAYOUT_URI, _V.String)
        await self._set(wg, "SecurityMode", ua.MessageSecurityMode.None_, _V.Int32)
        await self._set(wg, "MaxNetworkMessageSize", 0, _V.UInt32)
        settings = self.inst.create(
            wg, ua.NodeId(ids.JsonWriterGroupMessageType), _ZERO, path="PubSub.MQTT.Group.MessageSettings"
        )
        await self._set(settings, "NetworkMessageContentMask", NETWORK_MESSAGE_CONTENT_MASK, _V.UInt32)
        folder = ua.NodeId(ids.PublishSubscribe_PublishedDataSets)
        for w in writers:
            dw = self.inst.create(
                wg,
                ua.NodeId(ids.DataSetWriterType),
                w.name,
                reference_type=ids.HasDataSetWriter,
                path=f"PubSub.MQTT.Group.{w.writer_id}",
            )
            await self._set(dw, "DataSetWriterId", w.writer_id, _V.UInt16)
            await self._set(dw, "DataSetFieldContentMask", w.field_content_mask, _V.UInt32)
            await self._set(dw, "DataSetWriterProperties", [], _V.ExtensionObject)
            message = self.inst.create(
                dw, ua.NodeId(ids.JsonDataSetWriterMessageType), _ZERO, path=f"PubSub.MQTT.Group.{w.writer_id}.Message"
            )
            await self._set(message, "DataSetMessageContentMask", DATASET_MESSAGE_CONTENT_MASK, _V.UInt32)
            pds = self.inst.create(
                folder, ua.NodeId(ids.PublishedDataItemsType), w.name, path=f"PubSub.DataSets.{w.writer_id}"
            )
            version = ua.ConfigurationVersionDataType(MajorVersion=w.version.major, MinorVersion=w.version.minor)
            await self._set(pds, "ConfigurationVersion", version, _V.ExtensionObject)
            schema = (schemas or {}).get(w.writer_id)
            await self._set(pds, "DataSetMetaData", _metadata(w, version, schema), _V.ExtensionObject)
            published = [
                ua.PublishedVariableDataType(PublishedVariable=node, AttributeId=_A.Value)
                for node in sources.get(w.writer_id, [])
            ]
            await self._set(pds, "PublishedData", published, _V.ExtensionObject)
            self.inst.reference(pds, dw, ids.DataSetToWriter, ua.NodeClass.Object)
            self.states.append(toolkit.child(self.aspace, dw, "Status/State"))
        self.states += [toolkit.child(self.aspace, n, "Status/State") for n in (conn, wg)]
        await self.show(False)
        return conn

    async def show(self, connected: bool) -> None:
        """Status/State of every PubSub node: Operational while connected to the broker, else Error."""
        if connected == self.connected:
            return
        self.connected = connected
        state = ua.PubSubState.Operational if connected else ua.PubSubState.Error
        for node in self.states:
            await self.aspace.write_attribute_value(node, _A.Value, ua.DataValue(ua.Variant(state, _V.Int32)))

    async def _set(self, root: ua.NodeId, path: str, value: Any, vtype: ua.VariantType) -> None:
        node = toolkit.child(self.aspace, root, path)
        await self.aspace.write_attribute_value(node, _A.Value, ua.DataValue(ua.Variant(value, vtype)))
        read_only = ua.Variant(ua.AccessLevel.CurrentRead.mask, _V.Byte)
        for attr in (_A.AccessLevel, _A.UserAccessLevel):
            await self.aspace.write_attribute_value(node, attr, ua.DataValue(read_only))


def _metadata(w: Writer, version: ua.ConfigurationVersionDataType, schema: Schema | None) -> ua.DataSetMetaDataType:
    """The DataSetMetaData of the JSON metadata message, its NodeIds indexed by its own Namespaces
    (the first entry is NamespaceIndex 1, OPC 10000-5 §12.31)."""
    meta = w.metadata()
    types = schema.field_types if schema is not None else ()
    fields = []
    for i, f in enumerate(meta["Fields"]):
        dt = types[i] if i < len(types) else None
        fields.append(
            ua.FieldMetaData(
                Name=f["Name"],
                FieldFlags=ua.DataSetFieldFlags(0),
                BuiltInType=f["BuiltInType"],
                DataType=schema.local(dt) if schema is not None and dt is not None else _node_id(f["DataType"]),
                ValueRank=f["ValueRank"],
                DataSetFieldId=uuid.UUID(f["DataSetFieldId"]),
            )
        )
    if schema is None:
        return ua.DataSetMetaDataType(Name=w.name, Fields=fields, ConfigurationVersion=version)
    return ua.DataSetMetaDataType(
        Namespaces=list(meta["Namespaces"]),
        StructureDataTypes=schema.local_structures(),
        EnumDataTypes=schema.local_enums(),
        Name=w.name,
        Fields=fields,
        ConfigurationVersion=version,
    )


def _node_id(text: str) -> ua.NodeId:
    if text.startswith("nsu="):  # not expected: every field outside namespace 0 has its schema
        return ua.NodeId(ua.ObjectIds.BaseDataType)
    return ua.NodeId.from_string(text)
