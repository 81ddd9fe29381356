"""Every message a served cell sends to Debian's mosquitto, run through the validator written from OPC
10000-14/-6 v1.05 (tests/pubsub_validator.py): status, connection, metadata, data and events of a PackML
cycle and a robot program, keep-alives, and the clean stop that clears the retained topics. And the
broker dropping uacell on a keep-alive timeout, then a lost network: reconnects logged in one line each
with no traceback, each Will with a MessageId of its own (docs/pubsub.md)."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
from pathlib import Path
from typing import Any, cast

import pytest
from asyncua import Client, ua
from conftest import start_app
from helpers import call_path, wait_until
from mqtt_broker import Broker, Received, Subscriber, needs_mosquitto, subscribed
from pubsub_validator import Validator
from test_pubsub_server import CTRL, EXEC, MACH, PUBLISHER, SO, TASK, TC, F, pubsub_config, states, transitions_of

from uacell.pubsub.messages import DISABLED, ERROR, OPERATIONAL

pytestmark = needs_mosquitto


def validate(sub: Subscriber) -> Validator:
    v = Validator()
    for r in sub.messages:
        v.check(r.topic, r.raw, retain=r.retain)
    return v


def status_of(r: Received) -> int | None:
    return r.body["Status"] if r.body is not None and r.body.get("MessageType") == "ua-status" else None


async def ok(client: Client, obj: str, method: str, *args: ua.Variant) -> None:
    res = await call_path(client, obj, method, *args)
    assert res.StatusCode.is_good(), (obj, method, res.StatusCode)


async def address_space_masks(client: Client) -> dict[str, Any]:
    """The content masks and header layout below Server/PublishSubscribe, as a client reads them."""
    (conn,) = await client.get_node(ua.ObjectIds.PublishSubscribe).get_referenced_nodes(
        ua.ObjectIds.HasPubSubConnection
    )
    (group,) = await conn.get_referenced_nodes(ua.ObjectIds.HasWriterGroup)
    writers = {}
    for w in await group.get_referenced_nodes(ua.ObjectIds.HasDataSetWriter):
        name = (await w.read_browse_name()).Name
        field_mask = await (await w.get_child("0:DataSetFieldContentMask")).read_value()
        message_mask = await (await w.get_child(["0:MessageSettings", "0:DataSetMessageContentMask"])).read_value()
        writers[name] = (field_mask, message_mask)
    return {
        "layout": await (await group.get_child("0:HeaderLayoutUri")).read_value(),
        "network": await (await group.get_child(["0:MessageSettings", "0:NetworkMessageContentMask"])).read_value(),
        "writers": writers,
    }


async def test_every_message_of_a_served_cell_validates_and_a_clean_stop_clears_the_retained_topics(
    tmp_path: Path, broker: Broker
) -> None:
    # an enumeration field too (Robotics' ExecutionMode): a verbose Enumeration, described in EnumDataTypes
    extra = ["task_control:ParameterSet/ExecutionMode"]
    config = pubsub_config(tmp_path / "data", broker, keep_alive=5, extra_values=extra)
    async with subscribed(broker, "opcua/#") as sub:
        app = await start_app(config)
        try:
            assert app.pubsub is not None
            writers = {w.name: w for w in app.pubsub.writers}
            async with Client(app.endpoint, timeout=30) as client:
                execute = "BaseStateMachine/MachineState/ExecuteState/CurrentState"
                await ok(client, MACH, "Reset")
                await wait_until(lambda: "Idle" in states(sub, F, execute))
                await ok(client, EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject))
                await wait_until(lambda: "Execute" in states(sub, F, execute))
                await ok(client, MACH, "Stop")
                await ok(client, SO, "GetReady")
                await wait_until(
                    lambda: "Ready" in states(sub, CTRL, "SystemOperation/SystemOperationStateMachine/CurrentState")
                )
                for program in ("gripper", "pick_and_place"):
                    await ok(client, TC, "LoadByName", ua.Variant(program, ua.VariantType.String))
                await ok(client, TC, "Start")
                await wait_until(lambda: "ExecutingToReady" in transitions_of(sub, f"{TASK}.Events"))
                # a writer with nothing new for keep_alive (5 s) sends a keep-alive
                await wait_until(lambda: any(m["MessageType"] == "ua-keepalive" for m in sub.data()), timeout=30)
                shown = await address_space_masks(client)
            versions = {name: w.version for name, w in writers.items()}
        finally:
            await app.stop()
        topics = {f"opcua/json/connection/{PUBLISHER}"} | {f"opcua/json/metadata/{PUBLISHER}/Cell/{n}" for n in writers}
        await wait_until(lambda: {r.topic for r in sub.messages if r.raw == b""} >= topics, timeout=15)
        await wait_until(
            lambda: status_of(sub.messages[-1]) == DISABLED or any(status_of(r) == DISABLED for r in sub.messages)
        )

    v = validate(sub)
    assert {k for k, n in v.checked.items() if n} == {"ua-status", "ua-connection", "ua-metadata", "ua-data"}
    # the address space declares what is sent: the masks the validator checked every message against
    conn = next(r.body for r in sub.messages if r.topic.endswith(f"/connection/{PUBLISHER}") and r.raw)
    (group,) = conn["Connection"]["WriterGroups"]
    sent = {
        "layout": group["HeaderLayoutUri"],
        "network": group["MessageSettings"]["NetworkMessageContentMask"],
        "writers": {
            w["Name"]: (w.get("DataSetFieldContentMask", 0), w["MessageSettings"]["DataSetMessageContentMask"])
            for w in group["DataSetWriters"]
        },
    }
    assert shown == sent
    assert sent["writers"][f"{F}.Events"][0] == 0 and sent["writers"][F][0] == 3
    assert v.cleared == topics  # metadata and connection cleared; the status stays, Disabled
    data = sub.data()
    kinds = {m["MessageType"] for m in data}
    assert {"ua-keyframe", "ua-deltaframe", "ua-event", "ua-keepalive"} <= kinds
    # an inactive sub-state machine: its Status, not a null that reads as Good (§5.4.2.18)
    inactive = [
        f
        for m in sub.data(f"/{F}")
        for f in m.get("Payload", {}).values()
        if isinstance(f, dict) and f.get("Value") is None
    ]
    assert inactive and all(f["Status"]["Symbol"] == "BadStateNotActive" for f in inactive)
    # events: every field, null ones too (§7.2.5.4)
    event = next(m for m in sub.data(f"/{F}.Events") if m["MessageType"] == "ua-event")
    assert event["Payload"]["ConditionName"] is None and event["Payload"]["Transition"]["Text"]
    # Filler1's structured PackML fields are described for a generic decoder
    meta = next(r.body for r in sub.messages if r.topic.endswith(f"/metadata/{PUBLISHER}/Cell/{F}") and r.raw)
    described = {s["Name"] for s in meta["MetaData"]["StructureDataTypes"]}
    assert "nsu=http://opcfoundation.org/UA/PackML/;PackMLAlarmDataType" in described
    assert meta["MetaData"]["Namespaces"] == ["http://opcfoundation.org/UA/PackML/"]
    # the Enumeration field: "<name>_<value>", its names in EnumDataTypes
    task_meta = next(r.body for r in sub.messages if r.topic.endswith(f"/metadata/{PUBLISHER}/Cell/{TASK}") and r.raw)
    (enum,) = task_meta["MetaData"]["EnumDataTypes"]
    names = {f"{f['Name']}_{f['Value']}" for f in enum["EnumDefinition"]["Fields"]}
    modes = [
        m["Payload"]["ParameterSet/ExecutionMode"]["Value"]
        for m in sub.data(f"/{TASK}")
        if "ParameterSet/ExecutionMode" in m.get("Payload", {})
    ]
    assert modes and set(modes) <= names and "CONTINUOUS_1" in names
    # no empty Locale anywhere
    assert all('"Locale":""' not in r.raw.decode() for r in sub.messages)

    # after the stop a late subscriber finds the status (Disabled) and nothing else retained
    async with subscribed(broker, "opcua/#") as late:
        await late.wait_for(lambda r: status_of(r) is not None)
        await asyncio.sleep(0.3)  # retained messages arrive at once after subscribing; give stragglers a moment
        assert [(r.topic, status_of(r)) for r in late.messages] == [(f"opcua/json/status/{PUBLISHER}", DISABLED)]

    # a restart with the same cell keeps each DataSet's ConfigurationVersion
    again = await start_app(pubsub_config(tmp_path / "data", broker, keep_alive=5, extra_values=extra))
    try:
        assert again.pubsub is not None
        assert {w.name: w.version for w in again.pubsub.writers} == versions
    finally:
        await again.stop()


async def test_a_dropped_connection_reconnects_with_one_line_no_traceback_and_a_new_will(
    tmp_path: Path, broker: Broker, caplog: pytest.LogCaptureFixture
) -> None:
    """The broker stopped (SIGSTOP) until paho's keep-alive gives up, then continued: the broker drops
    the old connection and publishes its Will. Then the network goes (the socket shut): the broker
    publishes the Will of the new connection. Each Will has a MessageId of its own (Table 191)."""
    caplog.set_level(logging.INFO)
    assert broker.process is not None
    pid = broker.process.pid
    config = pubsub_config(tmp_path / "data", broker, keep_alive=5)
    app = await start_app(config)
    try:
        assert app.pubsub is not None
        link = app.pubsub.link
        await wait_until(link.connected.is_set)
        async with subscribed(broker, f"opcua/json/status/{PUBLISHER}") as sub:
            await sub.wait_for(lambda r: status_of(r) == OPERATIONAL)
            os.kill(pid, signal.SIGSTOP)
            try:
                await wait_until(lambda: not link.connected.is_set(), timeout=40)
            finally:
                os.kill(pid, signal.SIGCONT)
            await wait_until(lambda: link.connected.is_set() and link.connects >= 2, timeout=60)
            await sub.wait_for(lambda r: status_of(r) == ERROR, timeout=30)
            # the network lost: the socket shut under paho, no DISCONNECT sent
            session = link.session
            assert session is not None
            sock = session._client.socket()
            assert sock is not None
            cast(socket.socket, sock).shutdown(socket.SHUT_RDWR)  # paho's plain TCP socket to the test broker
            await wait_until(lambda: link.connected.is_set() and link.connects >= 3, timeout=60)
            await wait_until(lambda: len([r for r in sub.messages if status_of(r) == ERROR]) >= 2, timeout=30)
            await wait_until(lambda: status_of(sub.messages[-1]) == OPERATIONAL, timeout=30)
        wills = [r.body["MessageId"] for r in sub.messages if status_of(r) == ERROR]
        assert len(set(wills)) == len(wills) >= 2, wills
        ids = [r.body["MessageId"] for r in sub.messages]
        assert len(set(ids)) == len(ids), ids
        validate(sub)
    finally:
        await app.stop()
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not errors, [(r.name, r.getMessage()) for r in errors]
    assert "Traceback" not in caplog.text
    drops = [r.getMessage() for r in caplog.records if "pubsub: the broker" in r.getMessage()]
    assert 1 <= len(drops) <= 4, drops  # a line per reason, not per retry
