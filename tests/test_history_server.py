"""HistoryRead over a served cell from an asyncua client: values, events, continuation points, the
Part 11 codes, the attributes and capabilities, a restart (docs/history.md)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import until

from uacell.history.backends import VALUE
from uacell.history.service import mark_historizing, to_micros
from uacell.server import UacellServer

CELL = "urn:uacell:cell"
F = "Filler1"
HOUR = timedelta(hours=1)


@pytest.fixture
async def client(app: UacellServer) -> AsyncIterator[Client]:
    """A plain asyncua client of ``app`` (no data type definitions to load: none is needed here),
    keep-alives every 5 s: the in-process server and client share one loop on a loaded machine."""
    async with Client(app.endpoint, timeout=30, watchdog_intervall=5.0) as c:
        yield c


def now() -> datetime:
    return datetime.now(UTC)


async def history(client: Client, details: object, *nodes: ua.NodeId, cp: bytes | None = None) -> list[Any]:
    params = ua.HistoryReadParameters()
    params.HistoryReadDetails = details
    params.TimestampsToReturn = ua.TimestampsToReturn.Both
    params.ReleaseContinuationPoints = False
    params.NodesToRead = [ua.HistoryReadValueId(NodeId=n, ContinuationPoint=cp) for n in nodes]
    return list(await client.uaclient.history_read(params))


def raw(start: datetime | None, end: datetime | None, count: int = 0) -> ua.ReadRawModifiedDetails:
    d = ua.ReadRawModifiedDetails()
    d.IsReadModified = False
    d.StartTime = start or ua.get_win_epoch()
    d.EndTime = end or ua.get_win_epoch()
    d.NumValuesPerNode = count
    d.ReturnBounds = False  # asyncua's default is True: these tests read the values alone
    return d


async def set_speed(client: Client, ns: int, speed: float) -> None:
    unit = client.get_node(ua.NodeId(F, ns))
    await unit.call_method(ua.NodeId(f"{F}.SetMachSpeed", ns), ua.Variant(speed, ua.VariantType.Float))


async def read_all(client: Client, node: ua.NodeId, count: int, start: datetime, end: datetime) -> list[ua.DataValue]:
    """Every value through continuation points, ``count`` per request."""
    out: list[ua.DataValue] = []
    cp: bytes | None = None
    while True:
        (res,) = await history(client, raw(start, end, count), node, cp=cp)
        assert res.StatusCode.is_good(), res.StatusCode
        out += res.HistoryData.DataValues
        cp = res.ContinuationPoint
        if not cp:
            return out


async def test_values_attributes_and_capabilities(app: UacellServer, client: Client) -> None:
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(f"{F}.Status.MachSpeed", ns)
    t0 = now()
    for s in (10.0, 20.0, 30.0):
        await set_speed(client, ns, s)
    assert app.history is not None
    await app.history.store.flush()
    (res,) = await history(client, raw(t0 - HOUR, now() + HOUR), speed)
    assert res.StatusCode.is_good()
    assert [dv.Value.Value for dv in res.HistoryData.DataValues][-3:] == [10.0, 20.0, 30.0]
    times = [dv.SourceTimestamp for dv in res.HistoryData.DataValues]
    assert times == sorted(times)
    # newest first when StartTime is after EndTime
    (rev,) = await history(client, raw(now() + HOUR, t0 - HOUR), speed)
    assert [dv.Value.Value for dv in rev.HistoryData.DataValues][:3] == [30.0, 20.0, 10.0]

    node = client.get_node(speed)
    assert (await node.read_attribute(ua.AttributeIds.Historizing)).Value.Value is True
    level = (await node.read_attribute(ua.AttributeIds.AccessLevel)).Value.Value
    assert level & ua.AccessLevel.HistoryRead.mask
    user_level = (await node.read_attribute(ua.AttributeIds.UserAccessLevel)).Value.Value
    assert user_level & ua.AccessLevel.HistoryRead.mask
    # every kept variable's, the first one made through asyncua, the others copies of it with their own NodeIds
    for kept in (speed, ua.NodeId(f"{F}.OEE.Availability", ns), ua.NodeId(f"{F}.Admin.ProdProcessedCount", ns)):
        configs = await client.get_node(kept).get_referenced_nodes(ua.ObjectIds.HasHistoricalConfiguration)
        assert len(configs) == 1 and configs[0].nodeid.Identifier == f"{kept.Identifier}.HAConfiguration"
        assert (await configs[0].read_type_definition()) == ua.NodeId(ua.ObjectIds.HistoricalDataConfigurationType)
        assert (await configs[0].read_browse_name()) == ua.QualifiedName("HA Configuration", 0)
        back = await configs[0].get_referenced_nodes(
            ua.ObjectIds.HasHistoricalConfiguration, ua.BrowseDirection.Inverse
        )
        assert [n.nodeid for n in back] == [kept]
        assert await (await configs[0].get_child("0:Stepped")).read_value() is True
        aggregate = await configs[0].get_child("0:AggregateConfiguration")
        assert aggregate.nodeid.Identifier == f"{kept.Identifier}.HAConfiguration.AggregateConfiguration"
        assert await aggregate.read_type_definition() == ua.NodeId(ua.ObjectIds.AggregateConfigurationType)
        assert await (await aggregate.get_child("0:PercentDataGood")).read_value() == 100
        assert await (await aggregate.get_child("0:TreatUncertainAsBad")).read_value() is True
    # a variable nobody historizes has neither
    other = client.get_node(ua.NodeId(f"{F}.Status.StateChangeInProcess", ns))
    assert not (await other.read_attribute(ua.AttributeIds.AccessLevel)).Value.Value & ua.AccessLevel.HistoryRead.mask

    caps = ua.ObjectIds
    assert await client.get_node(caps.HistoryServerCapabilities_AccessHistoryDataCapability).read_value() is True
    assert await client.get_node(caps.HistoryServerCapabilities_AccessHistoryEventsCapability).read_value() is True
    assert await client.get_node(caps.HistoryServerCapabilities_InsertDataCapability).read_value() is False
    assert await client.get_node(caps.HistoryServerCapabilities_MaxReturnDataValues).read_value() == 10_000
    assert await client.get_node(caps.HistoryServerCapabilities_MaxReturnEventValues).read_value() == 1_000
    aggregates = await client.get_node(caps.HistoryServerCapabilities_AggregateFunctions).get_children()
    assert {n.nodeid for n in aggregates} == {
        ua.NodeId(getattr(ua.ObjectIds, f"AggregateFunction_{name}"))
        for name in ("Average", "Minimum", "Maximum", "Count", "TimeAverage", "Interpolative")
    }


async def test_a_variable_is_marked_historized_by_writes_only_where_it_is_not_yet(app: UacellServer) -> None:
    """What the snapshot keeps marked (``add_configurations`` marks before it is taken) a restart
    does not write again."""
    aspace = app.server.iserver.aspace
    objects = app.server.get_node(ua.ObjectIds.ObjectsFolder)
    var = await objects.add_variable(ua.NodeId("MarkedOnce", 1), "MarkedOnce", 1.5)
    written: list[ua.AttributeIds] = []
    write = aspace.write_attribute_value

    async def counting(node: ua.NodeId, attr: ua.AttributeIds, dv: ua.DataValue) -> ua.StatusCode:
        written.append(attr)
        return await write(node, attr, dv)

    aspace.write_attribute_value = counting
    try:
        await mark_historizing(aspace, var.nodeid)
        assert sorted(written) == sorted(
            [ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel, ua.AttributeIds.Historizing]
        )
        written.clear()
        await mark_historizing(aspace, var.nodeid)
        assert written == []
    finally:
        del aspace.write_attribute_value
    assert aspace.read_attribute_value(var.nodeid, ua.AttributeIds.Historizing).Value.Value is True
    level = aspace.read_attribute_value(var.nodeid, ua.AttributeIds.AccessLevel).Value.Value
    assert level & ua.AccessLevel.HistoryRead.mask and level & ua.AccessLevel.CurrentRead.mask


async def test_part11_codes(app: UacellServer, client: Client) -> None:
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(f"{F}.Status.MachSpeed", ns)
    plain = ua.NodeId(f"{F}.Status.StateChangeInProcess", ns)
    unknown = ua.NodeId("NoSuchNode", ns)
    codes = [r.StatusCode.value for r in await history(client, raw(now() - HOUR, now()), plain, unknown)]
    assert codes == [ua.StatusCodes.BadHistoryOperationUnsupported, ua.StatusCodes.BadNodeIdUnknown]
    (both,) = await history(client, raw(None, None), speed)
    assert both.StatusCode.value == ua.StatusCodes.BadInvalidTimestampArgument
    (end_only,) = await history(client, raw(None, now()), speed)
    assert end_only.StatusCode.value == ua.StatusCodes.BadHistoryOperationInvalid
    (forged,) = await history(client, raw(now() - HOUR, now()), speed, cp=b"\x00" * 28)
    assert forged.StatusCode.value == ua.StatusCodes.BadContinuationPointInvalid
    await set_speed(client, ns, 42.0)
    assert app.history is not None
    await app.history.store.flush()
    at_time = ua.ReadAtTimeDetails()
    at_time.ReqTimes = [now()]
    (r,) = await history(client, at_time, speed)  # the speed held now: the value kept last, Interpolated
    assert r.StatusCode.value == ua.StatusCodes.Good
    ((dv,),) = [r.HistoryData.DataValues]
    assert dv.SourceTimestamp == at_time.ReqTimes[0] and dv.StatusCode.value == 0x402
    assert dv.Value.Value == pytest.approx(42.0)
    annotations = ua.ReadAnnotationDataDetails(ReqTimes=[now()])
    (r,) = await history(client, annotations, speed)
    assert r.StatusCode.value == ua.StatusCodes.BadHistoryOperationUnsupported
    modified = raw(now() - HOUR, now())
    modified.IsReadModified = True
    (r,) = await history(client, modified, speed)
    assert r.StatusCode.value == ua.StatusCodes.BadHistoryOperationUnsupported
    (empty,) = await history(client, raw(now() - 10 * HOUR, now() - 9 * HOUR), speed)
    assert empty.StatusCode.value == ua.StatusCodes.GoodNoData and not empty.HistoryData.DataValues
    # events from a node that keeps none
    ev = ua.ReadEventDetails(StartTime=now() - HOUR, EndTime=now() + HOUR)
    ev.Filter = ua.EventFilter(SelectClauses=[ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("Message")])])
    (r,) = await history(client, ev, speed)
    assert r.StatusCode.value == ua.StatusCodes.BadHistoryOperationUnsupported


async def test_continuation_points_over_100000_values_sharing_timestamps(app: UacellServer, client: Client) -> None:
    """100,000 values, 1,000 to each timestamp, read 7,777 at a time: none repeated, none skipped."""
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(f"{F}.Status.CurMachSpeed", ns)
    assert app.history is not None
    store = app.history.store
    from asyncua.ua.ua_binary import variant_to_binary

    base = now() - 2 * HOUR
    key = app.history.values[speed]
    for i in range(100_000):
        t = to_micros(base + timedelta(seconds=i // 1000))
        store.record(key, t, VALUE, 0, "", variant_to_binary(ua.Variant(float(i), ua.VariantType.Double)))
    await store.flush()
    got = await read_all(client, speed, 7_777, base, base + HOUR)
    assert [dv.Value.Value for dv in got] == [float(i) for i in range(100_000)]
    # the server's own bound (MaxReturnDataValues) pages too
    got = await read_all(client, speed, 0, base, base + timedelta(seconds=30))
    assert len(got) == 30_000


async def test_events_with_a_filter(app: UacellServer, client: Client) -> None:
    ns = await client.get_namespace_index(CELL)
    t0 = now()
    unit = client.get_node(ua.NodeId(f"{F}.BaseStateMachine.MachineState", ns))
    await unit.call_method(ua.NodeId(f"{F}.BaseStateMachine.MachineState.Reset", ns))
    names = ["EventType", "Message", "SourceNode", "Time"]
    select = [ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName(n)]) for n in names]
    select.append(ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("ToState")]))
    where = ua.ContentFilter()
    of_type = ua.ContentFilterElement(
        FilterOperator=ua.FilterOperator.OfType,
        FilterOperands=[ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.TransitionEventType)))],
    )
    where.Elements = [of_type]
    details = ua.ReadEventDetails(StartTime=t0 - HOUR, EndTime=now() + HOUR)
    details.Filter = ua.EventFilter(SelectClauses=select, WhereClause=where)
    assert app.history is not None

    async def transitions() -> list[tuple[str, str]]:
        await app.history.store.flush()  # type: ignore[union-attr]
        (res,) = await history(client, details, ua.NodeId(ua.ObjectIds.Server))
        assert res.StatusCode.is_good()
        return [(f.EventFields[2].Value.Identifier, f.EventFields[4].Value.Text) for f in res.HistoryData.Events]

    want = [
        (f"{F}.BaseStateMachine.MachineState", "Running"),
        (f"{F}.BaseStateMachine.MachineState.ExecuteState", "Idle"),
    ]
    got: list[tuple[str, str]] = []

    async def arrived() -> bool:
        nonlocal got
        got = await transitions()
        return all(w in got for w in want)

    await until(arrived, True)
    assert all(w in got for w in want), got
    # the machine itself keeps its own events too; the audit events name the transitions' callers
    details.Filter.WhereClause.Elements[0].FilterOperands = [
        ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.AuditUpdateStateEventType)))
    ]
    (res,) = await history(client, details, ua.NodeId(f"{F}.BaseStateMachine.MachineState", ns))
    assert res.StatusCode.is_good()
    types = {f.EventFields[0].Value for f in res.HistoryData.Events}
    assert types == {ua.NodeId(ua.ObjectIds.AuditUpdateStateEventType)}
    # a page of one event at a time ends
    details.NumValuesPerNode = 1
    details.Filter.WhereClause = ua.ContentFilter()
    seen, cp = [], None
    while True:
        (res,) = await history(client, details, ua.NodeId(f"{F}.BaseStateMachine.MachineState", ns), cp=cp)
        seen += res.HistoryData.Events
        cp = res.ContinuationPoint
        if not cp:
            break
    assert len(seen) >= 2


async def test_a_restart_keeps_history(tmp_path: Path) -> None:
    config = fast_config(tmp_path / "data")
    app = await start_app(config)
    try:
        async with Client(app.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index(CELL)
            await set_speed(client, ns, 42.0)
    finally:
        await app.stop()
    config.server.port = 0
    app = await start_app(fast_config(tmp_path / "data"))
    try:
        async with Client(app.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index(CELL)
            node = ua.NodeId(f"{F}.Status.MachSpeed", ns)
            (res,) = await history(client, raw(now() - HOUR, now() + HOUR), node)
            values = [dv.Value.Value for dv in res.HistoryData.DataValues]
            assert 42.0 in values
    finally:
        await app.stop()


async def test_history_read_follows_the_callers_role(app: UacellServer, client: Client) -> None:
    """The service asks the role table with the calling session's role (anonymous on loopback: operator)."""
    from uacell.core.roles import ACTION_ROLES, Role

    assert ACTION_ROLES["history_read"] == Role.OBSERVER  # like Read
    assert app.history is not None
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(f"{F}.Status.MachSpeed", ns)
    asked: list[str] = []
    default = app.history.allows

    def only_admin(role: str) -> bool:
        asked.append(role)
        return role == "admin"

    app.history.allows = only_admin
    try:
        (res,) = await history(client, raw(now() - HOUR, now() + HOUR), speed)
    finally:
        app.history.allows = default
    assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    assert asked == ["operator"]
    (res,) = await history(client, raw(now() - HOUR, now() + HOUR), speed)
    assert res.StatusCode.is_good()


