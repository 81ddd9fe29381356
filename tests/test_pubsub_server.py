"""PubSub JSON over MQTT from a served cell to Debian's mosquitto, started on a free port: the Part 14
messages and topics, a PackML cycle and a robot program in order, retained metadata for a late
subscriber, the Will after kill -9, the broker killed and back, TLS and passwords (docs/pubsub.md)."""

from __future__ import annotations

import asyncio
import json
import os
import ssl
import subprocess
import sys
import time
import uuid
from collections import defaultdict
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving, start_app
from helpers import call_path, free_port, wait_until
from mqtt_broker import Broker, Received, Subscriber, make_tls, needs_mosquitto, subscribed
from test_operations import sample, scrape

from uacell.config import Config
from uacell.pubsub.messages import DISABLED, ERROR, OPERATIONAL
from uacell.server import UacellServer

pytestmark = needs_mosquitto

F = "Filler1"
BASE = f"{F}.BaseStateMachine"
MACH = f"{BASE}.MachineState"
EXEC = f"{MACH}.ExecuteState"
CTRL = "Robot1.Controllers.Controller1"
TASK = f"{CTRL}.TaskControls.TaskControl1"
TC = f"{TASK}.TaskControlOperation.TaskControlStateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
PUBLISHER = "cell-under-test"
PREFIX = f"opcua/json/data/{PUBLISHER}/Cell"
SRC = Path(__file__).resolve().parents[1] / "src"


def pubsub_config(data: Path, broker: Broker, **keys: Any) -> Config:
    config = fast_config(data)
    p = config.pubsub
    p.enabled = True
    p.broker = broker.url
    p.publisher_id = PUBLISHER
    p.publishing_interval = 0.05
    p.positions_interval = 0.2
    for key, value in keys.items():
        setattr(p, key, value)
    return config


@pytest.fixture
async def served(tmp_path: Path, broker: Broker) -> AsyncIterator[tuple[UacellServer, Client]]:
    async with serving(pubsub_config(tmp_path / "data", broker)) as served:
        yield served


@pytest.fixture
async def watched(tmp_path: Path, broker: Broker) -> AsyncIterator[tuple[Subscriber, Client]]:
    """A subscriber on every topic, subscribed before the cell starts, so it sees each writer's first
    message (sequence number 1), and a client of the served cell."""
    async with subscribed(broker, "opcua/#") as sub:
        async with serving(pubsub_config(tmp_path / "data", broker)) as (_app, client):
            yield sub, client


call = call_path


def states(sub: Subscriber, writer: str, field: str) -> list[str]:
    """The successive texts of a state field as the writer's messages carried them (repeats dropped)."""
    seen: list[str] = []
    for m in sub.data(f"/{writer}"):
        value = m.get("Payload", {}).get(field)
        if value is None:
            continue
        if value["Value"] is None:  # a sub-state machine not active: Bad_StateNotActive, no value
            assert value["Status"]["Symbol"] == "BadStateNotActive"
            text = "(not active)"
        else:
            text = value["Value"]["Text"]
        if not seen or seen[-1] != text:
            seen.append(text)
    return seen


def transitions_of(sub: Subscriber, writer: str) -> list[str]:
    return [
        m["Payload"]["Transition"]["Text"]
        for m in sub.data(f"/{writer}")
        if m["MessageType"] == "ua-event" and m["Payload"]["Transition"] is not None
    ]


