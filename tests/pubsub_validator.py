"""A validator of OPC UA PubSub JSON over MQTT, written from OPC 10000-14 v1.05 (§7.2.5 JSON message
mapping, §7.3.4/§7.3.5 MQTT topics) and OPC 10000-6 v1.05 (§5.4 JSON VerboseEncoding, §5.1.12 string
forms) alone, not from uacell's code. Feed it every message of a broker (``check``); it learns each
Publisher's declared configuration from its ``ua-connection`` message and each DataSet's fields from
its ``ua-metadata`` message, and checks the data messages against both. ``Invalid`` says what is wrong.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any


class Invalid(AssertionError):
    pass


ISO_UTC = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d{1,9})?Z$")  # §5.4.2.6: UTC, 'Z'
NODE_ID = re.compile(r"^(nsu=[^;]+;|ns=\d+;)?(i=\d+|s=.+|g=[0-9A-Fa-f-]{36}|b=[A-Za-z0-9+/=]*)$")  # §5.1.12
INT_RANGES = {2: (-(2**7), 2**7 - 1), 3: (0, 2**8 - 1), 4: (-(2**15), 2**15 - 1), 5: (0, 2**16 - 1)}
INT_RANGES |= {6: (-(2**31), 2**31 - 1), 7: (0, 2**32 - 1), 8: (-(2**63), 2**63 - 1), 9: (0, 2**64 - 1)}
# DataTypes of namespace 0 that are not built-in types but subtypes of one (OPC 10000-3/-5)
NS0_SIMPLE = {"i=290": 11, "i=294": 13, "i=295": 12, "i=288": 7, "i=289": 7, "i=291": 12, "i=292": 12}
NS0_ABSTRACT = {"i=24", "i=26", "i=27", "i=28", "i=22", "i=29"}  # BaseDataType, Number, Integer, UInteger...
DATAVALUE_KEYS = {  # §5.4.2.18, with the DataSetFieldContentMask bit that allows each (§6.2.4.2)
    "Status": 0x1,
    "SourceTimestamp": 0x2,
    "ServerTimestamp": 0x4,
    "SourcePicoseconds": 0x8,
    "ServerPicoseconds": 0x10,
}
DSM_HEADER = {  # JsonDataSetMessageContentMask bit -> DataSetMessage field (§6.3.2.3.1, §7.2.5.4)
    0x1: "DataSetWriterId",
    0x2: "MetaDataVersion",
    0x4: "SequenceNumber",
    0x8: "Timestamp",
    0x20: "MessageType",
    0x40: "DataSetWriterName",
    0x100: "PublisherId",
    0x200: "WriterGroupName",
    0x400: "MinorVersion",
}
MESSAGE_TYPES = {"data": "ua-data", "metadata": "ua-metadata", "status": "ua-status", "connection": "ua-connection"}
DSM_TYPES = {"ua-keyframe", "ua-deltaframe", "ua-event", "ua-keepalive", "ua-condition"}
JSON_WRITER_GROUP_MESSAGE = "i=15657"  # JsonWriterGroupMessageDataType
JSON_WRITER_MESSAGE = "i=15664"  # JsonDataSetWriterMessageDataType


def fail(where: str, why: str) -> None:
    raise Invalid(f"{where}: {why}")


def need(ok: bool, where: str, why: str) -> None:
    if not ok:
        fail(where, why)


def keys_within(obj: Any, allowed: set[str], where: str) -> dict[str, Any]:
    need(isinstance(obj, dict), where, f"a JSON object, not {obj!r}")
    extra = set(obj) - allowed
    need(not extra, where, f"fields the standard does not define: {sorted(extra)}")
    return dict(obj)


def uint(value: Any, bits: int, where: str) -> int:
    need(isinstance(value, int) and not isinstance(value, bool), where, f"a JSON number, not {value!r}")
    need(0 <= value < 2**bits, where, f"out of UInt{bits} range: {value}")
    return int(value)


def string(value: Any, where: str, *, empty: bool = True) -> str:
    need(isinstance(value, str), where, f"a JSON string, not {value!r}")
    need(empty or value != "", where, "empty")
    return str(value)


def status_code(value: Any, where: str, *, verbose: bool) -> None:
    """§5.4.2.12: {"Code", "Symbol"}, both left out for Good; Symbol not in the CompactEncoding."""
    obj = keys_within(value, {"Code", "Symbol"}, where)
    if "Code" in obj:
        need(uint(obj["Code"], 32, where + ".Code") != 0, where, "Code 0 (Good) is left out")
    else:
        need("Symbol" not in obj, where, "a Symbol without a Code")
    if "Symbol" in obj:
        need(verbose, where, "Symbol is left out in the CompactEncoding")
        need(string(obj["Symbol"], where) not in ("", "Good"), where, "Symbol of Good is left out")


def version_time(value: Any, where: str) -> int:
    """VersionTime (OPC 10000-4 §7.43): seconds since 2000-01-01 UTC, not in the future."""
    v = uint(value, 32, where)
    now = int((datetime.now(UTC) - datetime(2000, 1, 1, tzinfo=UTC)).total_seconds())
    need(v <= now + 86400, where, f"{v} is not seconds since 2000 (later than now)")
    need(v >= 10 * 365 * 86400, where, f"{v} is not a VersionTime of this century's second decade or later")
    return v


def configuration_version(value: Any, where: str) -> tuple[int, int]:
    obj = keys_within(value, {"MajorVersion", "MinorVersion"}, where)
    need(set(obj) == {"MajorVersion", "MinorVersion"}, where, "MajorVersion and MinorVersion (verbose: both)")
    major = version_time(obj["MajorVersion"], where + ".MajorVersion")
    minor = version_time(obj["MinorVersion"], where + ".MinorVersion")
    need(minor >= major, where, "MinorVersion is updated with every change, so never older than MajorVersion")
    return major, minor


def guid(value: Any, where: str) -> None:
    try:
        uuid.UUID(string(value, where))
    except ValueError:
        fail(where, f"not a Guid: {value!r}")


def node_id(value: Any, where: str, *, verbose: bool) -> str:
    text = string(value, where, empty=False)
    need(bool(NODE_ID.match(text)), where, f"not a NodeId string of OPC 10000-6 §5.1.12: {text!r}")
    need(not text.startswith("ns=0;"), where, "namespace 0 is written without 'ns=0;'")
    if verbose:
        need(not text.startswith("ns="), where, f"the VerboseEncoding names the namespace by URI (nsu=): {text!r}")
    return text


def namespace_of(data_type: str) -> str | None:
    return data_type[4:].split(";", 1)[0] if data_type.startswith("nsu=") else None


@dataclass
class MetaData:
    version: tuple[int, int]
    fields: dict[str, dict[str, Any]]
    order: list[str]
    structures: dict[str, dict[str, Any]]
    enums: dict[str, dict[str, Any]]


@dataclass
class Declared:
    """What a ua-connection message declares for one DataSetWriter."""

    network_mask: int
    dataset_mask: int
    field_mask: int


@dataclass
class Validator:
    prefix: str = "opcua"
    metadata: dict[tuple[str, int], MetaData] = field(default_factory=dict)
    declared: dict[tuple[str, int], Declared] = field(default_factory=dict)
    message_ids: dict[str, bytes] = field(default_factory=dict)
    checked: dict[str, int] = field(default_factory=dict)  # MessageType -> how many passed
    cleared: set[str] = field(default_factory=set)  # topics whose retained message was cleared

    # -- a message on a topic -------------------------------------------------------------------

    def check(self, topic: str, payload: bytes, *, retain: bool = False) -> dict[str, Any] | None:
        levels = topic.split("/")
        base = self.prefix.split("/")
        need(levels[: len(base)] == base and len(levels) >= len(base) + 3, topic, "not <prefix>/json/<type>/<id>")
        encoding, kind, publisher = levels[len(base) : len(base) + 3]
        rest = levels[len(base) + 3 :]
        need(encoding == "json", topic, "the encoding level is 'json' (§7.3.4.7.1)")
        need(kind in MESSAGE_TYPES, topic, f"unknown message type level {kind!r}")
        if kind in ("data", "metadata"):
            need(len(rest) == 2, topic, f"{kind} topics end with <WriterGroup>/<DataSetWriter> (§7.3.4.7)")
        else:
            need(not rest, topic, f"{kind} topics end with the PublisherId")
        if payload == b"":  # clears a retained message (MQTT 3.1.1 §3.3.1.3); live subscribers get it unretained
            need(kind != "data", topic, "an empty payload only clears a retained message, and data is not retained")
            self.cleared.add(topic)
            return None
        try:
            body = json.loads(payload.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            fail(topic, f"not UTF-8 JSON: {exc}")
        need(isinstance(body, dict), topic, "a JSON object")
        need(body.get("MessageType") == MESSAGE_TYPES[kind], topic, f"MessageType {MESSAGE_TYPES[kind]!r}")
        need(body.get("PublisherId") == publisher, topic, "PublisherId equals the topic's PublisherId level")
        message_id = string(body.get("MessageId"), topic + " MessageId", empty=False)
        earlier = self.message_ids.get(message_id)
        need(earlier is None or earlier == payload, topic, f"MessageId {message_id} reused for another message")
        self.message_ids[message_id] = payload
        {"data": self._data, "metadata": self._metadata, "status": self._status, "connection": self._connection}[kind](
            body, topic, rest
        )
        self.checked[body["MessageType"]] = self.checked.get(body["MessageType"], 0) + 1
        return dict(body)

    # -- ua-status (§7.2.5.5.5, Table 191) -------------------------------------------------------

    def _status(self, body: dict[str, Any], where: str, _rest: list[str]) -> None:
        keys_within(
            body,
            {"MessageId", "MessageType", "PublisherId", "Timestamp", "IsCyclic", "Status", "NextReportTime"},
            where,
        )
        need("Status" in body, where, "Status is mandatory")
        state = body["Status"]
        if isinstance(state, str):  # the VerboseEncoding of an Enumeration: <name>_<value>
            need(state in ("Disabled_0", "Paused_1", "Operational_2", "Error_3", "PreOperational_4"), where, state)
        else:
            need(uint(state, 32, where + ".Status") <= 4, where, "PubSubState is 0..4")
        cyclic = body.get("IsCyclic", False)
        need(isinstance(cyclic, bool), where, "IsCyclic is a Boolean")
        for key in ("Timestamp", "NextReportTime"):
            if cyclic:
                need(key in body, where, f"{key} is mandatory when IsCyclic")
                need(bool(ISO_UTC.match(string(body[key], where))), where, f"{key} UtcTime")
            else:
                need(key not in body, where, f"{key} is left out when IsCyclic is false")

    # -- ua-connection (§7.2.5.5.6): the PubSubConnectionDataType in the CompactEncoding -------------

    def _connection(self, body: dict[str, Any], where: str, _rest: list[str]) -> None:
        keys_within(body, {"MessageId", "MessageType", "PublisherId", "Timestamp", "Connection"}, where)
        need(bool(ISO_UTC.match(string(body.get("Timestamp"), where + ".Timestamp"))), where, "Timestamp mandatory")
        conn = keys_within(
            body.get("Connection"),
            {
                "Name",
                "Enabled",
                "PublisherId",
                "TransportProfileUri",
                "Address",
                "ConnectionProperties",
                "TransportSettings",
                "WriterGroups",
                "ReaderGroups",
            },
            where + ".Connection",
        )
        compact(conn, where + ".Connection")
        for empty in ("Address", "ReaderGroups", "ConnectionProperties"):
            need(empty not in conn, where, f"Connection.{empty} is empty in a ua-connection message")
        pid = keys_within(conn.get("PublisherId"), {"UaType", "Value"}, where + ".Connection.PublisherId")
        need(pid.get("Value") == body["PublisherId"], where, "Connection.PublisherId is the message's PublisherId")
        need(
            conn.get("TransportProfileUri") == "http://opcfoundation.org/UA-Profile/Transport/pubsub-mqtt-json",
            where,
            "the MQTT JSON transport profile",
        )
        for g, group in enumerate(conn.get("WriterGroups", [])):
            gw = f"{where}.WriterGroups[{g}]"
            keys_within(
                group,
                {
                    "Name",
                    "Enabled",
                    "SecurityMode",
                    "SecurityGroupId",
                    "SecurityKeyServices",
                    "MaxNetworkMessageSize",
                    "GroupProperties",
                    "WriterGroupId",
                    "PublishingInterval",
                    "KeepAliveTime",
                    "Priority",
                    "LocaleIds",
                    "HeaderLayoutUri",
                    "TransportSettings",
                    "MessageSettings",
                    "DataSetWriters",
                },
                gw,
            )
            need("GroupProperties" not in group, gw, "configuration properties are not included")
            settings = keys_within(group.get("MessageSettings"), {"UaTypeId", "NetworkMessageContentMask"}, gw)
            need(settings.get("UaTypeId") == JSON_WRITER_GROUP_MESSAGE, gw, "JsonWriterGroupMessageDataType")
            network_mask = uint(settings.get("NetworkMessageContentMask", 0), 32, gw)
            layout = group.get("HeaderLayoutUri", "")
            if layout == "http://opcfoundation.org/UA/PubSub-Layouts/JSON-NetworkMessage":  # A.3.4.2
                need(
                    network_mask & 0x3 == 0x3 and not network_mask & 0x4,
                    gw,
                    "JSON-NetworkMessage: both headers, an array",
                )
            elif layout == "http://opcfoundation.org/UA/PubSub-Layouts/JSON-DataSetMessage":  # A.3.3.2
                need(network_mask & 0x7 == 0x6, gw, "JSON-DataSetMessage: one DataSetMessage with its header only")
            else:
                need(layout == "", gw, f"an unknown HeaderLayoutUri {layout!r}")
            for w, writer in enumerate(group.get("DataSetWriters", [])):
                ww = f"{gw}.DataSetWriters[{w}]"
                keys_within(
                    writer,
                    {
                        "Name",
                        "Enabled",
                        "DataSetWriterId",
                        "DataSetFieldContentMask",
                        "KeyFrameCount",
                        "DataSetName",
                        "DataSetWriterProperties",
                        "TransportSettings",
                        "MessageSettings",
                    },
                    ww,
                )
                need("DataSetWriterProperties" not in writer, ww, "configuration properties are not included")
                ms = keys_within(writer.get("MessageSettings"), {"UaTypeId", "DataSetMessageContentMask"}, ww)
                need(ms.get("UaTypeId") == JSON_WRITER_MESSAGE, ww, "JsonDataSetWriterMessageDataType")
                writer_id = uint(writer.get("DataSetWriterId"), 16, ww + ".DataSetWriterId")
                self.declared[(body["PublisherId"], writer_id)] = Declared(
                    network_mask,
                    uint(ms.get("DataSetMessageContentMask", 0), 32, ww),
                    uint(writer.get("DataSetFieldContentMask", 0), 32, ww),
                )

    # -- ua-metadata (§7.2.5.5.3) ------------------------------------------------------------------

    def _metadata(self, body: dict[str, Any], where: str, rest: list[str]) -> None:
        keys_within(
            body,
            {
                "MessageId",
                "MessageType",
                "PublisherId",
                "DataSetWriterId",
                "DataSetWriterName",
                "WriterGroupName",
                "Timestamp",
                "MetaData",
            },
            where,
        )
        writer_id = uint(body.get("DataSetWriterId"), 16, where + ".DataSetWriterId")
        for mandatory in ("WriterGroupName", "DataSetWriterName", "Timestamp"):  # Table 188
            need(mandatory in body, where, f"{mandatory} is mandatory in ua-metadata")
        need(body["WriterGroupName"] == rest[0], where, "WriterGroupName equals the topic's writer group level")
        need(body["DataSetWriterName"] == rest[1], where, "DataSetWriterName equals the topic's writer level")
        need(bool(ISO_UTC.match(string(body["Timestamp"], where))), where, "Timestamp is ISO 8601 UTC")
        meta = keys_within(
            body.get("MetaData"),
            {
                "Namespaces",
                "StructureDataTypes",
                "EnumDataTypes",
                "SimpleDataTypes",
                "Name",
                "Description",
                "Fields",
                "DataSetClassId",
                "ConfigurationVersion",
            },
            where + ".MetaData",
        )
        version = configuration_version(meta.get("ConfigurationVersion"), where + ".ConfigurationVersion")
        namespaces = meta.get("Namespaces") or []
        need(isinstance(namespaces, list) and all(isinstance(n, str) and n for n in namespaces), where, "Namespaces")
        structures: dict[str, dict[str, Any]] = {}
        for s in meta.get("StructureDataTypes") or []:
            sw = f"{where}.StructureDataTypes"
            keys_within(s, {"DataTypeId", "Name", "StructureDefinition"}, sw)
            definition = keys_within(
                s.get("StructureDefinition"), {"DefaultEncodingId", "BaseDataType", "StructureType", "Fields"}, sw
            )
            for f in definition.get("Fields") or []:
                keys_within(
                    f,
                    {
                        "Name",
                        "Description",
                        "DataType",
                        "ValueRank",
                        "ArrayDimensions",
                        "MaxStringLength",
                        "IsOptional",
                    },
                    sw,
                )
                node_id(f.get("DataType"), sw + ".DataType", verbose=True)
            structures[node_id(s.get("DataTypeId"), sw, verbose=True)] = definition
        enums: dict[str, dict[str, Any]] = {}
        for e in meta.get("EnumDataTypes") or []:
            ew = f"{where}.EnumDataTypes"
            keys_within(e, {"DataTypeId", "Name", "EnumDefinition", "BuiltInType"}, ew)
            enums[node_id(e.get("DataTypeId"), ew, verbose=True)] = keys_within(e.get("EnumDefinition"), {"Fields"}, ew)
        fields: dict[str, dict[str, Any]] = {}
        order: list[str] = []
        for i, f in enumerate(meta.get("Fields") or []):
            fw = f"{where}.Fields[{i}]"
            keys_within(
                f,
                {
                    "Name",
                    "Description",
                    "FieldFlags",
                    "BuiltInType",
                    "DataType",
                    "ValueRank",
                    "ArrayDimensions",
                    "MaxStringLength",
                    "DataSetFieldId",
                    "Properties",
                },
                fw,
            )
            name = string(f.get("Name"), fw + ".Name", empty=False)
            need(name not in fields, fw, f"field name {name!r} twice")
            builtin = uint(f.get("BuiltInType"), 8, fw + ".BuiltInType")
            need(builtin <= 25, fw, f"BuiltInType {builtin} (0..25)")
            dt = node_id(f.get("DataType"), fw + ".DataType", verbose=True)
            if dt.startswith("i=") and int(dt[2:]) <= 25 and dt not in NS0_ABSTRACT:
                need(builtin == int(dt[2:]), fw, f"BuiltInType {builtin} does not match DataType {dt}")
            guid(f.get("DataSetFieldId"), fw + ".DataSetFieldId")
            need(isinstance(f.get("ValueRank"), int), fw, "ValueRank")
            self._described(dt, structures, enums, namespaces, fw)
            fields[name] = dict(f)
            order.append(name)
        for definition in structures.values():
            for f in definition.get("Fields") or []:
                self._described(f["DataType"], structures, enums, namespaces, where + ".StructureDataTypes")
        self.metadata[(body["PublisherId"], writer_id)] = MetaData(version, fields, order, structures, enums)

    @staticmethod
    def _described(
        dt: str, structures: dict[str, Any], enums: dict[str, Any], namespaces: list[str], where: str
    ) -> None:
        uri = namespace_of(dt)
        if uri is None and dt.startswith("ns="):
            fail(where, f"{dt}: a namespace index in metadata")
        if uri is not None and uri != "http://opcfoundation.org/UA/":
            need(uri in namespaces, where, f"namespace {uri} of {dt} is not in Namespaces")
            need(
                dt in structures or dt in enums,
                where,
                f"DataType {dt} is described in neither StructureDataTypes "
                "nor EnumDataTypes: a consumer cannot decode the field",
            )

    # -- ua-data (§7.2.5.3, §7.2.5.4) -------------------------------------------------------------

    def _data(self, body: dict[str, Any], where: str, rest: list[str]) -> None:
        keys_within(
            body, {"MessageId", "MessageType", "PublisherId", "WriterGroupName", "DataSetClassId", "Messages"}, where
        )
        need(body.get("WriterGroupName", rest[0]) == rest[0], where, "WriterGroupName equals the topic's level")
        messages = body.get("Messages")
        declared = [d for (p, _w), d in self.declared.items() if p == body["PublisherId"]]
        need(bool(declared), where, "no ua-connection message declared this Publisher's writers before its data")
        if declared[0].network_mask & 0x4:  # SingleDataSetMessage: an object, else an array (§7.2.5.3)
            need(isinstance(messages, dict), where, "Messages is a JSON object when SingleDataSetMessage is declared")
            messages = [messages]
        need(isinstance(messages, list) and len(messages) >= 1, where, "Messages is an array of DataSetMessages")
        assert isinstance(messages, list)
        for i, message in enumerate(messages):
            self._dataset_message(body, message, f"{where}.Messages[{i}]", rest)

    def _dataset_message(self, body: dict[str, Any], m: Any, where: str, rest: list[str]) -> None:
        keys_within(m, set(DSM_HEADER.values()) | {"Status", "Payload"}, where)
        writer_id = uint(m.get("DataSetWriterId"), 16, where + ".DataSetWriterId")
        need(writer_id != 0, where, "DataSetWriterId 0 is not a writer")
        key = (body["PublisherId"], writer_id)
        declared = self.declared.get(key)
        need(declared is not None, where, f"writer {writer_id} is not declared in the ua-connection message")
        assert declared is not None
        for bit, name in DSM_HEADER.items():
            if declared.dataset_mask & bit:
                need(name in m, where, f"{name} is declared by the DataSetMessageContentMask but missing")
            else:
                need(name not in m, where, f"{name} is sent but the DataSetMessageContentMask leaves it out")
        need("Status" not in m or bool(declared.dataset_mask & 0x10), where, "Status is not declared")
        if "Status" in m:
            status_code(m["Status"], where + ".Status", verbose=True)
        if "DataSetWriterName" in m:
            need(m["DataSetWriterName"] == rest[1], where, "DataSetWriterName equals the topic's writer level")
        uint(m.get("SequenceNumber", 0), 32, where + ".SequenceNumber")
        if "Timestamp" in m:
            need(bool(ISO_UTC.match(string(m["Timestamp"], where))), where, "Timestamp is ISO 8601 UTC")
        kind = m.get("MessageType", "ua-keyframe")
        need(kind in DSM_TYPES, where, f"MessageType {kind!r}")
        verbose = bool(declared.dataset_mask & 0x800) and not declared.dataset_mask & 0x80
        need(verbose, where, "only the VerboseEncoding (FieldEncoding2 set, FieldEncoding1 clear) is checked here")
        meta = self.metadata.get(key)
        need(meta is not None, where, f"no ua-metadata for writer {writer_id} before its data")
        assert meta is not None
        if "MetaDataVersion" in m:
            version = configuration_version(m["MetaDataVersion"], where + ".MetaDataVersion")
            need(version[0] == meta.version[0], where, "MajorVersion differs from the metadata's")
        if kind == "ua-keepalive":
            need("Payload" not in m, where, "a keep-alive has no Payload")
            return
        payload = keys_within(m.get("Payload"), set(meta.fields), where + ".Payload")
        if kind in ("ua-keyframe", "ua-event"):  # every field with its name and value (§7.2.5.4)
            need(set(payload) == set(meta.fields), where, f"missing fields {sorted(set(meta.fields) - set(payload))}")
        need(bool(payload) or kind == "ua-deltaframe", where, "an empty Payload")
        for name, value in payload.items():
            self._field(value, meta.fields[name], meta, declared.field_mask, f"{where}.Payload[{name!r}]")

    def _field(self, value: Any, fmd: dict[str, Any], meta: MetaData, mask: int, where: str) -> None:
        dt, rank = fmd["DataType"], fmd["ValueRank"]
        abstract = dt in NS0_ABSTRACT or fmd["BuiltInType"] == 0
        if mask & 0x1F:  # a DataValue (§6.2.4.2, §5.4.2.18)
            allowed = {"Value", "UaType", "Dimensions"} | {k for k, bit in DATAVALUE_KEYS.items() if mask & bit}
            dv = keys_within(value, allowed, where)
            need("Value" in dv, where, "the VerboseEncoding writes a null Value as null, not leaves it out")
            if "Status" in dv:
                status_code(dv["Status"], where + ".Status", verbose=True)
            for t in ("SourceTimestamp", "ServerTimestamp"):
                if t in dv:
                    need(bool(ISO_UTC.match(string(dv[t], where))), where, f"{t} is ISO 8601 UTC")
            inner = dv["Value"]
            if abstract and inner is not None:
                need("UaType" in dv, where, "an abstract DataType keeps the Variant's UaType")
                self._value(inner, uint(dv["UaType"], 8, where), "", rank, meta, where)
            else:
                need("UaType" not in dv, where, "a concrete DataType's Variant is collapsed (no UaType, §7.2.5.4.2)")
                self._typed(inner, fmd, meta, where)
        elif abstract and value is not None:  # a Variant that keeps its type
            v = keys_within(value, {"UaType", "Value", "Dimensions"}, where)
            self._value(v.get("Value"), uint(v.get("UaType"), 8, where), "", rank, meta, where)
        else:  # a Variant collapsed to its value
            self._typed(value, fmd, meta, where)

    def _typed(self, value: Any, fmd: dict[str, Any], meta: MetaData, where: str) -> None:
        self._value(value, fmd["BuiltInType"], fmd["DataType"], fmd["ValueRank"], meta, where)

    def _value(self, value: Any, builtin: int, dt: str, rank: int, meta: MetaData, where: str) -> None:
        if value is None:
            return  # the VerboseEncoding's null
        if rank >= 1 or (rank in (0, -2, -3) and isinstance(value, list)):
            need(isinstance(value, list), where, "an array")
            for i, item in enumerate(value):
                self._value(item, builtin, dt, -1, meta, f"{where}[{i}]")
            return
        if dt in meta.enums:
            names = {f"{f['Name']}_{f['Value']}" for f in meta.enums[dt].get("Fields") or []}
            need(value in names, where, f"a verbose Enumeration '<name>_<value>' of {sorted(names)}, not {value!r}")
            return
        if dt in meta.structures:
            definition = meta.structures[dt]
            declared = {f["Name"]: f for f in definition.get("Fields") or []}
            obj = keys_within(value, set(declared), where)
            for name, f in declared.items():
                need(name in obj or f.get("IsOptional"), where, f"structure field {name!r} (verbose: every field)")
                if name in obj:
                    sub = f["DataType"]
                    b = int(sub[2:]) if sub.startswith("i=") and int(sub[2:]) <= 25 else NS0_SIMPLE.get(sub, 22)
                    self._value(obj[name], b, sub, f.get("ValueRank", -1), meta, f"{where}.{name}")
            return
        builtin = NS0_SIMPLE.get(dt, builtin)
        self._builtin(value, builtin, where)

    @staticmethod
    def _builtin(value: Any, builtin: int, where: str) -> None:
        if builtin == 1:
            need(isinstance(value, bool), where, f"Boolean true/false, not {value!r}")
        elif builtin in (2, 3, 4, 5, 6, 7):
            low, high = INT_RANGES[builtin]
            need(isinstance(value, int) and not isinstance(value, bool), where, f"an integer number, not {value!r}")
            need(low <= value <= high, where, f"out of range: {value}")
        elif builtin in (8, 9):
            need(
                isinstance(value, str) and bool(re.fullmatch(r"-?\d+", value)),
                where,
                f"(U)Int64 as a string: {value!r}",
            )
            low, high = INT_RANGES[builtin]
            need(low <= int(value) <= high, where, f"out of range: {value}")
        elif builtin in (10, 11):
            need(
                (isinstance(value, int | float) and not isinstance(value, bool))
                or value in ("NaN", "Infinity", "-Infinity"),
                where,
                f"a number, not {value!r}",
            )
        elif builtin in (12, 16, 20):
            string(value, where)
        elif builtin == 13:
            need(bool(ISO_UTC.match(string(value, where))), where, f"DateTime ISO 8601 UTC, not {value!r}")
            # DateTime.MinValue (the binary encoding's 0, 1601-01-01) is written 0001-01-01T00:00:00Z (§5.4.2.6)
            need(not value.startswith("1601-01-01T00:00:00"), where, "DateTime.MinValue is 0001-01-01T00:00:00Z")
        elif builtin == 14:
            guid(value, where)
        elif builtin == 15:
            try:
                base64.b64decode(string(value, where), validate=True)
            except binascii.Error:
                fail(where, f"ByteString base64, not {value!r}")
        elif builtin in (17, 18):
            node_id(value, where, verbose=True)
        elif builtin == 19:
            status_code(value, where, verbose=True)
        elif builtin == 21:
            lt = keys_within(value, {"Locale", "Text"}, where)
            for k, v in lt.items():
                need(string(v, f"{where}.{k}") != "", where, f"an empty {k} is left out (§5.4.2.15)")
        elif builtin == 22:
            need(isinstance(value, dict), where, "a structure is a JSON object")
        elif builtin == 0:
            pass


def compact(obj: Any, where: str) -> None:
    """The CompactEncoding leaves out fields with default values (OPC 10000-6 §5.4.1)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            need(v not in (0, False, "", [], {}, None), where, f"{k}: a default value is left out")
            compact(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            compact(v, f"{where}[{i}]")