async def test_alarm_events_are_kept_with_the_server_object(app: UacellServer) -> None:
    """SimulateAlarm (engineer and above) raises EmergencyStop: its AlarmConditionType events are in the
    Server object's history, found with an OfType filter."""
    import dataclasses

    from helpers import raw_call

    from uacell.core.roles import Role

    manager = app.server.iserver.user_manager
    policy = manager.policy
    manager.policy = dataclasses.replace(policy, anonymous_role=Role.ENGINEER)
    t0 = now()
    try:
        async with Client(app.endpoint, timeout=30) as engineer:
            ns = await engineer.get_namespace_index(CELL)
            ctrl = "Robot1.Controllers.Controller1"
            simulate = ua.NodeId(ctrl, ns), ua.NodeId(f"{ctrl}.SimulateAlarm", ns)
            name = ua.Variant("EmergencyStop", ua.VariantType.String)
            res = await raw_call(engineer, *simulate, name, ua.Variant(True, ua.VariantType.Boolean))
            assert res.StatusCode.is_good(), res.StatusCode
            assert app.history is not None
            select = [
                ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName(n)])
                for n in ("EventType", "SourceName", "ConditionName")
            ]
            select.append(
                ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("ActiveState"), ua.QualifiedName("Id")])
            )
            where = ua.ContentFilter()
            where.Elements = [
                ua.ContentFilterElement(
                    FilterOperator=ua.FilterOperator.OfType,
                    FilterOperands=[ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.AlarmConditionType)))],
                )
            ]
            details = ua.ReadEventDetails(StartTime=t0 - HOUR, EndTime=now() + HOUR)
            details.Filter = ua.EventFilter(SelectClauses=select, WhereClause=where)
            alarms: list[Any] = []
            for _ in range(100):
                await app.history.store.flush()
                (res,) = await history(engineer, details, ua.NodeId(ua.ObjectIds.Server))
                assert res.StatusCode.is_good()
                alarms = res.HistoryData.Events
                if alarms:
                    break
            assert alarms, "no alarm event kept"
            fields = [[v.Value for v in f.EventFields] for f in alarms]
            assert all(
                f[:3] == [ua.NodeId(ua.ObjectIds.AlarmConditionType), "Controller1", "EmergencyStop"] for f in fields
            )
            assert any(f[3] is True for f in fields), fields  # raised
            await raw_call(engineer, *simulate, name, ua.Variant(False, ua.VariantType.Boolean))
    finally:
        manager.policy = policy


