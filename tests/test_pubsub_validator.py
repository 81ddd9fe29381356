"""The PubSub validator (tests/pubsub_validator.py, written from OPC 10000-14/-6 v1.05) on crafted
messages: a consistent good set passes, and each message breaking one rule of the standard is refused
with the rule named. The same validator checks every message a served cell sends in
tests/test_pubsub_standard.py."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from typing import Any

import pytest
from pubsub_validator import Invalid, Validator

P = "line1-cell4"
NS = "http://opcfoundation.org/UA/PackML/"
ALARM = f"nsu={NS};i=15"
VERSION = {"MajorVersion": 849_000_000, "MinorVersion": 849_000_100}


def connection() -> dict[str, Any]:
    def writer(writer_id: int, name: str, field_mask: int) -> dict[str, Any]:
        w: dict[str, Any] = {"Name": name, "Enabled": True, "DataSetWriterId": writer_id, "DataSetName": name}
        if field_mask:
            w["DataSetFieldContentMask"] = field_mask
        w["MessageSettings"] = {"UaTypeId": "i=15664", "DataSetMessageContentMask": 2175}
        return w

    return {
        "MessageId": "c-1",
        "MessageType": "ua-connection",
        "PublisherId": P,
        "Timestamp": "2026-11-25T18:00:00Z",
        "Connection": {
            "Name": "MQTT",
            "Enabled": True,
            "PublisherId": {"UaType": 12, "Value": P},
            "TransportProfileUri": "http://opcfoundation.org/UA-Profile/Transport/pubsub-mqtt-json",
            "WriterGroups": [
                {
                    "Name": "Cell",
                    "Enabled": True,
                    "WriterGroupId": 1,
                    "PublishingInterval": 500.0,
                    "HeaderLayoutUri": "http://opcfoundation.org/UA/PubSub-Layouts/JSON-NetworkMessage",
                    "MessageSettings": {"UaTypeId": "i=15657", "NetworkMessageContentMask": 75},
                    "DataSetWriters": [writer(7, "Filler1", 3), writer(8, "Filler1.Events", 0)],
                }
            ],
        },
    }


def field(name: str, builtin: int, data_type: str, rank: int = -1) -> dict[str, Any]:
    return {
        "Name": name,
        "Description": {},
        "FieldFlags": 0,
        "BuiltInType": builtin,
        "DataType": data_type,
        "ValueRank": rank,
        "ArrayDimensions": [],
        "MaxStringLength": 0,
        "DataSetFieldId": "13552c95-a6e7-564a-9434-2a8a373404e9",
        "Properties": [],
    }


def metadata(writer_id: int, name: str, fields: list[dict[str, Any]], structures: bool = False) -> dict[str, Any]:
    alarm = {
        "DataTypeId": ALARM,
        "Name": f"nsu={NS};PackMLAlarmDataType",
        "StructureDefinition": {
            "DefaultEncodingId": f"nsu={NS};i=74",
            "BaseDataType": "i=22",
            "StructureType": "Structure_0",
            "Fields": [
                {"Name": "ID", "Description": {}, "DataType": "i=6", "ValueRank": -1, "ArrayDimensions": None,
                 "MaxStringLength": 0, "IsOptional": False},
                {"Name": "Message", "Description": {}, "DataType": "i=12", "ValueRank": -1, "ArrayDimensions": None,
                 "MaxStringLength": 0, "IsOptional": False},
            ],
        },
    }  # fmt: skip
    return {
        "MessageId": f"m-{writer_id}",
        "MessageType": "ua-metadata",
        "PublisherId": P,
        "DataSetWriterId": writer_id,
        "WriterGroupName": "Cell",
        "DataSetWriterName": name,
        "Timestamp": "2026-11-25T18:00:00Z",
        "MetaData": {
            "Namespaces": [NS] if structures else [],
            "StructureDataTypes": [alarm] if structures else [],
            "EnumDataTypes": [],
            "SimpleDataTypes": [],
            "Name": name,
            "Description": {},
            "Fields": fields,
            "DataSetClassId": "00000000-0000-0000-0000-000000000000",
            "ConfigurationVersion": VERSION,
        },
    }


VALUE_FIELDS = [
    field("State", 21, "i=21"),
    field("Speed", 10, "i=10"),
    field("Count", 8, "i=8"),
    field("Alarm", 22, ALARM, 1),
    field("Any", 0, "i=24"),
]
EVENT_FIELDS = [field("Message", 21, "i=21"), field("Time", 13, "i=294"), field("ConditionName", 12, "i=12")]


def data(writer_id: int, name: str, kind: str, payload: dict[str, Any] | None, message_id: str) -> dict[str, Any]:
    m: dict[str, Any] = {
        "DataSetWriterId": writer_id,
        "DataSetWriterName": name,
        "SequenceNumber": 1,
        "MetaDataVersion": VERSION,
        "Timestamp": "2026-11-25T18:02:14.512Z",
        "MessageType": kind,
    }
    if payload is not None:
        m["Payload"] = payload
    return {
        "MessageId": message_id,
        "MessageType": "ua-data",
        "PublisherId": P,
        "WriterGroupName": "Cell",
        "Messages": [m],
    }


def key_frame() -> dict[str, Any]:
    return data(
        7,
        "Filler1",
        "ua-keyframe",
        {
            "State": {"Value": {"Text": "Execute"}, "SourceTimestamp": "2026-11-25T18:02:14.471Z"},
            "Speed": {"Value": 42.5, "SourceTimestamp": "2026-11-25T18:02:14.471Z"},
            "Count": {"Value": "12", "SourceTimestamp": "2026-11-25T18:02:14.471Z"},
            "Alarm": {"Value": [{"ID": 1, "Message": "Jam"}]},
            "Any": {"UaType": 6, "Value": 3},
        },
        "d-1",
    )


def event() -> dict[str, Any]:
    payload = {"Message": {"Locale": "en", "Text": "Started"}, "Time": "2026-11-25T18:02:14.5Z", "ConditionName": None}
    return data(8, "Filler1.Events", "ua-event", payload, "e-1")


def status(state: Any = 2) -> dict[str, Any]:
    return {"MessageId": "s-1", "MessageType": "ua-status", "PublisherId": P, "IsCyclic": False, "Status": state}


T = {
    "connection": f"opcua/json/connection/{P}",
    "status": f"opcua/json/status/{P}",
    "meta7": f"opcua/json/metadata/{P}/Cell/Filler1",
    "meta8": f"opcua/json/metadata/{P}/Cell/Filler1.Events",
    "data7": f"opcua/json/data/{P}/Cell/Filler1",
    "data8": f"opcua/json/data/{P}/Cell/Filler1.Events",
}


def good_set() -> list[tuple[str, dict[str, Any]]]:
    return [
        (T["status"], status()),
        (T["connection"], connection()),
        (T["meta7"], metadata(7, "Filler1", copy.deepcopy(VALUE_FIELDS), structures=True)),
        (T["meta8"], metadata(8, "Filler1.Events", copy.deepcopy(EVENT_FIELDS))),
        (T["data7"], key_frame()),
        (T["data8"], event()),
    ]


def run(messages: list[tuple[str, dict[str, Any]]]) -> Validator:
    v = Validator()
    for topic, body in messages:
        v.check(topic, json.dumps(body).encode())
    return v


def test_a_consistent_set_of_messages_passes():
    v = run(good_set())
    assert v.checked == {"ua-status": 1, "ua-connection": 1, "ua-metadata": 2, "ua-data": 2}
    v.check(T["meta7"], b"")  # clearing a retained message
    assert v.cleared == {T["meta7"]}


def at(index: int, change: Callable[[dict[str, Any]], None]) -> Callable[[list[Any]], None]:
    def apply(messages: list[Any]) -> None:
        change(messages[index][1])

    return apply


def payload7(change: Callable[[dict[str, Any]], None]) -> Callable[[list[Any]], None]:
    return at(4, lambda b: change(b["Messages"][0]["Payload"]))


def single(group: dict[str, Any]) -> None:
    """SingleDataSetMessage declared (no header layout), the data still sent as an array."""
    group["MessageSettings"]["NetworkMessageContentMask"] = 79
    group.pop("HeaderLayoutUri")


BAD: dict[str, tuple[Callable[[list[Any]], None], str]] = {
    "StatusCode instead of Status": (
        payload7(lambda p: p["State"].update(Value=None, StatusCode={"Code": 2160001024})),
        "fields the standard does not define",
    ),
    "Good status sent": (payload7(lambda p: p["State"].update(Status={"Code": 0})), "Code 0 (Good)"),
    "empty Locale": (payload7(lambda p: p["State"].update(Value={"Locale": "", "Text": "Idle"})), "empty Locale"),
    "null Value left out": (payload7(lambda p: p["State"].pop("Value")), "null Value"),
    "UaType on a concrete type": (payload7(lambda p: p["Speed"].update(UaType=10)), "collapsed"),
    "no UaType on BaseDataType": (payload7(lambda p: p["Any"].pop("UaType")), "keeps the Variant's UaType"),
    "Int64 as a number": (payload7(lambda p: p["Count"].update(Value=12)), "Int64 as a string"),
    "LocalizedText as a string (non-reversible)": (
        payload7(lambda p: p["State"].update(Value="Execute")),
        "JSON object",
    ),
    "ServerTimestamp not declared": (
        payload7(lambda p: p["Speed"].update(ServerTimestamp="2026-11-25T18:02:14Z")),
        "fields the standard does not define",
    ),
    "structure field missing": (payload7(lambda p: p["Alarm"]["Value"][0].pop("Message")), "structure field"),
    "key frame without a field": (payload7(lambda p: p.pop("Speed")), "missing fields"),
    "event leaves a null field out": (at(5, lambda b: b["Messages"][0]["Payload"].pop("ConditionName")), "missing"),
    "event sends DataValues though declared Variant": (
        at(5, lambda b: b["Messages"][0]["Payload"].update(ConditionName={"Value": None})),
        "JSON string",
    ),
    "header field not declared": (at(4, lambda b: b["Messages"][0].update(PublisherId=P)), "leaves it out"),
    "Status of the DataSetMessage Good": (
        at(4, lambda b: b["Messages"][0].update(Status={"Code": 0, "Symbol": "Good"})),
        "Good",
    ),
    "MetaDataVersion a hash": (
        at(4, lambda b: b["Messages"][0].update(MetaDataVersion={"MajorVersion": 7, "MinorVersion": 7})),
        "VersionTime",
    ),
    "metadata version major later than minor": (
        at(
            2,
            lambda b: b["MetaData"].update(
                ConfigurationVersion={"MajorVersion": 849_000_100, "MinorVersion": 849_000_000}
            ),
        ),
        "never older",
    ),
    "structured field without StructureDataTypes": (
        at(2, lambda b: b["MetaData"].update(StructureDataTypes=[])),
        "neither StructureDataTypes",
    ),
    "structured field without Namespaces": (at(2, lambda b: b["MetaData"].update(Namespaces=[])), "not in Namespaces"),
    "status with a Timestamp though not cyclic": (
        at(0, lambda b: b.update(Timestamp="2026-11-25T18:00:00Z")),
        "left out",
    ),
    "status of an unknown state": (at(0, lambda b: b.update(Status=9)), "PubSubState"),
    "connection with a default value": (at(1, lambda b: b["Connection"].update(ReaderGroups=[])), "default value"),
    "connection without Timestamp": (at(1, lambda b: b.pop("Timestamp")), "Timestamp"),
    "writer not declared": (
        at(1, lambda b: b["Connection"]["WriterGroups"][0]["DataSetWriters"].pop()),
        "not declared",
    ),
    "MessageType disagrees with the topic": (at(0, lambda b: b.update(MessageType="ua-data")), "MessageType"),
    "PublisherId disagrees with the topic": (at(4, lambda b: b.update(PublisherId="other")), "PublisherId"),
    "an array though SingleDataSetMessage is declared": (
        at(1, lambda b: single(b["Connection"]["WriterGroups"][0])),
        "JSON object when SingleDataSetMessage",
    ),
    "a header layout the masks do not follow": (
        at(
            1,
            lambda b: b["Connection"]["WriterGroups"][0].update(
                HeaderLayoutUri="http://opcfoundation.org/UA/PubSub-Layouts/JSON-DataSetMessage"
            ),
        ),
        "JSON-DataSetMessage",
    ),
    "DateTime.MinValue as 1601": (
        at(5, lambda b: b["Messages"][0]["Payload"].update(Time="1601-01-01T00:00:00Z")),
        "MinValue",
    ),
    "metadata without its Timestamp": (at(2, lambda b: b.pop("Timestamp")), "Timestamp is mandatory"),
    "a MessageId used twice": (at(5, lambda b: b.update(MessageId="d-1")), "reused"),
    "NodeId with a namespace index in verbose": (
        at(3, lambda b: b["MetaData"]["Fields"][0].update(DataType="ns=1;i=15")),
        "by URI",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_message_breaking_one_rule_is_refused(case: str):
    change, words = BAD[case]
    messages = good_set()
    change(messages)
    with pytest.raises(Invalid) as e:
        run(messages)
    assert words in str(e.value), str(e.value)


def test_an_empty_data_message_and_a_bad_topic_are_refused():
    v = run(good_set())
    with pytest.raises(Invalid, match="data is not retained"):
        v.check(T["data7"], b"")
    with pytest.raises(Invalid, match="encoding level"):
        v.check(f"opcua/uadp/status/{P}", json.dumps(status()).encode())
    with pytest.raises(Invalid, match="not UTF-8 JSON"):
        v.check(T["status"], b"{nope")