def check_network_message(r: Received) -> None:
    """The fields OPC 10000-14 v1.05 7.2.5.3 / 7.2.5.4 give a JSON NetworkMessage and its DataSetMessages."""
    body = r.body
    assert body["MessageType"] == "ua-data"
    assert body["PublisherId"] == PUBLISHER
    assert body["WriterGroupName"] == "Cell"
    uuid.UUID(body["MessageId"])
    (m,) = body["Messages"]
    assert isinstance(m["DataSetWriterId"], int) and 1 <= m["DataSetWriterId"] <= 65535
    assert r.topic == f"{PREFIX}/{m['DataSetWriterName']}"
    assert isinstance(m["SequenceNumber"], int)
    assert set(m["MetaDataVersion"]) == {"MajorVersion", "MinorVersion"}
    assert m["Timestamp"].endswith("Z")
    assert "Status" not in m  # Good: left out (OPC 10000-6 §5.4.2.12)
    assert m["MessageType"] in ("ua-keyframe", "ua-deltaframe", "ua-event", "ua-keepalive")
    assert ("Payload" in m) == (m["MessageType"] != "ua-keepalive")


def check_sequences(sub: Subscriber) -> None:
    """SequenceNumbers strictly increase per writer (keep-alives announce the next one)."""
    by_writer: dict[int, list[int]] = defaultdict(list)
    for m in sub.data():
        if m["MessageType"] != "ua-keepalive":
            by_writer[m["DataSetWriterId"]].append(m["SequenceNumber"])
    assert by_writer
    for writer, numbers in by_writer.items():
        assert numbers == sorted(set(numbers)), (writer, numbers)
        assert numbers[0] == 1, (writer, numbers[:3])


@needs_mosquitto
async def test_a_packml_cycle_arrives_in_order_as_part14_json(watched) -> None:
    sub, client = watched
    status = await sub.wait_for(lambda r: r.topic == f"opcua/json/status/{PUBLISHER}")
    assert status.body["MessageType"] == "ua-status"
    assert status.body["Status"] == OPERATIONAL and status.body["IsCyclic"] is False
    meta = await sub.wait_for(lambda r: r.topic == f"opcua/json/metadata/{PUBLISHER}/Cell/{F}")
    assert meta.body["MessageType"] == "ua-metadata"
    fields = {f["Name"]: f for f in meta.body["MetaData"]["Fields"]}
    assert fields["BaseStateMachine/MachineState/ExecuteState/CurrentState"]["BuiltInType"] == 21
    assert fields["Status/MachSpeed"]["BuiltInType"] == 10  # Float
    assert "Admin/ProdProcessedCount" in fields and "Status/UnitModeCurrent" in fields

    assert (await call(client, MACH, "Reset")).StatusCode.is_good()
    await wait_until(lambda: "Idle" in states(sub, F, "BaseStateMachine/MachineState/ExecuteState/CurrentState"))
    speed = ua.Variant(42.5, ua.VariantType.Float)
    assert (await call(client, F, "SetMachSpeed", speed)).StatusCode.is_good()
    start = await call(client, EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject))
    assert start.StatusCode.is_good(), start.StatusCode
    await wait_until(lambda: "Execute" in states(sub, F, "BaseStateMachine/MachineState/ExecuteState/CurrentState"))
    assert (await call(client, MACH, "Stop")).StatusCode.is_good()
    await wait_until(lambda: states(sub, F, "BaseStateMachine/MachineState/CurrentState")[-1:] == ["Stopped"])

    walk = states(sub, F, "BaseStateMachine/MachineState/ExecuteState/CurrentState")
    assert walk[walk.index("Resetting") :][:4] == ["Resetting", "Idle", "Starting", "Execute"]
    speeds = [
        m["Payload"]["Status/MachSpeed"]["Value"]
        for m in sub.data(f"/{F}")
        if "Status/MachSpeed" in m.get("Payload", {})
    ]
    assert speeds[-1] == 42.5
    # the TransitionEvents, as event DataSetMessages of the unit's events writer
    await wait_until(lambda: "RunningToStopping" in transitions_of(sub, f"{F}.Events"))
    events = [m for m in sub.data(f"/{F}.Events") if m["MessageType"] != "ua-keepalive"]
    assert all(m["MessageType"] == "ua-event" for m in events)
    transitions = [m["Payload"]["Transition"]["Text"] for m in events if m["Payload"]["Transition"] is not None]
    assert (
        transitions.index("IdleToStarting")
        < transitions.index("StartingToExecute")
        < transitions.index("RunningToStopping")
    )
    for r in sub.on(lambda r: "/json/data/" in r.topic):
        check_network_message(r)
    check_sequences(sub)


