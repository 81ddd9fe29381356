"""A served cell's PubSub messages decoded by node-opcua's own OPC 10000-6 v1.05 JSON decoder
(node-opcua-json, interop/pubsub_decode.js), as a generic subscriber would: each field's BuiltInType
from the writer's metadata, the value from the JSON. What it reads must be what uacell holds.

Where node-opcua-json 2.186.4 departs from the standard it is not followed (docs/pubsub.md): it
reads a DataValue's status from "StatusCode" where OPC 10000-6 v1.05 §5.4.2.18 names it "Status",
and it decodes false, 0 and "" as null; those are left out of the comparison, not imitated."""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from conftest import run_node, serving
from helpers import call_path, wait_until
from mqtt_broker import Broker, needs_mosquitto, subscribed
from test_pubsub_server import EXEC, MACH, F, pubsub_config, states, transitions_of

pytestmark = [pytest.mark.interop, needs_mosquitto]

EXECUTE = "BaseStateMachine/MachineState/ExecuteState/CurrentState"


def falsy(value: Any) -> bool:
    return value in (False, 0, "") and value is not None


async def test_node_opcua_json_decodes_what_uacell_publishes(tmp_path: Path, broker: Broker) -> None:
    async with subscribed(broker, "opcua/#") as sub:
        async with serving(pubsub_config(tmp_path / "data", broker)) as (_app, client):
            assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
            await wait_until(lambda: "Idle" in states(sub, F, EXECUTE))
            start = await call_path(client, EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject))
            assert start.StatusCode.is_good()
            await wait_until(lambda: "StartingToExecute" in transitions_of(sub, f"{F}.Events"))
    capture = tmp_path / "messages.json"
    capture.write_text(json.dumps([{"topic": r.topic, "payload": r.raw.decode()} for r in sub.messages]))
    result = run_node("pubsub_decode.js", str(capture))
    assert result["errors"] == []
    assert "http://opcfoundation.org/UA/PackML/" in result["namespaces"]

    # every decoded field against the JSON uacell sent, message by message, field by field
    sent = [
        (r.topic, name, field)
        for r in sub.messages
        if "/json/data/" in r.topic
        for m in r.body["Messages"]
        for name, field in m.get("Payload", {}).items()
    ]
    decoded = iter(result["decoded"])
    compared: dict[str, int] = {}
    for topic, name, field in sent:
        value = field["Value"] if isinstance(field, dict) and "Value" in field else field
        if (isinstance(value, dict) and "Text" not in value) or isinstance(value, list):
            continue  # a structure: not decoded here
        got = next(decoded)
        assert (got["topic"], got["field"]) == (topic, name)
        if value is None or falsy(value):
            continue  # node-opcua-json reads false/0/"" as null
        if got["type"] == "LocalizedText":
            assert got["value"]["text"] == value["Text"], (name, got)
        elif got["type"] == "ByteString":
            assert base64.b64decode(got["value"]) == base64.b64decode(value)
        elif got["type"] == "DateTime":
            assert got["value"][:23] == value[:23], (name, got)
        elif got["type"] == "NodeId":
            assert got["value"].split(";")[-1] == value.split(";")[-1], (name, got)
        else:
            assert got["value"] == value, (name, got)
        compared[got["type"]] = compared.get(got["type"], 0) + 1
    assert next(decoded, None) is None
    assert {"LocalizedText", "Float", "Int32", "NodeId", "DateTime", "ByteString", "UInt16", "String"} <= set(compared)
