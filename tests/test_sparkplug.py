"""Sparkplug B 3.0 from a served cell to Debian's mosquitto on a free port, checked by an independent
host application (sparkplug_host.py: protoc-generated classes from the spec's payload definition):
births before data with aliases, seq without gaps, bdSeq of NBIRTH and NDEATH after kill -9, rebirth,
DDEATH/DBIRTH when a PLC goes and comes back, the primary host's STATE, commands with and without a
role, the broker lost while OPC UA calls go on (docs/sparkplug.md)."""

from __future__ import annotations

import json
import logging
import os
import ssl
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving, start_app
from helpers import call_path, free_port, packml_params, wait_until
from mqtt_broker import Broker, make_tls, needs_mosquitto, running_broker
from sparkplug_host import BOOLEAN, FLOAT, INT32, STRING, Host, compile_proto, following, value
from test_operations import sample, scrape, wait_for_audit

from uacell.catalog import companions
from uacell.config import Config, load_cell
from uacell.core.companion import datasets_of
from uacell.core.errors import ConfigError
from uacell.robotics.datasets import POSITION
from uacell.sparkplug.config import SparkplugConfig, check_sparkplug, password_of
from uacell.sparkplug.node import Device, EdgeNode, Sample
from uacell.sparkplug.payload import DataType

GROUP, EDGE = "plant", "cell-under-test"
F = "Filler1"
MACH = f"{F}.BaseStateMachine.MachineState"
EXEC = f"{MACH}.ExecuteState"
CTRL = "Robot1.Controllers.Controller1"
EXEC_STATE = "BaseStateMachine/MachineState/ExecuteState/CurrentState"
SRC = Path(__file__).resolve().parents[1] / "src"


@pytest.fixture(autouse=True)
def _sparkplug_said(caplog: pytest.LogCaptureFixture) -> None:
    """What the edge node and its MQTT link say at INFO (a STATE followed or ignored, a session left,
    a reconnection) is in a failing test's report."""
    for name in ("uacell.sparkplug", "uacell.pubsub"):
        caplog.set_level(logging.INFO, logger=name)