def s(text: str) -> ua.Variant:
    return ua.Variant(text, ua.VariantType.String)


async def robot_status(client: Client, obj: str, method: str, *args: ua.Variant) -> int:
    res = await call(client, obj, method, *args)
    assert res.StatusCode.is_good(), (method, res.StatusCode)
    value: int = res.OutputArguments[0].Value
    return value


async def test_a_robot_program_run_arrives_with_its_program_line_and_axis_positions(watched) -> None:
    sub, client = watched
    assert await robot_status(client, SO, "GetReady") == 0
    so_field = "SystemOperation/SystemOperationStateMachine/CurrentState"
    await wait_until(lambda: states(sub, CTRL, so_field)[-1:] == ["Ready"])
    assert await robot_status(client, TC, "LoadByName", s("gripper")) == 0
    assert await robot_status(client, TC, "LoadByName", s("pick_and_place")) == 0
    assert await robot_status(client, TC, "Start") == 0
    await wait_until(lambda: "ExecutingToReady" in transitions_of(sub, f"{TASK}.Events"))
    task_field = "TaskControlOperation/TaskControlStateMachine/CurrentState"
    await wait_until(lambda: states(sub, TASK, task_field)[-1:] == ["Ready"])
    # values are sampled each publishing interval (a short run may start and end within one);
    # every transition arrives as an event, in order
    names = [
        m["Payload"]["ParameterSet/TaskProgramName"]["Value"]
        for m in sub.data(f"/{TASK}")
        if "ParameterSet/TaskProgramName" in m["Payload"]
    ]
    assert names[-1] == "PickAndPlace"
    pointers = [
        m["Payload"]["ParameterSet/ProgramPointer"]
        for m in sub.data(f"/{TASK}")
        if "ParameterSet/ProgramPointer" in m.get("Payload", {})
    ]
    assert len(pointers) >= 2  # the pointer moved while the program ran
    lines = [
        m["Payload"]["ParameterSet/CurrentLine"]["Value"]
        for m in sub.data(f"/{TASK}")
        if "ParameterSet/CurrentLine" in m.get("Payload", {})
    ]
    assert any(line > 0 for line in lines)  # the source line the robot was at
    so = states(sub, CTRL, so_field)
    assert "Executing" in so
    assert transitions_of(sub, f"{TASK}.Events")[-2:] == ["ReadyToExecuting", "ExecutingToReady"]
    # the axis positions, on their own writer and at their own (lower) rate
    axes = [m for m in sub.data("/Robot1.MotionDevices.Arm1.Axes") if m["MessageType"] != "ua-keepalive"]
    assert axes, "no axis positions arrived"
    assert any(k.endswith("/ParameterSet/ActualPosition") for m in axes for k in m["Payload"])
    check_sequences(sub)


