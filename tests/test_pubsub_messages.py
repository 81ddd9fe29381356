"""The pure half of PubSub: DataSetWriters' key, delta and keep-alive frames and sequence numbers, the
JSON encoding of values, the topic tree, and the [pubsub] checks (docs/pubsub.md)."""

from __future__ import annotations

import os
import uuid
from datetime import UTC, datetime
from pathlib import Path

import pytest
from asyncua import ua

from uacell.core.errors import ConfigError
from uacell.pubsub.config import PubSubConfig, broker_of, check_pubsub, password_of
from uacell.pubsub.encoding import JsonEncoder
from uacell.pubsub.messages import DELTA, KEEPALIVE, KEY, Field, Publisher, Topics, Writer, encode
from uacell.pubsub.mqtt import LinkSettings, MqttLink, Outgoing
from uacell.pubsub.versions import Version, VersionStore, next_version, version_time

T = datetime(2026, 11, 25, 18, 0, 0, 123000, tzinfo=UTC)
FIELDS = (Field("A", 6, "i=6"), Field("B", 12, "i=12"))


def writer(**kw: object) -> Writer:
    w = Writer(writer_id=7, name="Filler1", fields=FIELDS, keyframe_count=3, keep_alive=5.0, **kw)  # type: ignore[arg-type]
    w.update("A", {"Value": 1})
    w.update("B", {"Value": "x"})
    return w


def test_first_message_is_a_key_frame_then_deltas_then_a_key_frame_every_keyframe_count():
    w = writer()
    (m1,) = w.due(0.0, T)
    assert m1["MessageType"] == KEY and m1["Payload"] == {"A": {"Value": 1}, "B": {"Value": "x"}}
    assert m1["SequenceNumber"] == 1 and m1["DataSetWriterId"] == 7 and m1["DataSetWriterName"] == "Filler1"
    assert m1["Timestamp"] == "2026-11-25T18:00:00.123000Z"
    assert list(w.due(0.1, T)) == []  # nothing changed, keep-alive not due
    w.update("A", {"Value": 2})
    (m2,) = w.due(0.2, T)
    assert m2["MessageType"] == DELTA and m2["Payload"] == {"A": {"Value": 2}} and m2["SequenceNumber"] == 2
    w.update("B", {"Value": "y"})
    (m3,) = w.due(0.3, T)
    assert m3["MessageType"] == DELTA and m3["SequenceNumber"] == 3
    w.update("B", {"Value": "z"})
    (m4,) = w.due(0.4, T)  # the third after the key frame: a key frame again, with every field
    assert m4["MessageType"] == KEY and m4["Payload"] == {"A": {"Value": 2}, "B": {"Value": "z"}}


def test_a_silent_writer_sends_keep_alives_with_the_next_sequence_number():
    w = writer()
    list(w.due(0.0, T))
    assert list(w.due(4.9, T)) == []
    (k,) = w.due(5.0, T)
    assert k["MessageType"] == KEEPALIVE and k["SequenceNumber"] == 2 and "Payload" not in k
    w.update("A", {"Value": 3})
    (m,) = w.due(5.1, T)
    assert m["SequenceNumber"] == 2  # the keep-alive announced it; it was not used up


def test_sequence_numbers_wrap_at_uint32():
    w = writer(sequence=2**32 - 1)
    (m,) = w.due(0.0, T)
    assert m["SequenceNumber"] == 0


def test_an_event_writer_sends_one_event_message_per_event_in_order():
    w = Writer(writer_id=2, name="Filler1.Events", fields=(Field("Message", 21, "i=21"),), events=True)
    w.event({"Message": {"Text": "one"}})
    w.event({"Message": {"Text": "two"}})
    got = list(w.due(0.0, T))
    assert [m["MessageType"] for m in got] == ["ua-event", "ua-event"]
    assert [m["SequenceNumber"] for m in got] == [1, 2]
    assert [m["Payload"]["Message"]["Text"] for m in got] == ["one", "two"]
    assert list(w.due(0.1, T)) == []


def test_metadata_describes_the_fields_and_carries_the_writers_version():
    w = writer(version=Version(850_000_000, 850_000_100))
    meta = w.metadata()
    assert [f["Name"] for f in meta["Fields"]] == ["A", "B"]
    assert [f["BuiltInType"] for f in meta["Fields"]] == [6, 12]
    uuid.UUID(meta["Fields"][0]["DataSetFieldId"])
    assert meta["ConfigurationVersion"] == {"MajorVersion": 850_000_000, "MinorVersion": 850_000_100}
    (m,) = w.due(0.0, T)
    assert m["MetaDataVersion"] == {"MajorVersion": 850_000_000, "MinorVersion": 850_000_100}
    assert "Status" not in m  # Good is left out (OPC 10000-6 §5.4.2.12)