@pytest.fixture(scope="module")
def pb(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    return compile_proto(tmp_path_factory.mktemp("sparkplug_pb"))


# -- pure: payloads, sequence numbers, the configuration -------------------------------------------


def test_a_birth_and_data_decode_with_the_spec_definition(pb: ModuleType) -> None:
    node = EdgeNode(GROUP, EDGE, bdseq=7)
    device = Device("D1")
    a = node.first_device_alias  # after the node's own: bdSeq 1, Node Control/Rebirth 2
    assert a == 3
    device.add("Speed", DataType.Float, Sample(1.5, 1000), [("engUnit", DataType.String, "ppm")], alias=a)
    device.add("Offset", DataType.Int32, Sample(-5, 1001), alias=a + 1)
    device.add("Name", DataType.String, Sample(None, 1002), alias=a + 2)
    node.devices["D1"] = device
    births = [node.nbirth(2000), node.dbirth(device, 2000)]
    device.update(a + 1, Sample(-70000, 3000))
    data = node.ddata(device, 3001)
    assert data is not None and node.ddata(device, 3002) is None  # nothing new: no message
    host = Host(pb, 0, GROUP)
    for m in [*births, data]:
        host.handle(m.topic, m.payload)
    assert host.errors == []
    assert [s.topic for s in host.seen] == [
        f"spBv1.0/{GROUP}/NBIRTH/{EDGE}",
        f"spBv1.0/{GROUP}/DBIRTH/{EDGE}/D1",
        f"spBv1.0/{GROUP}/DDATA/{EDGE}/D1",
    ]
    view = host.device(EDGE, "D1")
    assert view.values == {"Speed": 1.5, "Offset": -70000, "Name": None}
    assert view.properties["Speed"] == {"engUnit": "ppm"} and view.stamps["Offset"] == 3000
    assert host.nodes[EDGE].births == [7] and host.nodes[EDGE].aliases == {"bdSeq": 1, "Node Control/Rebirth": 2}
    (only,) = host.seen[2].payload.metrics
    assert only.alias == a + 1 and not only.HasField("name") and only.datatype == INT32  # by alias only
    death = pb.Payload()
    death.ParseFromString(node.ndeath(4000).payload)
    assert [(m.name, value(m, m.datatype)) for m in death.metrics] == [("bdSeq", 7)]
    assert not death.HasField("seq")


def test_a_value_its_datatype_cannot_hold_is_null_not_an_error(pb: ModuleType) -> None:
    node = EdgeNode(GROUP, EDGE)
    device = Device("D1")
    device.add("Count", DataType.Int32, Sample("not a number", 5), alias=3)
    node.devices["D1"] = device
    host = Host(pb, 0, GROUP)
    for m in (node.nbirth(5), node.dbirth(device, 5)):
        host.handle(m.topic, m.payload)
    assert host.device(EDGE, "D1").values == {"Count": None} and host.errors == []


def test_seq_wraps_after_255_and_bdseq_counts_sessions() -> None:
    node = EdgeNode(GROUP, EDGE, bdseq=254)
    device = Device("D1")
    device.add("X", DataType.Int32, Sample(0, 0), alias=1)
    node.devices["D1"] = device
    node.nbirth(0)
    node.dbirth(device, 0)
    seqs = []
    for i in range(300):
        device.update(1, Sample(i, i))
        message = node.ddata(device, i)
        assert message is not None
        seqs.append(message.payload)
    assert node.seq == (2 + 300) % 256
    assert [node.next_session(), node.next_session()] == [255, 0]
    assert node.nbirth(0) and node.seq == 1  # a birth starts again at 0


@pytest.mark.parametrize(
    ("keys", "message"),
    [
        ({"broker": "http://x"}, "[sparkplug] broker: must look like mqtt://"),
        ({"broker": "mqtt://u:p@host"}, "[sparkplug] broker: no user or password"),
        ({"group_id": "a/b"}, "[sparkplug] group_id: must be one MQTT topic level"),
        ({"group_id": ""}, "[sparkplug] group_id: must be one MQTT topic level"),
        ({"edge_node_id": "a+"}, "[sparkplug] edge_node_id"),
        ({"primary_host_id": "#"}, "[sparkplug] primary_host_id"),
        ({"command_role": "root"}, "[sparkplug] command_role: must be one of"),
        ({"keep_alive": 2}, "[sparkplug] keep_alive"),
        ({"key_file": Path("k.pem")}, "[sparkplug] key_file: needs cert_file"),
        ({"extra_values": ["nocolon"]}, "[sparkplug] extra_values"),
        ({"parts": ["a/b"]}, "[sparkplug] parts"),
    ],
)
def test_settings_that_cannot_work_are_one_line(keys: dict[str, Any], message: str) -> None:
    cfg = SparkplugConfig(enabled=True, **keys)
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]").replace("+", r"\+")):
        check_sparkplug(cfg)


def test_the_password_only_from_an_owner_only_file_or_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    secret = tmp_path / "secret"
    secret.write_text("s3cret\n")
    secret.chmod(0o644)
    with pytest.raises(ConfigError, match="may be read by others"):
        password_of(SparkplugConfig(password_file=secret))
    secret.chmod(0o600)
    assert password_of(SparkplugConfig(password_file=secret)) == "s3cret"
    monkeypatch.setenv("UACELL_SPARKPLUG_PASSWORD", "from-env")
    assert password_of(SparkplugConfig()) == "from-env"


def test_the_section_is_read_from_toml(tmp_path: Path) -> None:
    from uacell.config import load_config

    path = tmp_path / "uacell.toml"
    path.write_text(
        f'[server]\ndata_dir = "{tmp_path / "d"}"\n[sparkplug]\nenabled = true\ngroup_id = "line1"\n'
        'parts = ["Filler1"]\ncommand_role = "operator"\n'
    )
    cfg = load_config(path).sparkplug
    assert (cfg.enabled, cfg.group_id, cfg.parts, cfg.command_role) == (True, "line1", ["Filler1"], "operator")
    path.write_text('[sparkplug]\ngroup_id = "a/b"\n')
    with pytest.raises(ConfigError, match=r"\[sparkplug\] group_id"):
        load_config(path)


def test_every_command_is_refused_to_the_role_commands_run_under_by_default() -> None:
    """Without ``command_role`` commands run as observer: the role table refuses every declared one."""
    from uacell.core.rights import RoleTable
    from uacell.core.roles import Role

    may_call = RoleTable(companions()).may_call

    families = {"packml_unit": "PackML", "controller": "SystemOperation", "task_control": "TaskControl"}
    declared = 0
    for role, family in families.items():
        dataset = datasets_of(companions()).of(role)
        assert dataset is not None
        for _name, targets in dataset.commands:
            for _obj, method in targets:
                declared += 1
                assert not may_call(Role.OBSERVER, method, family), (role, method)
                assert may_call(Role.OPERATOR, method, family), (role, method)
    assert declared == 19