async def test_a_late_subscriber_learns_every_writer_from_the_retained_metadata(served, broker: Broker) -> None:
    app, _client = served
    assert app.pubsub is not None
    await wait_until(lambda: app.pubsub is not None and app.pubsub.link.connected.is_set())
    writers = {w.name: w for w in app.pubsub.writers}
    async with subscribed(broker, f"opcua/json/+/{PUBLISHER}/#") as sub:
        await wait_until(lambda: len(sub.on(lambda r: "/metadata/" in r.topic)) == len(writers))
        for r in sub.on(lambda r: "/metadata/" in r.topic):
            assert r.retain
            body = r.body
            assert body["MessageType"] == "ua-metadata" and body["PublisherId"] == PUBLISHER
            writer = writers[body["DataSetWriterName"]]
            assert body["DataSetWriterId"] == writer.writer_id
            assert [f["Name"] for f in body["MetaData"]["Fields"]] == [f.name for f in writer.fields]
            version = body["MetaData"]["ConfigurationVersion"]
            assert version == {"MajorVersion": writer.version.major, "MinorVersion": writer.version.minor}
    async with subscribed(broker, f"opcua/json/status/{PUBLISHER}") as sub:
        status = await sub.wait_for(lambda r: True)
        assert status.retain and status.body["Status"] == OPERATIONAL
    # the same with Debian's own client, the worked example of docs/pubsub.md
    out = subprocess.run(
        [
            "mosquitto_sub",
            "-h",
            "127.0.0.1",
            "-p",
            str(broker.port),
            "-t",
            f"opcua/json/metadata/{PUBLISHER}/Cell/{F}",
            "-C",
            "1",
            "-W",
            "10",
        ],
        capture_output=True,
        timeout=20,
        check=True,
    )
    assert json.loads(out.stdout)["MetaData"]["Name"] == F


async def test_a_clean_stop_leaves_status_disabled(tmp_path: Path, broker: Broker) -> None:
    app = await start_app(pubsub_config(tmp_path / "data", broker))
    try:
        assert app.pubsub is not None
        await wait_until(lambda: app.pubsub is not None and app.pubsub.link.connected.is_set())
    finally:
        await app.stop()
    async with subscribed(broker, f"opcua/json/status/{PUBLISHER}") as sub:
        status = await sub.wait_for(lambda r: True)
        assert status.retain and status.body["Status"] == DISABLED


async def test_kill_9_the_broker_sends_the_will(tmp_path: Path, broker: Broker) -> None:
    """uacell run as `uacell serve`, killed with -9: the broker publishes its Will (status Error, a
    MessageId of its own). MQTT gives the broker 1.5 keep-alives; mosquitto 2.0 takes 7 to 13 s for
    keep_alive 5 (docs/pubsub.md), so the bound is the broker's, not uacell's."""
    port = free_port()
    config = tmp_path / "uacell.toml"
    config.write_text(
        f"""
[server]
port = {port}
data_dir = "{tmp_path / "data"}"

[web]
enabled = false

[pubsub]
enabled = true
broker = "{broker.url}"
publisher_id = "{PUBLISHER}"
keep_alive = 5
"""
    )
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "uacell", "serve", "--config", str(config)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        async with subscribed(broker, f"opcua/json/status/{PUBLISHER}") as sub:
            await sub.wait_for(lambda r: r.body is not None and r.body["Status"] == OPERATIONAL, timeout=60)
            proc.kill()
            proc.wait(10)
            killed = time.monotonic()
            will = await sub.wait_for(lambda r: r.body is not None and r.body["Status"] == ERROR, timeout=30)
            assert time.monotonic() - killed <= 3 * 5 + 2.0  # mosquitto: 7-13 s; generous for a loaded machine
            assert will.body["MessageType"] == "ua-status" and will.body["IsCyclic"] is False
            operational = next(r for r in sub.messages if r.body is not None and r.body["Status"] == OPERATIONAL)
            assert will.body["MessageId"] != operational.body["MessageId"]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


