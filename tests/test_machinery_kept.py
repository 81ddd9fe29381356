"""A machine's MachineryItemState and MachineryOperationMode kept by history and published over PubSub,
through the Machinery companion's DataSets (joined to the unit's and the robot's own): HistoryRead of
the values and the TransitionEvents from an asyncua client, and the JSON messages on Debian's mosquitto."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

from asyncua import ua
from conftest import serving
from helpers import call_path, until, wait_until
from helpers import cell_state as state
from mqtt_broker import Broker, needs_mosquitto, subscribed
from test_history_server import history, raw
from test_pubsub_server import pubsub_config, states, transitions_of

from uacell.catalog import companions
from uacell.core.companion import datasets_of

EXEC = "Filler1.BaseStateMachine.MachineState.ExecuteState"
MACH = "Filler1.BaseStateMachine.MachineState"
ITEM = "Filler1.MachineryBuildingBlocks.MachineryItemState"
FIELD = "MachineryBuildingBlocks/MachineryItemState/CurrentState"
EMPTY = ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)


def test_the_robot_and_the_unit_keep_their_own_dataset_and_the_machines():
    dataset_of = datasets_of(companions()).of
    unit = dataset_of("packml_unit")
    assert unit is not None and unit.values[0].path == "BaseStateMachine/CurrentState"  # PackML's first
    assert FIELD in [i.path for i in unit.values]
    assert "MachineryBuildingBlocks/MachineryOperationMode" in unit.notifiers
    robot = dataset_of("robot")
    assert robot is not None and [i.path for i in robot.values] == [
        FIELD,
        "MachineryBuildingBlocks/MachineryOperationMode/CurrentState",
    ]


async def cycle(client) -> None:
    assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
    await until(lambda: state(client, EXEC), "Idle")
    assert (await call_path(client, EXEC, "Start", EMPTY)).StatusCode.is_good()


async def test_history_keeps_the_item_state_and_its_transition_events(tmp_path: Path) -> None:
    from conftest import fast_config

    started = datetime.now(UTC) - timedelta(seconds=1)
    async with serving(fast_config(tmp_path / "data")) as (_app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        current = ua.NodeId(f"{ITEM}.CurrentState", ns)
        node = client.get_node(current)
        assert (await node.read_attribute(ua.AttributeIds.Historizing)).Value.Value is True
        await cycle(client)
        await until(lambda: state(client, ITEM), "Executing")

        async def kept() -> list[str]:  # the batched writer stores them soon after
            (res,) = await history(client, raw(started, datetime.now(UTC) + timedelta(seconds=5)), current)
            return [dv.Value.Value.Text for dv in res.HistoryData.DataValues]

        await until(kept, ["NotExecuting", "Executing"])  # the value at start, then the change
        # the TransitionEvent, kept with the machine's events
        details = ua.ReadEventDetails()
        details.StartTime, details.EndTime, details.NumValuesPerNode = (
            started,
            datetime.now(UTC) + timedelta(seconds=5),
            0,
        )
        evfilter = ua.EventFilter()
        evfilter.SelectClauses = [
            ua.SimpleAttributeOperand(
                TypeDefinitionId=ua.NodeId(ua.ObjectIds.BaseEventType),
                BrowsePath=[ua.QualifiedName("Message")],
                AttributeId=ua.AttributeIds.Value,
            )
        ]
        details.Filter = evfilter
        (res,) = await history(client, details, ua.NodeId(ITEM, ns))
        assert res.StatusCode.is_good(), res.StatusCode
        messages = [e.EventFields[0].Value.Text for e in res.HistoryData.Events]
        assert any("FromNotExecutingToExecuting" in m for m in messages), messages


@needs_mosquitto
async def test_pubsub_publishes_the_item_state_and_its_transitions(tmp_path: Path) -> None:
    broker = Broker(tmp_path / "broker")
    broker.start()
    try:
        async with serving(pubsub_config(tmp_path / "data", broker)) as (_app, client):
            async with subscribed(broker, "opcua/#") as sub:
                meta = await sub.wait_for(lambda r: r.topic.endswith("/metadata/cell-under-test/Cell/Filler1"))
                fields = {f["Name"]: f for f in meta.body["MetaData"]["Fields"]}
                assert fields[FIELD]["BuiltInType"] == 21  # LocalizedText
                await cycle(client)
                await wait_until(lambda: "Executing" in states(sub, "Filler1", FIELD))
                await wait_until(lambda: "FromNotExecutingToExecuting" in transitions_of(sub, "Filler1.Events"))
                robot = await sub.wait_for(lambda r: r.topic.endswith("/data/cell-under-test/Cell/Robot1"))
                (message,) = robot.body["Messages"]
                assert message["Payload"][FIELD]["Value"]["Text"] == "NotExecuting"
    finally:
        broker.stop()


async def test_metrics_count_the_machines_by_state_and_mode(tmp_path: Path) -> None:
    from conftest import fast_config
    from helpers import free_port
    from test_operations import sample, scrape

    config = fast_config(tmp_path / "data")
    config.metrics.enabled, config.metrics.port = True, free_port()
    async with serving(config) as (app, client):
        status, body = await scrape(app)
        assert status.endswith("200 OK")
        assert sample(body, "uacell_machines", item_state="NotExecuting", operation_mode="Processing") == 2.0
        await cycle(client)
        await until(lambda: state(client, ITEM), "Executing")
        _, body = await scrape(app)
        assert sample(body, "uacell_machines", item_state="NotExecuting", operation_mode="Processing") == 1.0
        assert sample(body, "uacell_machines", item_state="Executing", operation_mode="Processing") == 1.0
        # and each machine's own state with every other state machine's
        machine = "Filler1.MachineryBuildingBlocks.MachineryItemState"
        assert sample(body, "uacell_state_machine_state", machine=machine, state="Executing") == 1.0