async def test_processed_read_codes(app: UacellServer, client: Client) -> None:
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(f"{F}.Status.MachSpeed", ns)

    def processed(*aggregates: int, start: datetime | None = None) -> ua.ReadProcessedDetails:
        d = ua.ReadProcessedDetails()
        d.EndTime = now()
        d.StartTime = start or d.EndTime - HOUR  # six intervals of ten minutes
        d.ProcessingInterval = 600_000.0
        d.AggregateType = [ua.NodeId(a) for a in aggregates]
        return d

    ids = ua.ObjectIds
    assert app.history is not None
    await app.history.store.flush()  # HistoryRead sees what is committed (at most flush_interval late)
    (good,) = await history(client, processed(ids.AggregateFunction_TimeAverage), speed)
    assert good.StatusCode.is_good() and len(good.HistoryData.DataValues) == 6
    last = good.HistoryData.DataValues[-1]
    assert last.Value.Value == pytest.approx(await client.get_node(speed).read_value())  # the value held since start
    (two,) = await history(client, processed(ids.AggregateFunction_Average, ids.AggregateFunction_Count), speed)
    assert two.StatusCode.value == ua.StatusCodes.BadAggregateListMismatch
    (other,) = await history(client, processed(ids.AggregateFunction_Range), speed)
    assert other.StatusCode.value == ua.StatusCodes.BadAggregateNotSupported
    (reverse,) = await history(client, processed(ids.AggregateFunction_Average, start=now() + HOUR), speed)
    assert reverse.StatusCode.value == ua.StatusCodes.BadHistoryOperationUnsupported