async def test_the_broker_killed_and_back_uacell_serves_on_reconnects_and_counts_the_gap(
    tmp_path: Path, broker: Broker
) -> None:
    config = pubsub_config(tmp_path / "data", broker, buffer=5)
    config.metrics.enabled = True
    config.metrics.port = free_port()
    app = await start_app(config)
    try:
        assert app.pubsub is not None
        link = app.pubsub.link
        filler = next(w for w in app.pubsub.writers if w.name == F)
        await wait_until(link.connected.is_set)
        async with Client(app.endpoint, timeout=30) as client:
            broker.kill()
            await wait_until(lambda: not link.connected.is_set(), timeout=30)
            # the server answers while the broker is away; the changes overflow the 5-message buffer
            for i in range(20):
                speed = ua.Variant(float(i + 1), ua.VariantType.Float)
                assert (await call(client, F, "SetMachSpeed", speed)).StatusCode.is_good()
                await wait_until(lambda: not filler.changed)
            assert link.dropped > 0
            _, body = await scrape(app)  # counted in /metrics too
            assert sample(body, "uacell_pubsub_messages_dropped_total") == link.dropped
            assert sample(body, "uacell_pubsub_connected") == 0
            broker.start()  # the same port
            async with subscribed(broker, f"{PREFIX}/{F}") as sub:
                await wait_until(lambda: link.connects >= 2, timeout=30)
                assert (
                    await call(client, F, "SetMachSpeed", ua.Variant(99.0, ua.VariantType.Float))
                ).StatusCode.is_good()
                got = await sub.wait_for(
                    lambda r: r.body["Messages"][0].get("Payload", {}).get("Status/MachSpeed", {}).get("Value") == 99.0
                )
                numbers = [m["SequenceNumber"] for m in sub.data(f"/{F}")]
                assert numbers == sorted(numbers)
                # the subscriber sees the gap: the numbers the dropped messages had are missing
                assert got.body["Messages"][0]["SequenceNumber"] > len(numbers)
    finally:
        await app.stop()


