"""OPC UA PubSub JSON messages (OPC 10000-14 v1.05, 7.2.5) and their MQTT topics (7.3.4.7). Pure.

A ``Writer`` is one DataSetWriter: its DataSet's fields, its sequence numbers and what changed since
its last message. Every publishing interval it yields at most one DataSetMessage: a key frame (every
field) on its first message and every ``keyframe_count``-th after, else a delta frame (the fields that
changed), else, after ``keep_alive`` seconds of silence, a keep-alive carrying the next sequence
number. An event writer yields one ``ua-event`` message per event instead, with every field of its
DataSet (JSON null where the event has none, §7.2.5.4). Each message travels in a NetworkMessage of its
own on the writer's topic, so a subscriber picks writers by topic filter.

The header fields sent are the ones the content masks below declare (and the address space shows).
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from uacell.pubsub.encoding import iso
from uacell.pubsub.versions import Version

# PubSubState (OPC 10000-14 6.2.1): the Status message's value.
DISABLED, PAUSED, OPERATIONAL, ERROR = 0, 1, 2, 3
KEY, DELTA, EVENT, KEEPALIVE = "ua-keyframe", "ua-deltaframe", "ua-event", "ua-keepalive"
_UINT32 = 1 << 32
_FIELD_IDS = uuid.UUID("5b1a3f0e-7c1d-4c55-9a3e-0d3c7e6b9f21")  # namespace for DataSetFieldIds

UNSET = Version(0, 0)

# JsonNetworkMessageContentMask (§6.3.2.1.1): NetworkMessageHeader | DataSetMessageHeader | PublisherId |
# WriterGroupName. Not SingleDataSetMessage: ``Messages`` is an array (§7.2.5.3), of one DataSetMessage.
NETWORK_MESSAGE_CONTENT_MASK = 0x01 | 0x02 | 0x08 | 0x40
# JsonDataSetMessageContentMask (§6.3.2.3.1): DataSetWriterId | MetaDataVersion | SequenceNumber |
# Timestamp | Status | MessageType | DataSetWriterName | FieldEncoding2 (FieldEncoding1 clear: the
# VerboseEncoding, Table 112). Status is left out while Good (OPC 10000-6 §5.4.2.12); MetaDataVersion
# carries both MajorVersion and MinorVersion.
DATASET_MESSAGE_CONTENT_MASK = 0x01 | 0x02 | 0x04 | 0x08 | 0x10 | 0x20 | 0x40 | 0x800
# DataSetFieldContentMask (§6.2.4.2): value writers send DataValues with StatusCode and SourceTimestamp;
# event writers send Variants (no bit), collapsed to their value by the VerboseEncoding (§7.2.5.4.2).
VALUE_FIELD_CONTENT_MASK = 0x1 | 0x2
EVENT_FIELD_CONTENT_MASK = 0


@dataclass(frozen=True)
class Field:
    """A DataSet field as its metadata describes it (FieldMetaData, OPC 10000-14 6.2.3.2.3)."""

    name: str
    builtin: int  # BuiltInType (OPC 10000-6 5.1.2); 0: any (Variant)
    data_type: str  # the DataType's NodeId, e.g. "i=21"
    value_rank: int = -1
    abstract: bool = False  # an abstract DataType (BaseDataType, Number...): the value keeps its UaType
    names: tuple[tuple[int, str], ...] = ()  # an Enumeration DataType's (value, name) pairs

    def shape(self) -> list[Any]:
        return [self.name, self.builtin, self.data_type, self.value_rank]


@dataclass(frozen=True)
class Topics:
    """The MQTT topic tree of OPC 10000-14 7.3.4.7 for one Publisher and WriterGroup."""

    prefix: str
    publisher_id: str
    writer_group: str

    def data(self, writer: str) -> str:
        return f"{self.prefix}/json/data/{self.publisher_id}/{self.writer_group}/{writer}"

    def metadata(self, writer: str) -> str:
        return f"{self.prefix}/json/metadata/{self.publisher_id}/{self.writer_group}/{writer}"

    def status(self) -> str:
        return f"{self.prefix}/json/status/{self.publisher_id}"

    def connection(self) -> str:
        return f"{self.prefix}/json/connection/{self.publisher_id}"


@dataclass
class Writer:
    """One DataSetWriter (see the module's doc)."""

    writer_id: int  # DataSetWriterId, 1..65535
    name: str  # DataSetWriterName: one topic level
    fields: tuple[Field, ...]
    events: bool = False
    interval_ticks: int = 1  # publishes every n-th publishing interval
    keyframe_count: int = 10
    keep_alive: float = 10.0
    version: Version = UNSET  # ConfigurationVersion: versions.py gives it
    schema: dict[str, Any] = field(default_factory=dict)  # Namespaces, StructureDataTypes... (DataTypeSchemaHeader)
    sequence: int = 0  # the last sequence number sent
    latest: dict[str, Any] = field(default_factory=dict)  # field name -> its JSON value, for key frames
    changed: dict[str, Any] = field(default_factory=dict)  # since the last message
    queued_events: list[dict[str, Any]] = field(default_factory=list)
    _since_key: int = -1  # messages since the last key frame; -1: none sent yet
    _last_sent: float | None = None

    @property
    def field_content_mask(self) -> int:
        return EVENT_FIELD_CONTENT_MASK if self.events else VALUE_FIELD_CONTENT_MASK

    def shape(self) -> list[Any]:
        return [f.shape() for f in self.fields]

    def update(self, name: str, value: Any) -> None:
        self.latest[name] = value
        self.changed[name] = value

    def event(self, payload: dict[str, Any]) -> None:
        """Queues one event: every field of the DataSet, in order, null where ``payload`` has none."""
        self.queued_events.append({f.name: payload.get(f.name) for f in self.fields})

    def _next(self) -> int:
        self.sequence = (self.sequence + 1) % _UINT32
        return self.sequence

    def due(self, now: float, timestamp: datetime) -> Iterator[dict[str, Any]]:
        """The DataSetMessages to send now (``now`` a monotonic clock in seconds)."""
        if self.events:
            for payload in self.queued_events:
                self._last_sent = now
                yield self._message(EVENT, self._next(), timestamp, payload)
            self.queued_events.clear()
        elif self.changed or (self._since_key < 0 and self.latest):
            key = self._since_key < 0 or self._since_key + 1 >= self.keyframe_count
            payload = dict(self.latest) if key else dict(self.changed)
            self._since_key = 0 if key else self._since_key + 1
            self.changed.clear()
            self._last_sent = now
            yield self._message(KEY if key else DELTA, self._next(), timestamp, payload)
            return
        if self._last_sent is None:
            self._last_sent = now
        elif now - self._last_sent >= self.keep_alive:
            self._last_sent = now
            next_number = (self.sequence + 1) % _UINT32
            yield self._message(KEEPALIVE, next_number, timestamp, None)

    def _message(self, kind: str, sequence: int, timestamp: datetime, payload: dict[str, Any] | None) -> dict[str, Any]:
        message: dict[str, Any] = {
            "DataSetWriterId": self.writer_id,
            "DataSetWriterName": self.name,
            "SequenceNumber": sequence,
            "MetaDataVersion": self.version.json(),
            "Timestamp": iso(timestamp),
            "MessageType": kind,
        }
        if payload is not None:
            message["Payload"] = payload
        return message

    def metadata(self) -> dict[str, Any]:
        """DataSetMetaDataType (OPC 10000-14 6.2.3.2) of this writer's DataSet."""
        return {
            "Namespaces": list(self.schema.get("Namespaces", [])),
            "StructureDataTypes": list(self.schema.get("StructureDataTypes", [])),
            "EnumDataTypes": list(self.schema.get("EnumDataTypes", [])),
            "SimpleDataTypes": [],
            "Name": self.name,
            "Description": {},
            "Fields": [
                {
                    "Name": f.name,
                    "Description": {},
                    "FieldFlags": 0,
                    "BuiltInType": f.builtin,
                    "DataType": f.data_type,
                    "ValueRank": f.value_rank,
                    "ArrayDimensions": [],
                    "MaxStringLength": 0,
                    "DataSetFieldId": self.field_id(f),
                    "Properties": [],
                }
                for f in self.fields
            ],
            "DataSetClassId": "00000000-0000-0000-0000-000000000000",
            "ConfigurationVersion": self.version.json(),
        }

    def field_id(self, f: Field) -> str:
        return str(uuid.uuid5(_FIELD_IDS, f"{self.name}/{f.name}"))


@dataclass(frozen=True)
class Publisher:
    """Builds the NetworkMessages of one PublisherId and WriterGroup."""

    publisher_id: str
    writer_group: str

    def network_message(self, dataset_message: dict[str, Any]) -> dict[str, Any]:
        return {
            "MessageId": str(uuid.uuid4()),
            "MessageType": "ua-data",
            "PublisherId": self.publisher_id,
            "WriterGroupName": self.writer_group,
            "Messages": [dataset_message],
        }

    def metadata_message(self, writer: Writer, timestamp: datetime) -> dict[str, Any]:
        return {
            "MessageId": str(uuid.uuid4()),
            "MessageType": "ua-metadata",
            "PublisherId": self.publisher_id,
            "DataSetWriterId": writer.writer_id,
            "WriterGroupName": self.writer_group,
            "DataSetWriterName": writer.name,
            "Timestamp": iso(timestamp),
            "MetaData": writer.metadata(),
        }

    def connection_message(self, connection: dict[str, Any], timestamp: datetime) -> dict[str, Any]:
        """``ua-connection`` (§7.2.5.5.6): the PubSubConnectionDataType, in the CompactEncoding."""
        return {
            "MessageId": str(uuid.uuid4()),
            "MessageType": "ua-connection",
            "PublisherId": self.publisher_id,
            "Timestamp": iso(timestamp),
            "Connection": connection,
        }

    def status_message(self, state: int) -> dict[str, Any]:
        """Not cyclic (OPC 10000-14 7.2.5.5.5, Table 191): sent when the state changes, no Timestamp; the
        broker sends the Will. Every call has a new MessageId."""
        return {
            "MessageId": str(uuid.uuid4()),
            "MessageType": "ua-status",
            "PublisherId": self.publisher_id,
            "IsCyclic": False,
            "Status": state,
        }


def encode(message: dict[str, Any]) -> bytes:
    return json.dumps(message, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