def test_configuration_version_is_version_time_with_the_major_and_minor_rules_of_part14():
    """OPC 10000-14 §6.2.3.2.6: seconds since 2000; fields added at the end change only MinorVersion;
    removed, reordered or retyped fields change both; unchanged fields keep both."""
    t0 = datetime(2026, 11, 25, tzinfo=UTC)
    assert version_time(t0) == 9825 * 86400  # 26 years with 7 leap days, and 328 days of 2026
    a, b, c = ["A", 6, "i=6", -1], ["B", 12, "i=12", -1], ["C", 1, "i=1", -1]
    first = next_version(None, [a, b], 1000)
    assert first == Version(1000, 1000)
    record = {"shape": [a, b], "major": 1000, "minor": 1000}
    assert next_version(record, [a, b], 5000) == Version(1000, 1000)  # a restart, same fields
    assert next_version(record, [a, b, c], 5000) == Version(1000, 5000)  # added at the end: minor
    assert next_version(record, [b, a], 5000) == Version(5000, 5000)  # reordered: major
    assert next_version(record, [a], 5000) == Version(5000, 5000)  # removed: major
    assert next_version(record, [a, [*b[:1], 11, "i=11", -1]], 5000) == Version(5000, 5000)  # retyped
    assert next_version(record, [a, b, c], 900) == Version(1000, 1001)  # never older than the last


def test_versions_are_kept_across_restarts(tmp_path: Path):
    store = VersionStore(tmp_path)
    v1 = store.version("Filler1", [["A", 6, "i=6", -1]], T)
    store.save()
    later = datetime(2027, 1, 1, tzinfo=UTC)
    again = VersionStore(tmp_path).version("Filler1", [["A", 6, "i=6", -1]], later)
    assert again == v1 == Version(version_time(T), version_time(T))
    grown = VersionStore(tmp_path).version("Filler1", [["A", 6, "i=6", -1], ["B", 1, "i=1", -1]], later)
    assert grown == Version(v1.major, version_time(later))


def test_an_event_carries_every_field_null_where_the_event_has_none():
    fields = (Field("Message", 21, "i=21"), Field("ConditionName", 12, "i=12"), Field("Retain", 1, "i=1"))
    w = Writer(writer_id=2, name="Robot1.Events", fields=fields, events=True)
    w.event({"Message": {"Text": "moved"}})
    (m,) = w.due(0.0, T)
    assert m["Payload"] == {"Message": {"Text": "moved"}, "ConditionName": None, "Retain": None}
    assert list(m["Payload"]) == ["Message", "ConditionName", "Retain"]


def test_network_metadata_and_status_messages_and_topics():
    p = Publisher("cell-7", "Cell")
    w = writer()
    (dsm,) = w.due(0.0, T)
    nm = p.network_message(dsm)
    assert nm["MessageType"] == "ua-data" and nm["PublisherId"] == "cell-7" and nm["Messages"] == [dsm]
    uuid.UUID(nm["MessageId"])
    md = p.metadata_message(w, T)
    assert md["MessageType"] == "ua-metadata" and md["DataSetWriterId"] == 7 and md["MetaData"]["Name"] == "Filler1"
    st = p.status_message(2)
    assert st == {
        "MessageId": st["MessageId"],
        "MessageType": "ua-status",
        "PublisherId": "cell-7",
        "IsCyclic": False,
        "Status": 2,
    }
    conn = p.connection_message({"Name": "MQTT"}, T)
    assert conn["MessageType"] == "ua-connection" and conn["Timestamp"] == "2026-11-25T18:00:00.123000Z"
    assert p.status_message(2)["MessageId"] != st["MessageId"]  # every message its own MessageId
    t = Topics("umati/v3", "cell-7", "Cell")
    assert t.connection() == "umati/v3/json/connection/cell-7"
    assert t.data("Filler1") == "umati/v3/json/data/cell-7/Cell/Filler1"
    assert t.metadata("Filler1") == "umati/v3/json/metadata/cell-7/Cell/Filler1"
    assert t.status() == "umati/v3/json/status/cell-7"