def test_devices_of_the_demo_cell_and_what_joins_them() -> None:
    from uacell.sparkplug.devices import PartRef, plan_devices

    demo = [  # the demo cell's parts as the server builds them (role, path), in its order
        ("", "Robot1"),
        ("controller", CTRL),
        ("task_control", f"{CTRL}.TaskControls.TaskControl1"),
        ("", f"{CTRL}.Software.Software1"),
        ("motion_device", "Robot1.MotionDevices.Arm1"),
        ("", "Robot1.MotionDevices.Arm1.Axes.Axis1"),
        ("", "Robot1.SafetyStates.SafetyState1"),
        ("packml_unit", F),
    ]
    parts = [PartRef(role, ua.NodeId(path, 6), path) for role, path in demo]
    datasets = datasets_of(companions())
    plans = plan_devices(datasets, parts, axis_positions=False)
    assert [p.device_id for p in plans] == [CTRL, F]
    robot = plans[0]
    assert [(s.part.path, s.prefix) for s in robot.sources] == [
        (CTRL, ""),
        (f"{CTRL}.TaskControls.TaskControl1", "TaskControls/TaskControl1/"),
        ("Robot1.MotionDevices.Arm1", "MotionDevices/Arm1/"),
    ]
    assert all(i.kind is not POSITION for s in robot.sources for i in s.items)
    assert [p.device_id for p in plan_devices(datasets, parts, only=[F])] == [F]


# -- a served cell ---------------------------------------------------------------------------------


def sparkplug_config(data: Path, broker: Broker, **keys: Any) -> Config:
    config = fast_config(data)
    s = config.sparkplug
    s.enabled, s.broker, s.group_id, s.edge_node_id = True, broker.url, GROUP, EDGE
    for key, v in keys.items():
        setattr(s, key, v)
    return config


@pytest.fixture
async def host(pb: ModuleType, broker: Broker) -> AsyncIterator[Host]:
    async with following(pb, broker.port, GROUP, "scada") as h:
        yield h


async def born(host: Host, *devices: str, births: int = 1) -> None:
    await host.wait(lambda: len(host.of("NBIRTH")) >= births)
    for d in devices:
        await host.wait(lambda d=d: host.device(EDGE, d).births >= births)


def metric(host: Host, device: str, name: str) -> Any:
    return host.device(EDGE, device).values.get(name)


@needs_mosquitto
async def test_births_before_data_aliases_resolved_seq_without_gaps(tmp_path: Path, broker: Broker, host: Host) -> None:
    async with serving(sparkplug_config(tmp_path / "data", broker, command_role="operator")) as (_app, client):
        await born(host, F, CTRL)
        filler = host.device(EDGE, F)
        assert filler.values["BaseStateMachine/MachineState/CurrentState"] == "Stopped"
        assert filler.datatypes["Status/MachSpeed"] == FLOAT and filler.datatypes["Status/UnitModeCurrent"] == INT32
        assert filler.datatypes["Command/Reset"] == BOOLEAN and filler.datatypes["Command/SetMachSpeed"] == FLOAT
        robot = host.device(EDGE, CTRL)
        assert robot.values["SystemOperation/SystemOperationStateMachine/CurrentState"] == "Idle"
        assert robot.datatypes["Command/LoadByName"] == STRING
        assert "MotionDevices/Arm1/Axes/Axis1/ParameterSet/ActualPosition" in robot.values
        assert len(set(filler.aliases) | set(robot.aliases)) == len(filler.aliases) + len(robot.aliases)
        # a PackML cycle from an OPC UA client: every state arrives as DDATA by alias, in order
        assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
        await host.wait(lambda: metric(host, F, EXEC_STATE) == "Idle")
        assert (await call_path(client, EXEC, "Start", packml_params())).StatusCode.is_good()
        await host.wait(lambda: metric(host, F, EXEC_STATE) == "Execute")
        speed = ua.Variant(75.0, ua.VariantType.Float)
        assert (await call_path(client, F, "SetMachSpeed", speed)).StatusCode.is_good()
        await host.wait(lambda: metric(host, F, "Status/MachSpeed") == 75.0)
        ns = await client.get_namespace_index("urn:uacell:cell")
        dv = await client.get_node(ua.NodeId(f"{F}.Status.MachSpeed", ns)).read_data_value()
        assert filler.stamps["Status/MachSpeed"] == int(dv.SourceTimestamp.timestamp() * 1000)  # the source's
        states = [
            value(m, 12)
            for s in host.of("DDATA", F)
            for m in s.payload.metrics
            if filler.aliases[m.alias] == EXEC_STATE
        ]
        assert [s for s in states if s] == ["Resetting", "Idle", "Starting", "Execute"]
        births = [i for i, s in enumerate(host.seen) if s.kind in ("NBIRTH", "DBIRTH")]
        first_data = min(i for i, s in enumerate(host.seen) if s.kind == "DDATA")
        assert max(births) < first_data
        assert host.errors == []  # seq without gaps, aliases all born