async def test_broker_away_at_start_the_server_serves_and_says_so_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    down = Broker(tmp_path / "nobroker")  # a free port nobody listens on
    app = await start_app(pubsub_config(tmp_path / "data", down))
    try:
        assert app.pubsub is not None
        async with Client(app.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            assert await client.get_node(ua.NodeId(f"{F}.Status.MachSpeed", ns)).read_value() is not None
            await wait_until(lambda: app.pubsub is not None and app.pubsub.link.last_error != "", timeout=30)
            first = app.pubsub.link.last_error
            # retries go on (0.5 s, 1 s, ...) but the same reason is logged once
            await wait_until(lambda: app.pubsub is not None and app.pubsub.link.failures >= 3, timeout=30)
            assert app.pubsub.link.connects == 0
            lines = [r for r in caplog.records if "pubsub: the broker" in r.getMessage()]
            assert len(lines) == 1 and first in lines[0].getMessage()
    finally:
        await app.stop()


async def test_tls_and_a_password_from_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tls = make_tls(tmp_path / "tls")
    secure = Broker(tmp_path / "secure", users={"cell": "s3cret-pass"}, tls=tls)
    secure.start()
    try:
        monkeypatch.setenv("UACELL_MQTT_PASSWORD", "s3cret-pass")
        app = await start_app(pubsub_config(tmp_path / "data", secure, username="cell", ca_file=tls.ca))
        try:
            assert app.pubsub is not None
            await wait_until(app.pubsub.link.connected.is_set, timeout=30)
            ctx = ssl.create_default_context(cafile=str(tls.ca))
            async with subscribed(secure, "opcua/#", username="cell", password="s3cret-pass", tls_context=ctx) as sub:
                meta = await sub.wait_for(lambda r: r.topic.endswith(f"/metadata/{PUBLISHER}/Cell/{F}"))
                assert meta.retain
        finally:
            await app.stop()
    finally:
        secure.stop()


async def test_a_wrong_password_gives_one_clear_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    guarded = Broker(tmp_path / "guarded", users={"cell": "right-password"})
    guarded.start()
    try:
        monkeypatch.setenv("UACELL_MQTT_PASSWORD", "wrong-password")
        app = await start_app(pubsub_config(tmp_path / "data", guarded, username="cell"))
        try:
            assert app.pubsub is not None
            await wait_until(lambda: app.pubsub is not None and app.pubsub.link.failures >= 2, timeout=30)
            lines = [r.getMessage() for r in caplog.records if "pubsub: the broker" in r.getMessage()]
            assert len(lines) == 1, lines
            assert guarded.url in lines[0]
            assert "not authorized" in lines[0].lower() or "bad user name" in lines[0].lower(), lines[0]
            assert app.pubsub.link.connects == 0
        finally:
            await app.stop()
    finally:
        guarded.stop()


async def test_the_pubsub_configuration_is_readable_below_publish_subscribe_and_not_writable(served) -> None:
    app, client = served
    assert app.pubsub is not None
    await wait_until(app.pubsub.link.connected.is_set)
    ps = client.get_node(ua.ObjectIds.PublishSubscribe)
    conns = await ps.get_referenced_nodes(ua.ObjectIds.HasPubSubConnection)
    (conn,) = conns
    assert (await conn.read_browse_name()).Name == "MQTT"
    assert await (await conn.get_child("0:PublisherId")).read_value() == PUBLISHER
    profile = await (await conn.get_child("0:TransportProfileUri")).read_value()
    assert profile == "http://opcfoundation.org/UA-Profile/Transport/pubsub-mqtt-json"
    (group,) = await conn.get_referenced_nodes(ua.ObjectIds.HasWriterGroup)
    assert await (await group.get_child("0:PublishingInterval")).read_value() == 50.0
    state = await group.get_child(["0:Status", "0:State"])
    await wait_until_async(lambda: state.read_value(), ua.PubSubState.Operational)
    writers = await group.get_referenced_nodes(ua.ObjectIds.HasDataSetWriter)
    assert len(writers) == len(app.pubsub.writers)
    by_name = {w.name: w for w in app.pubsub.writers}
    for node in writers:
        name = (await node.read_browse_name()).Name
        assert await (await node.get_child("0:DataSetWriterId")).read_value() == by_name[name].writer_id
    datasets = await client.get_node(ua.ObjectIds.PublishSubscribe_PublishedDataSets).get_children()
    names = [(await d.read_browse_name()).Name for d in datasets]
    filler = datasets[names.index(F)]
    meta = await (await filler.get_child("0:DataSetMetaData")).read_value()
    assert [f.Name for f in meta.Fields] == [f.name for f in by_name[F].fields]
    # the structured PackML fields, described with NodeIds indexed by the metadata's own Namespaces
    assert meta.Namespaces == ["http://opcfoundation.org/UA/PackML/"]
    alarm = next(d for d in meta.StructureDataTypes if d.Name.Name == "PackMLAlarmDataType")
    assert alarm.DataTypeId.NamespaceIndex == 1 and alarm.Name.NamespaceIndex == 1
    assert [f.Name for f in alarm.StructureDefinition.Fields][:3] == ["ID", "Value", "Message"]
    alarm_field = next(f for f in meta.Fields if f.Name == "Admin/Alarm")
    assert alarm_field.DataType == alarm.DataTypeId and alarm_field.ValueRank == 1
    version = by_name[F].version
    assert (meta.ConfigurationVersion.MajorVersion, meta.ConfigurationVersion.MinorVersion) == (
        version.major,
        version.minor,
    )
    published = await (await filler.get_child("0:PublishedData")).read_value()
    ns = await client.get_namespace_index("urn:uacell:cell")
    assert ua.NodeId(f"{F}.Status.MachSpeed", ns) in [p.PublishedVariable for p in published]
    (target,) = await filler.get_referenced_nodes(ua.ObjectIds.DataSetToWriter)
    assert (await target.read_browse_name()).Name == F
    # read-only: a write is refused, the value stays
    interval = await group.get_child("0:PublishingInterval")
    with pytest.raises(ua.UaStatusCodeError) as e:
        await interval.write_value(ua.Variant(1.0, ua.VariantType.Double))
    assert e.value.code in (ua.StatusCodes.BadNotWritable, ua.StatusCodes.BadUserAccessDenied)
    assert await interval.read_value() == 50.0


async def wait_until_async(read: Any, expected: Any, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while (got := await read()) != expected:
        assert time.monotonic() < deadline, f"{got} != {expected}"
        await asyncio.sleep(0.02)