def test_values_encode_as_part6_json():
    e = JsonEncoder(["http://opcfoundation.org/UA/", "urn:uacell:cell"])
    assert e.variant(ua.Variant(ua.LocalizedText("Idle", "en"), ua.VariantType.LocalizedText)) == {
        "Locale": "en",
        "Text": "Idle",
    }
    # empty parts are left out (§5.4.2.15)
    assert e.variant(ua.Variant(ua.LocalizedText("Idle", ""), ua.VariantType.LocalizedText)) == {"Text": "Idle"}
    assert e.value(ua.LocalizedText("", "")) == {}
    assert e.value(ua.PubSubState.Operational) == "Operational_2"  # verbose Enumeration (§5.4.4.2)
    assert e.value(ua.QualifiedName("Robot", 1)) == "nsu=urn:uacell:cell;Robot"
    assert e.typed(ua.Variant(3, ua.VariantType.Int32)) == {"UaType": 6, "Value": 3}
    assert e.status(0) == {}
    # an Enumeration held as its number, with its names from the DataType's EnumDefinition
    mode = ua.DataValue(ua.Variant(1, ua.VariantType.Int32), SourceTimestamp=T)
    assert e.data_value(mode, names={0: "CYCLE", 1: "CONTINUOUS"})["Value"] == "CONTINUOUS_1"
    assert e.enumeration(7, {0: "CYCLE"}) == "7"  # not named: the number as a string (§5.4.4.2)
    assert e.variant(ua.Variant(2**40, ua.VariantType.Int64)) == str(2**40)
    assert e.variant(ua.Variant(float("nan"), ua.VariantType.Double)) == "NaN"
    assert e.variant(ua.Variant(b"\x01\x02", ua.VariantType.ByteString)) == "AQI="
    assert e.node_id(ua.NodeId("Filler1", 1)) == "nsu=urn:uacell:cell;s=Filler1"
    assert e.node_id(ua.NodeId(2253, 0)) == "i=2253"
    assert e.value(T) == "2026-11-25T18:00:00.123000Z"
    assert e.value(datetime(1601, 1, 1, tzinfo=UTC)) == "0001-01-01T00:00:00Z"  # MinValue (§5.4.2.6)
    dv = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadStateNotActive), SourceTimestamp=T)
    assert e.data_value(dv) == {
        "Value": None,  # the VerboseEncoding writes null, not leaves it out (§5.4.2.1)
        "Status": {"Code": ua.StatusCodes.BadStateNotActive, "Symbol": "BadStateNotActive"},
        "SourceTimestamp": "2026-11-25T18:00:00.123000Z",
    }
    good = ua.DataValue(ua.Variant(2.5, ua.VariantType.Double), SourceTimestamp=T)
    assert e.data_value(good) == {"Value": 2.5, "SourceTimestamp": "2026-11-25T18:00:00.123000Z"}
    assert e.data_value(good, typed=True) == {
        "UaType": 11,
        "Value": 2.5,
        "SourceTimestamp": "2026-11-25T18:00:00.123000Z",
    }
    # structures are encoded field by field
    assert e.value(ua.Argument(Name="Speed", DataType=ua.NodeId(10), ValueRank=-1))["Name"] == "Speed"


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [
        ("broker", "http://x", "mqtt://host"),
        ("broker", "mqtt://u:p@host", "no user or password"),
        ("publisher_id", "a/b", "one MQTT topic level"),
        ("topic_prefix", "a/#", "topic levels"),
        ("qos", 3, "0, 1 or 2"),
        ("publishing_interval", 0.001, "0.01..3600"),
        ("keep_alive", 1, "5..3600"),
        ("extra_values", ["Status/X"], "role:Browse/Path"),
    ],
)
def test_bad_pubsub_settings_are_refused_naming_the_key(key: str, value: object, words: str):
    cfg = PubSubConfig()
    setattr(cfg, key, value)
    with pytest.raises(ConfigError) as e:
        check_pubsub(cfg)
    assert f"[pubsub] {key}" in str(e.value) and words in str(e.value)


def test_broker_urls_and_the_password_sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    assert broker_of(PubSubConfig(broker="mqtts://plant-broker")).port == 8883
    assert broker_of(PubSubConfig(broker="mqtt://10.0.0.9")).port == 1883
    monkeypatch.setenv("UACELL_MQTT_PASSWORD", "from-env")
    assert password_of(PubSubConfig()) == "from-env"
    secret = tmp_path / "mqtt-password"
    secret.write_text("from-file\n")
    os.chmod(secret, 0o644)
    with pytest.raises(ConfigError, match="may be read by others"):
        password_of(PubSubConfig(password_file=secret))
    os.chmod(secret, 0o600)
    assert password_of(PubSubConfig(password_file=secret)) == "from-file"
    with pytest.raises(ConfigError, match="cannot read"):
        password_of(PubSubConfig(password_file=tmp_path / "missing"))


def test_keep_alives_do_not_count_in_keyframe_count():
    w = writer()  # keyframe_count 3
    assert [m["MessageType"] for m in w.due(0.0, T)] == [KEY]
    assert [m["MessageType"] for m in w.due(5.0, T)] == [KEEPALIVE]
    assert [m["MessageType"] for m in w.due(10.0, T)] == [KEEPALIVE]
    w.update("A", {"Value": 5})
    assert [m["MessageType"] for m in w.due(10.1, T)] == [DELTA]
    w.update("A", {"Value": 6})
    assert [m["MessageType"] for m in w.due(10.2, T)] == [DELTA]
    w.update("A", {"Value": 7})
    assert [m["MessageType"] for m in w.due(10.3, T)] == [KEY]  # the third data message after the key frame


async def test_the_link_registers_a_new_will_on_every_connect():
    made: list[str] = []

    def will() -> Outgoing:
        message = Publisher("cell-7", "Cell").status_message(3)
        made.append(message["MessageId"])
        return Outgoing("opcua/json/status/cell-7", encode(message), retain=True)

    link = MqttLink(LinkSettings(broker_of(PubSubConfig()), "cell-7", 1, 10, 100), will, list)
    link._client()  # what each connect does
    link._client()
    assert len(made) == 2 and made[0] != made[1]
    fixed = Outgoing("t", b"x", retain=True)
    link.will = fixed  # still assignable, as before
    assert link.will is fixed