@needs_mosquitto
@pytest.mark.interop
async def test_eclipse_tahus_decoder_reads_what_the_host_read(tmp_path: Path, broker: Broker, host: Host) -> None:
    """The third reader: Eclipse Tahu's JavaScript library (sparkplug-payload, interop/) decodes every
    message the host took, and finds the same seq, names, aliases, types and values."""
    import base64
    import json

    from conftest import INTEROP

    async with serving(sparkplug_config(tmp_path / "data", broker)) as (_app, client):
        await born(host, F, CTRL)
        assert (await call_path(client, F, "SetMachSpeed", ua.Variant(64.5, ua.VariantType.Float))).StatusCode.is_good()
        await host.wait(lambda: metric(host, F, "Status/MachSpeed") == 64.5)
    seen = [x for x in host.seen if x.kind in ("NBIRTH", "DBIRTH", "DDATA")]
    given = json.dumps([{"topic": x.topic, "payload": base64.b64encode(x.raw).decode()} for x in seen])
    proc = subprocess.run(
        ["node", str(INTEROP / "sparkplug_decode.js")], input=given, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    tahu = json.loads(proc.stdout.splitlines()[-1])["messages"]
    assert [m["seq"] for m in tahu] == [x.payload.seq for x in seen]
    names = {"Boolean": BOOLEAN, "Float": FLOAT, "Int32": INT32, "String": STRING}
    tahu_uint32 = 0
    for x, t in zip(seen, tahu, strict=True):
        for ours, theirs in zip(x.payload.metrics, t["metrics"], strict=True):
            assert theirs["alias"] == ours.alias
            assert theirs.get("name", "") == ours.name
            if theirs["type"] in names:
                assert names[theirs["type"]] == ours.datatype
            mine = value(ours, ours.datatype)
            if theirs["type"] == "UInt32":
                # Tahu's JavaScript library reads a UInt32 from long_value; Sparkplug 3.0 ("Datatype
                # Details": Google Protocol Buffer Type uint32) and uacell put it in int_value
                assert ours.WhichOneof("value") in ("int_value", None) and theirs["value"] is None
                tahu_uint32 += 1
            elif isinstance(mine, float):
                assert theirs["value"] == pytest.approx(mine)
            elif mine is not None:
                assert theirs["value"] == mine, (x.topic, ours.alias)
    speeds = [m for t in tahu if "/DDATA/" in t["topic"] for m in t["metrics"] if m["value"] == 64.5]
    assert speeds and speeds[0]["type"] == "Float"
    assert tahu_uint32 > 0  # the deviation above is real (Command/Result/StatusCode, program pointers)


@needs_mosquitto
async def test_rebirth_on_request_and_data_after_it(tmp_path: Path, broker: Broker, host: Host) -> None:
    async with serving(sparkplug_config(tmp_path / "data", broker)) as (_app, client):
        await born(host, F, CTRL)
        bdseq = host.nodes[EDGE].bdseq
        await host.rebirth(EDGE)
        await born(host, F, CTRL, births=2)
        assert host.nodes[EDGE].births == [bdseq, bdseq]  # the same session
        assert host.of("NBIRTH")[1].payload.seq == 0
        await host.rebirth(EDGE, by_alias=True)  # the same by the alias the NBIRTH gave
        await born(host, F, CTRL, births=3)
        assert (await call_path(client, F, "SetMachSpeed", ua.Variant(33.0, ua.VariantType.Float))).StatusCode.is_good()
        await host.wait(lambda: metric(host, F, "Status/MachSpeed") == 33.0)
        assert host.errors == []


@needs_mosquitto
async def test_commands_are_refused_until_a_role_is_configured(tmp_path: Path, broker: Broker, host: Host) -> None:
    async with serving(sparkplug_config(tmp_path / "data", broker)) as (app, _client):
        await born(host, F)
        await host.dcmd(EDGE, F, ("Command/Reset", BOOLEAN, True))
        await host.wait(lambda: metric(host, F, "Command/Result/Symbol") == "BadUserAccessDenied")
        assert metric(host, F, "Command/Result/Status") is None  # PackML methods have no Status output
        assert metric(host, F, "Command/Result/Command") == "Command/Reset"
        assert metric(host, F, "Command/Result/StatusCode") == ua.StatusCodes.BadUserAccessDenied
        assert metric(host, F, "BaseStateMachine/MachineState/CurrentState") == "Stopped"
        entry = await wait_for_audit(app, lambda e: e.get("method") == "Reset" and e.get("session") == "sparkplug")
        assert entry["result"] == "BadUserAccessDenied" and entry["role"] == "observer"
        assert host.errors == []


@needs_mosquitto
async def test_commands_run_the_same_calls_with_the_configured_role(tmp_path: Path, broker: Broker, host: Host) -> None:
    extra = ["packml_unit:Status/StartParameters"]  # where a unit keeps Start's Parameter (docs/packml.md)
    config = sparkplug_config(tmp_path / "data", broker, command_role="operator", extra_values=extra)
    async with serving(config) as (app, _client):
        await born(host, F, CTRL)
        await host.dcmd(EDGE, F, ("Command/Reset", BOOLEAN, True), by_alias=True)
        await host.wait(lambda: metric(host, F, EXEC_STATE) == "Idle")
        assert metric(host, F, "Command/Result/Symbol") == "Good"
        entry = await wait_for_audit(app, lambda e: e.get("method") == "Reset" and e.get("session") == "sparkplug")
        assert (entry["result"], entry["role"], entry["user"]) == ("Good", "operator", "sparkplug")
        await host.dcmd(EDGE, F, ("Command/SetMachSpeed", FLOAT, 42.0))
        await host.wait(lambda: metric(host, F, "Status/MachSpeed") == 42.0)
        # a value of the wrong type: the dispatcher's answer, nothing changed
        await host.dcmd(EDGE, F, ("Command/SetMachSpeed", STRING, "fast"))
        await host.wait(lambda: metric(host, F, "Command/Result/Symbol") == "BadTypeMismatch")
        assert metric(host, F, "Status/MachSpeed") == 42.0
        # Start with its Parameter array from the metrics beside it
        await host.dcmd(EDGE, F, ("Command/Start", BOOLEAN, True), ("Command/Start/Parameter/7", FLOAT, 2.5))
        await host.wait(lambda: metric(host, F, EXEC_STATE) == "Execute")
        entry = await wait_for_audit(app, lambda e: e.get("method") == "Start" and e.get("session") == "sparkplug")
        assert entry["result"] == "Good"
        await host.wait(lambda: bool(json.loads(metric(host, F, "Status/StartParameters") or "[]")))
        (parameter,) = json.loads(metric(host, F, "Status/StartParameters"))
        assert (parameter["ID"], parameter["Value"]) == (7, 2.5)  # the metric set became Start's Parameter
        # a state the command cannot run in: the unit's answer
        await host.dcmd(EDGE, F, ("Command/Reset", BOOLEAN, True))
        await host.wait(lambda: metric(host, F, "Command/Result/Symbol") == "BadInvalidState")
        # a metric that is no command
        await host.dcmd(EDGE, F, ("Status/MachSpeed", FLOAT, 1.0))
        await host.wait(lambda: metric(host, F, "Command/Result/Symbol") == "BadNotWritable")
        # the robot: GetReady, then a program by name
        await host.dcmd(EDGE, CTRL, ("Command/GetReady", BOOLEAN, True))
        system = "SystemOperation/SystemOperationStateMachine/CurrentState"
        await host.wait(lambda: metric(host, CTRL, system) == "Ready")
        await host.dcmd(EDGE, CTRL, ("Command/LoadByName", STRING, "pick_and_place"))
        name = "TaskControls/TaskControl1/ParameterSet/TaskProgramName"
        await host.wait(lambda: metric(host, CTRL, name) == "PickAndPlace", timeout=30)
        assert metric(host, CTRL, "TaskControls/TaskControl1/ParameterSet/TaskProgramLoaded") is True
        assert metric(host, CTRL, "Command/Result/Command") == "Command/LoadByName"
        assert metric(host, CTRL, "Command/Result/Status") == 0  # LoadByName's Status output: loaded
        await host.dcmd(EDGE, CTRL, ("Command/UnloadProgram", BOOLEAN, True))
        await host.wait(lambda: metric(host, CTRL, "TaskControls/TaskControl1/ParameterSet/TaskProgramLoaded") is False)
        await host.dcmd(EDGE, CTRL, ("Command/LoadByName", STRING, "no_such_program"))
        await host.wait(lambda: metric(host, CTRL, "Command/Result/Status") == -1)  # Good call, Status: not found
        assert metric(host, CTRL, "Command/Result/Symbol") == "Good"
        await host.dcmd(EDGE, CTRL, ("Command/LoadByName", STRING, "pick_and_place"))
        await host.wait(lambda: metric(host, CTRL, name) == "PickAndPlace")
        await host.dcmd(EDGE, CTRL, ("Command/Start", BOOLEAN, True))
        await host.wait(lambda: metric(host, CTRL, "Command/Result/Command") == "Command/Start")
        assert metric(host, CTRL, "Command/Result/Symbol") == "Good"

        def program_run(e: dict[str, Any]) -> bool:
            ours = e.get("session") == "sparkplug"
            return ours and e.get("method") == "Start" and "TaskControl" in e.get("object", "")

        assert (await wait_for_audit(app, program_run))["result"] == "Good"
        assert host.errors == []


@needs_mosquitto
async def test_a_primary_host_offline_stops_publishing_and_its_return_brings_a_rebirth(
    tmp_path: Path, broker: Broker, host: Host
) -> None:
    async with serving(sparkplug_config(tmp_path / "data", broker, primary_host_id="scada")) as (app, client):
        sp = app.sparkplug
        assert sp is not None
        await wait_until(sp.link.connected.is_set)
        assert not sp.live and host.of("NBIRTH") == []  # connected, subscribed, waiting for the host
        await host.state(True)
        await born(host, F, CTRL)
        first = host.nodes[EDGE].bdseq
        assert first is not None  # its NBIRTH carried one
        await host.state(False, stamp=1)  # older than the online STATE: not followed
        assert (await call_path(client, F, "SetMachSpeed", ua.Variant(11.0, ua.VariantType.Float))).StatusCode.is_good()
        await host.wait(lambda: metric(host, F, "Status/MachSpeed") == 11.0)
        await host.state(False)
        await host.wait(lambda: bool(host.nodes[EDGE].deaths))
        assert host.nodes[EDGE].deaths == [first], [(x.kind, x.device) for x in host.seen]  # its NDEATH, once
        await wait_until(lambda: sp.link.connects >= 2 and not sp.live, timeout=30)
        seen = len(host.seen)
        assert (await call_path(client, F, "SetMachSpeed", ua.Variant(12.0, ua.VariantType.Float))).StatusCode.is_good()
        await app.settle()
        await host.state(True)
        await born(host, F, CTRL, births=2)
        assert host.nodes[EDGE].births == [first, (first + 1) % 256]
        assert host.seen[seen].kind == "NBIRTH"  # nothing between the NDEATH and it
        assert metric(host, F, "Status/MachSpeed") == 12.0  # the birth carries what changed meanwhile
        assert host.errors == []


@needs_mosquitto
async def test_kill_9_the_ndeath_has_the_bdseq_of_the_nbirth(tmp_path: Path, broker: Broker, host: Host) -> None:
    config = tmp_path / "uacell.toml"
    config.write_text(
        f"""
[server]
port = {free_port()}
data_dir = "{tmp_path / "data"}"

[web]
enabled = false

[sparkplug]
enabled = true
broker = "{broker.url}"
group_id = "{GROUP}"
edge_node_id = "{EDGE}"
keep_alive = 5
"""
    )
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    cmd = [sys.executable, "-m", "uacell", "serve", "--config", str(config)]
    for run in (1, 2):  # the second run goes on from the bdSeq the first one kept
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            await host.wait(lambda run=run: len(host.node(EDGE).births) >= run, timeout=60)
            proc.kill()
            proc.wait(10)
            killed = time.monotonic()
            await host.wait(lambda run=run: len(host.nodes[EDGE].deaths) >= run, timeout=15)
            assert time.monotonic() - killed <= 1.5 * 5 + 1.0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    node = host.nodes[EDGE]
    first = node.births[0]
    assert first is not None  # its NBIRTH carried one
    assert node.deaths == node.births and node.births[1] == (first + 1) % 256
    assert not node.online and host.errors == []


@needs_mosquitto
async def test_a_plc_lost_is_a_ddeath_and_its_return_a_dbirth(tmp_path: Path, broker: Broker, host: Host) -> None:
    from gateway_plcs import ModbusPLC
    from gateway_plcs import modbus_cell as shipped_cell

    plc = ModbusPLC()
    plc.start()
    try:
        path = tmp_path / "cell.toml"
        path.write_text(shipped_cell(plc))
        config = sparkplug_config(tmp_path / "data", broker)
        config.cell = load_cell(path)
        async with serving(config) as (_app, _client):
            await born(host, "Capper", "Labeler")
            assert host.device(EDGE, "Capper").values["Status/UnitModeCurrent"] is not None
            plc.kill()
            await host.wait(lambda: [host.device(EDGE, d).deaths for d in ("Capper", "Labeler")] == [1, 1])
            assert not host.device(EDGE, "Capper").online and host.nodes[EDGE].online  # the node lives on
            plc.start()  # the same port
            await host.wait(lambda: host.device(EDGE, "Capper").births == 2, timeout=30)
            capper = host.device(EDGE, "Capper")
            assert capper.online and capper.values["Status/UnitModeCurrent"] is not None
            assert host.errors == []
    finally:
        plc.kill()


@needs_mosquitto
async def test_a_robot_controller_lost_is_a_ddeath_and_its_return_a_dbirth(
    tmp_path: Path, broker: Broker, host: Host
) -> None:
    """The modbus-signals robot (the example controller behind Modbus/TCP): its axis values say when
    it cannot be reached, and so its device dies and is born again."""
    from test_gateway_robot import PLC, cell_text

    plc = PLC(free_port(), 1.0)
    plc.start()
    try:
        await plc.io()  # listening before uacell starts
        cell = tmp_path / "cell.toml"
        cell.write_text(cell_text(plc.port))
        config = sparkplug_config(tmp_path / "data", broker)
        config.cell = load_cell(cell)
        robot = "Palletizer.Controllers.Cabinet"
        async with serving(config):
            await born(host, robot)
            assert host.device(EDGE, robot).values["MotionDevices/Arm1/Axes/Axis1/ParameterSet/ActualPosition"] == 0.0
            plc.kill()
            await host.wait(lambda: host.device(EDGE, robot).deaths == 1)
            plc.start()  # the same port
            await host.wait(lambda: host.device(EDGE, robot).births == 2, timeout=30)
            assert host.device(EDGE, robot).online and host.errors == []
    finally:
        plc.kill()
        for conn in plc.clients:
            conn.close()


@needs_mosquitto
async def test_tls_and_a_password_from_the_environment(
    tmp_path: Path, pb: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    tls = make_tls(tmp_path / "tls")
    users = {"cell": "s3cret-pass", "scada": "h0st-pass"}
    with running_broker(tmp_path / "secure", users=users, tls=tls) as secure:
        monkeypatch.setenv("UACELL_SPARKPLUG_PASSWORD", "s3cret-pass")
        ctx = ssl.create_default_context(cafile=str(tls.ca))
        async with following(pb, secure.port, GROUP, username="scada", password="h0st-pass", tls_context=ctx) as host:
            app = await start_app(sparkplug_config(tmp_path / "data", secure, username="cell", ca_file=tls.ca))
            try:
                assert secure.url.startswith("mqtts://")
                await born(host, F, CTRL)
                assert host.errors == []
            finally:
                await app.stop()
            await host.wait(lambda: host.nodes[EDGE].deaths == host.nodes[EDGE].births)  # a clean stop's NDEATH


@needs_mosquitto
async def test_a_wrong_password_is_one_clear_line_and_uacell_serves_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    with running_broker(tmp_path / "secure", users={"cell": "right-pass"}) as secure:
        monkeypatch.setenv("UACELL_SPARKPLUG_PASSWORD", "wrong-pass")
        async with serving(sparkplug_config(tmp_path / "data", secure, username="cell")) as (app, client):
            sp = app.sparkplug
            assert sp is not None
            await wait_until(lambda: sp.link.failures >= 3, timeout=30)
            lines = [r.getMessage() for r in caplog.records if r.name == "uacell.sparkplug.link"]
            assert len(lines) == 1 and "Not authorized" in lines[0] and secure.url in lines[0], lines
            res = await call_path(client, F, "SetMachSpeed", ua.Variant(5.0, ua.VariantType.Float))
            assert res.StatusCode.is_good() and not sp.live


@needs_mosquitto
async def test_a_ca_file_not_there_yet_is_one_line_and_the_node_is_born_once_it_is(
    tmp_path: Path, pb: ModuleType, caplog: pytest.LogCaptureFixture
) -> None:
    """The TLS set-up failing (the CA file missing) is a failed connection like any other: one WARNING
    line, no traceback, retries; once the file is there the node connects and is born."""
    tls = make_tls(tmp_path / "tls")
    ca_file = tmp_path / "later" / "ca.pem"
    with running_broker(tmp_path / "secure", tls=tls) as secure:
        ctx = ssl.create_default_context(cafile=str(tls.ca))
        async with following(pb, secure.port, GROUP, tls_context=ctx) as host:
            async with serving(sparkplug_config(tmp_path / "data", secure, ca_file=ca_file)) as (app, client):
                sp = app.sparkplug
                assert sp is not None
                await wait_until(lambda: sp.link.failures >= 2, timeout=30)
                lines = [r for r in caplog.records if r.name == "uacell.sparkplug.link"]
                assert len(lines) == 1 and lines[0].levelno == logging.WARNING and not lines[0].exc_info, lines
                assert secure.url in lines[0].getMessage() and "[sparkplug]" in lines[0].getMessage()
                res = await call_path(client, F, "SetMachSpeed", ua.Variant(5.0, ua.VariantType.Float))
                assert res.StatusCode.is_good() and not sp.live
                ca_file.parent.mkdir()
                ca_file.write_bytes(tls.ca.read_bytes())
                await born(host, F, CTRL)
                assert sp.link.connects == 1 and host.errors == []
    assert "Traceback" not in caplog.text


@needs_mosquitto
async def test_beside_pubsub_on_the_same_broker_with_the_default_ids(
    tmp_path: Path, broker: Broker, host: Host
) -> None:
    """[pubsub] and [sparkplug] on one broker, ids left to their defaults: two MQTT clients that do not
    push each other off (the same client id would), each publishing its own messages."""
    from mqtt_broker import subscribed

    config = sparkplug_config(tmp_path / "data", broker, edge_node_id="")
    config.pubsub.enabled, config.pubsub.broker, config.pubsub.publishing_interval = True, broker.url, 0.05
    async with subscribed(broker, "opcua/json/data/#") as sub, serving(config) as (app, client):
        sp, ps = app.sparkplug, app.pubsub
        assert sp is not None and ps is not None
        edge = sp.node.edge
        assert edge == ps.publisher.publisher_id  # the same default name, yet two clients
        await host.wait(lambda: host.device(edge, F).births == 1)
        res = await call_path(client, F, "SetMachSpeed", ua.Variant(21.0, ua.VariantType.Float))
        assert res.StatusCode.is_good()
        await host.wait(lambda: host.device(edge, F).values.get("Status/MachSpeed") == 21.0)
        await sub.wait_for(lambda r: "Status/MachSpeed" in str(r.body) and "21.0" in str(r.body))
        assert sp.link.connects == 1 and ps.link.connects == 1 and sp.link.failures == 0 == ps.link.failures
        assert len(host.of("NBIRTH")) == 1 and host.errors == []


@needs_mosquitto
async def test_the_broker_lost_calls_go_on_and_the_next_session_births_again(
    tmp_path: Path, pb: ModuleType, broker: Broker
) -> None:
    config = sparkplug_config(tmp_path / "data", broker)
    config.metrics.enabled, config.metrics.port = True, free_port()
    app = await start_app(config)
    try:
        sp = app.sparkplug
        assert sp is not None
        await wait_until(lambda: sp.live, timeout=30)
        first = sp.node.bdseq
        async with Client(app.endpoint, timeout=30) as client:
            broker.kill()
            await wait_until(lambda: not sp.link.connected.is_set(), timeout=30)
            res = await call_path(client, F, "SetMachSpeed", ua.Variant(55.0, ua.VariantType.Float))
            assert res.StatusCode.is_good()  # the server answers while the broker is away
            _, body = await scrape(app)  # and /metrics says so
            assert (
                sample(body, "uacell_sparkplug_connected") == 0 and sample(body, "uacell_sparkplug_sessions_total") == 1
            )
            broker.start()  # the same port
            async with following(pb, broker.port, GROUP) as host:
                # uacell may have connected and been born before this host subscribed: as a host does
                # on joining late, it asks for a rebirth once the node's new session is up
                await wait_until(lambda: sp.link.connects >= 2 and sp.live, timeout=30)
                await host.rebirth(EDGE)
                await born(host, F)
                assert host.nodes[EDGE].births[-1] == (first + 1) % 256
                assert metric(host, F, "Status/MachSpeed") == 55.0
                assert host.errors == []
                _, body = await scrape(app)
                assert (
                    sample(body, "uacell_sparkplug_sessions_total") == 2 and sample(body, "uacell_sparkplug_born") == 1
                )
    finally:
        await app.stop()
