"""Read, Write, Browse, BrowseNext and TranslateBrowsePathsToNodeIds as OPC 10000-4 says (decision 81),
through a server and asyncua clients over TCP.

Written from the standard's text: 5.9.2 (Browse: RequestedMaxReferencesPerNode and continuation points,
Bad_NodeIdUnknown, Bad_ReferenceTypeIdInvalid, Bad_BrowseDirectionInvalid, Bad_ViewIdUnknown,
ResultMask, NodeClassMask, Bad_NoContinuationPoints), 5.9.3 (BrowseNext: releasing,
Bad_ContinuationPointInvalid), 5.9.4 (TranslateBrowsePathsToNodeIds: an empty TargetName only in the last
element), 5.11.2 (Read: Bad_MaxAgeInvalid, Bad_TimestampsToReturnInvalid), 5.11.4 (Write:
Bad_WriteNotSupported for an IndexRange that cannot be written and for a timestamp or status the server
does not write, Bad_NotWritable, Bad_TypeMismatch), 7.27 (NumericRange: Bad_IndexRangeInvalid for the
syntax, Bad_IndexRangeNoData for a lower bound beyond the value, partial results beyond the upper one),
7.38 (Bad_NothingToDo for a request of no operations). asyncua answered most of these otherwise.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import robot_cell, wait_until
from test_subscription_sessions import PASSWORD, client_of

from uacell.robotics.equipment import ExecutionMode
from uacell.server import UacellServer
from uacell.ua import views

SC = ua.StatusCodes
_NS_ARRAY = ua.NodeId(ua.ObjectIds.Server_NamespaceArray)
_OBJECTS = ua.NodeId(ua.ObjectIds.ObjectsFolder)
_SERVER = ua.NodeId(ua.ObjectIds.Server)
_HIERARCHICAL = ua.NodeId(ua.ObjectIds.HierarchicalReferences)
pytestmark = pytest.mark.asyncio(loop_scope="module")
_MODE = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.ParameterSet.ExecutionMode"


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[UacellServer]:
    server = await start_app(fast_config(tmp_path_factory.mktemp("services") / "data"))
    server.users.add("eng", "engineer", PASSWORD)
    # a variable asyncua stores client writes of (no binding routes it), Double, writable
    folder = server.server.get_node(_OBJECTS)
    ns = await server.server.get_namespace_index("urn:uacell:cell")
    variable = await folder.add_variable(ua.NodeId("Test.Setpoint", ns), "Setpoint", 1.5, ua.VariantType.Double)
    await variable.set_writable()
    await folder.add_variable(ua.NodeId("Test.Levels", ns), "Levels", [1.0, 2.0, 3.0], ua.VariantType.Double)
    try:
        yield server
    finally:
        await server.stop()


@pytest_asyncio.fixture(loop_scope="module")
async def client(app: UacellServer) -> AsyncIterator[Client]:
    async with client_of(app) as c:
        yield c


@pytest_asyncio.fixture(loop_scope="module")
async def engineer(app: UacellServer) -> AsyncIterator[Client]:
    async with client_of(app, "eng") as c:
        yield c


async def _ns(c: Client) -> int:
    return int(await c.get_namespace_index("urn:uacell:cell"))


def _code(exc: pytest.ExceptionInfo[ua.UaStatusCodeError]) -> int:
    return int(exc.value.code)


# --- Read ------------------------------------------------------------------------------------------


async def _read(c: Client, *items: tuple[ua.NodeId, str], **params: Any) -> list[ua.DataValue]:
    request = ua.ReadParameters(**params)
    request.NodesToRead = [ua.ReadValueId(NodeId=n, AttributeId=ua.AttributeIds.Value, IndexRange=r) for n, r in items]
    return list(await c.uaclient.read(request))


async def test_read_applies_the_index_range(client: Client) -> None:
    (whole,) = await _read(client, (_NS_ARRAY, ""))
    namespaces = whole.Value.Value
    assert len(namespaces) > 3
    one, two, partial, strings = await _read(
        client, (_NS_ARRAY, "1"), (_NS_ARRAY, "0:1"), (_NS_ARRAY, f"2:{len(namespaces) + 5}"), (_NS_ARRAY, "0:1,0:3")
    )
    assert one.StatusCode.is_good() and one.Value.Value == namespaces[1:2]
    assert two.Value.Value == namespaces[:2]
    assert partial.Value.Value == namespaces[2:]  # the upper bound beyond the array: what there is
    assert strings.Value.Value == [name[:4] for name in namespaces[:2]]  # a substring of each element
    assert strings.Value.VariantType == ua.VariantType.String
    assert one.SourceTimestamp == whole.SourceTimestamp  # the value's own timestamps kept
    (again,) = await _read(client, (_NS_ARRAY, ""))
    assert again.Value.Value == namespaces  # the stored value is not cut


async def test_read_refuses_an_index_range_it_cannot_answer(client: Client) -> None:
    ns = await _ns(client)
    speed = ua.NodeId("Filler1.Status.MachSpeed", ns)
    product = ua.NodeId(ua.ObjectIds.Server_ServerStatus_BuildInfo_ProductName)
    results = await _read(
        client,
        (_NS_ARRAY, "5:2"),  # the lower first: invalid syntax
        (_NS_ARRAY, "3:3"),
        (_NS_ARRAY, " 1"),
        (_NS_ARRAY, "1:x"),
        (_NS_ARRAY, "50:60"),  # the lower bound beyond the array
        (speed, "0"),  # a scalar number has no elements
        (product, "0:2"),  # a String's characters
        (product, "0,0"),  # more dimensions than a String has
    )
    codes = [r.StatusCode.value for r in results]
    assert codes[:4] == [SC.BadIndexRangeInvalid] * 4
    assert codes[4:6] == [SC.BadIndexRangeNoData] * 2
    assert results[6].StatusCode.is_good()
    (name,) = await _read(client, (product, ""))
    assert results[6].Value.Value == name.Value.Value[:3]
    assert codes[7] == SC.BadIndexRangeNoData


async def test_read_returns_the_timestamps_asked_for(client: Client) -> None:
    """5.11.2.2, 7.40: timestampsToReturn names the timestamps of each Value returned; other attributes
    are left as they are. asyncua returned both whatever was asked."""
    ns = await _ns(client)
    speed = ua.NodeId("Filler1.Status.MachSpeed", ns)
    stamps = {}
    for asked in (ua.TimestampsToReturn.Source, ua.TimestampsToReturn.Server, ua.TimestampsToReturn.Both,
                  ua.TimestampsToReturn.Neither):  # fmt: skip
        (dv,) = await _read(client, (speed, ""), TimestampsToReturn=asked)
        stamps[asked] = (dv.SourceTimestamp is not None, dv.ServerTimestamp is not None)
        assert dv.Value.Value is not None
    assert stamps == {
        ua.TimestampsToReturn.Source: (True, False),
        ua.TimestampsToReturn.Server: (False, True),
        ua.TimestampsToReturn.Both: (True, True),
        ua.TimestampsToReturn.Neither: (False, False),
    }
    (both,) = await _read(client, (speed, ""), TimestampsToReturn=ua.TimestampsToReturn.Both)
    assert both.SourceTimestamp is not None  # the stored value keeps its timestamps


async def test_read_request_checks(client: Client) -> None:
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _read(client)
    assert _code(refused) == SC.BadNothingToDo
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _read(client, (_NS_ARRAY, ""), MaxAge=-1)
    assert _code(refused) == SC.BadMaxAgeInvalid
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _read(client, (_NS_ARRAY, ""), TimestampsToReturn=ua.TimestampsToReturn.Invalid)
    assert _code(refused) == SC.BadTimestampsToReturnInvalid


async def _unread_subscription(c: Client, interval: int) -> int:
    """A subscription whose notifications are not looked at (its id): for the services' answers alone."""
    created = await c.uaclient.create_subscription(
        ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=interval, RequestedLifetimeCount=300, RequestedMaxKeepAliveCount=10,
            PublishingEnabled=True,
        ),
        lambda *_: None,
    )  # fmt: skip
    assert created.RevisedPublishingInterval == interval
    return int(created.SubscriptionId)


class Reported:
    """A subscription's handler that keeps (client handle, value, status code) of each data change."""

    def __init__(self) -> None:
        self.seen: list[tuple[int, Any, int]] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        item = data.monitored_item
        self.seen.append((item.ClientHandle, val, item.Value.StatusCode.value))

    def of(self, handle: int) -> list[tuple[Any, int]]:
        return [(value, code) for h, value, code in self.seen if h == handle]


async def test_a_monitored_item_reports_the_part_its_index_range_names(app: UacellServer, client: Client) -> None:
    """OPC 10000-4 5.13.2: an item with an IndexRange reports that part of the value, and only when it
    changes; a range with no data yet is reported as Bad_IndexRangeNoData; one that does not parse is
    refused when the item is created. asyncua ignored the range and reported the whole array."""
    ns = await _ns(client)
    levels = ua.NodeId("Test.Levels", ns)
    handler = Reported()
    subscription = await client.create_subscription(0, handler)

    def request(rng: str, handle: int) -> ua.MonitoredItemCreateRequest:
        return ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=levels, AttributeId=ua.AttributeIds.Value, IndexRange=rng),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=handle, QueueSize=10, DiscardOldest=True),
        )

    made = await subscription.create_monitored_items([request("1", 1), request("5:6", 2), request("2:1", 3)])
    assert isinstance(made[0], int) and isinstance(made[1], int)
    assert made[2] == ua.StatusCode(SC.BadIndexRangeInvalid)
    await wait_until(lambda: bool(handler.of(1)) and bool(handler.of(2)))
    assert handler.of(1) == [([2.0], SC.Good)]
    assert handler.of(2) == [(None, SC.BadIndexRangeNoData)]
    node = app.server.get_node(levels)
    await node.write_value(ua.Variant([9.0, 2.0, 3.0], ua.VariantType.Double))  # element 0 only
    await node.write_value(ua.Variant([9.0, 7.0, 3.0], ua.VariantType.Double))
    await wait_until(lambda: len(handler.of(1)) == 2)
    assert handler.of(1) == [([2.0], SC.Good), ([7.0], SC.Good)]
    assert handler.of(2) == [(None, SC.BadIndexRangeNoData)]  # still nothing there: nothing new
    await subscription.delete()


async def test_queue_sizes_are_revised_by_the_standard(app: UacellServer, client: Client) -> None:
    """OPC 10000-4 7.21: a data item asking for a queue of 0 or 1 gets 1, the latest value only; an event
    item's 0 is the server's default; a larger request is capped, on ModifyMonitoredItems too. asyncua
    gave a data item's 0 its largest queue, so a client that asked for the latest value was sent every
    change, and took any size a modification asked for."""
    ns = await _ns(client)
    setpoint = ua.NodeId("Test.Setpoint", ns)
    sid = await _unread_subscription(client, 500)

    def request(handle: int, size: int, flt: Any = None) -> ua.MonitoredItemCreateRequest:
        attribute = ua.AttributeIds.EventNotifier if flt is not None else ua.AttributeIds.Value
        return ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=setpoint if flt is None else _SERVER, AttributeId=attribute),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=handle, QueueSize=size, Filter=flt),
        )

    largest = app.server.iserver.max_monitored_item_queue_size
    items = [request(31, 0), request(32, 5), request(33, 10**9), request(34, 0, _event_filter())]
    made = await client.uaclient.create_monitored_items(
        ua.CreateMonitoredItemsParameters(SubscriptionId=sid, TimestampsToReturn=2, ItemsToCreate=items)
    )
    assert [r.RevisedQueueSize for r in made] == [1, 5, largest, largest]
    modify = ua.MonitoredItemModifyRequest(
        MonitoredItemId=made[1].MonitoredItemId,
        RequestedParameters=ua.MonitoringParameters(ClientHandle=32, QueueSize=2**32 - 1),
    )
    (modified,) = await client.uaclient.modify_monitored_items(
        ua.ModifyMonitoredItemsParameters(SubscriptionId=sid, TimestampsToReturn=2, ItemsToModify=[modify])
    )
    assert modified.RevisedQueueSize == largest
    await client.uaclient.delete_subscriptions([sid])


async def test_a_queue_of_one_sends_the_latest_value_of_each_publishing_interval(
    app: UacellServer, client: Client
) -> None:
    """OPC 10000-4 7.21: with a queue of one, the values written while nothing is published reach the
    client as the last of them (publishing is switched off meanwhile, so that no interval ends between
    the writes)."""
    ns = await _ns(client)
    handler = Reported()
    subscription = await client.create_subscription(500, handler)
    node = client.get_node(ua.NodeId("Test.Setpoint", ns))
    await subscription.subscribe_data_change(node, queuesize=1)
    await wait_until(lambda: len(handler.seen) == 1)
    first = handler.seen[0][1]
    server_node = app.server.get_node(node.nodeid)
    await subscription.set_publishing_mode(False)
    for value in (first + 1, first + 2, first + 3):
        await server_node.write_value(ua.Variant(value, ua.VariantType.Double))
    await subscription.set_publishing_mode(True)
    await wait_until(lambda: len(handler.seen) == 2)
    await server_node.write_value(ua.Variant(first + 4, ua.VariantType.Double))
    await wait_until(lambda: len(handler.seen) == 3)
    assert [value for _, value, _ in handler.seen] == [first, first + 3, first + 4]
    await subscription.delete()
    await server_node.write_value(ua.Variant(first, ua.VariantType.Double))


async def test_sampling_intervals_are_revised_by_the_standard(app: UacellServer, client: Client) -> None:
    """OPC 10000-4 5.13.1.2 and 7.21 (decision 86): the revised sampling interval is never less than the
    request (asyncua answered the publishing interval, 100 ms, for every item made), a negative or NaN
    request is the publishing interval (asyncua echoed a modification's -1), 0 stays 0, an event item's
    is 0, and the variable's MinimumSamplingInterval is a floor."""
    ns = await _ns(client)
    setpoint = ua.NodeId("Test.Setpoint", ns)
    floored = await app.server.nodes.objects.add_variable(ua.NodeId("Test.Slow", ns), "Slow", 0.0)
    await floored.write_attribute(
        ua.AttributeIds.MinimumSamplingInterval, ua.DataValue(ua.Variant(500.0, ua.VariantType.Double))
    )
    sid = await _unread_subscription(client, 100)

    def request(handle: int, sampling: float, node: ua.NodeId = setpoint, flt: Any = None) -> Any:
        attribute = ua.AttributeIds.EventNotifier if flt is not None else ua.AttributeIds.Value
        return ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=node, AttributeId=attribute),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(
                ClientHandle=handle, SamplingInterval=sampling, QueueSize=1, Filter=flt
            ),
        )

    items = [
        request(41, 250.0),
        request(42, -1.0),
        request(43, float("nan")),
        request(44, 0.0),
        request(45, 10**12),
        request(46, 500.0, _SERVER, _event_filter()),
        request(47, 100.0, floored.nodeid),
    ]
    made = await client.uaclient.create_monitored_items(
        ua.CreateMonitoredItemsParameters(SubscriptionId=sid, TimestampsToReturn=2, ItemsToCreate=items)
    )
    assert [r.StatusCode.name for r in made] == ["Good"] * 7
    assert [r.RevisedSamplingInterval for r in made] == [250.0, 100.0, 100.0, 0.0, 3_600_000.0, 0.0, 500.0]
    modify = [
        ua.MonitoredItemModifyRequest(
            MonitoredItemId=made[i].MonitoredItemId,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=41 + i, SamplingInterval=sampling, QueueSize=1),
        )
        for i, sampling in ((0, -1.0), (3, 1000.0))
    ]
    modified = await client.uaclient.modify_monitored_items(
        ua.ModifyMonitoredItemsParameters(SubscriptionId=sid, TimestampsToReturn=2, ItemsToModify=modify)
    )
    assert [r.RevisedSamplingInterval for r in modified] == [100.0, 1000.0]
    await client.uaclient.delete_subscriptions([sid])


async def test_an_item_samples_at_its_interval_and_takes_the_latest_value(app: UacellServer, client: Client) -> None:
    """OPC 10000-4 5.13.1.2: "the time between values returned to the Client shall be greater or equal
    to the sampling interval". Three values written back to back reach an item sampling every 1.5 s as
    the last of them, at the next sample, while an item sampling at 0 (every change) gets all three."""
    ns = await _ns(client)
    node = client.get_node(ua.NodeId("Test.Setpoint", ns))
    handler = Reported()
    subscription = await client.create_subscription(50, handler)
    loop = asyncio.get_running_loop()
    await subscription.subscribe_data_change(node, queuesize=10, sampling_interval=0.0)
    made = loop.time()
    await subscription.subscribe_data_change(node, queuesize=10, sampling_interval=1500.0)
    await wait_until(lambda: len({h for h, _, _ in handler.seen}) == 2)
    every, sampled = sorted({h for h, _, _ in handler.seen})  # the handles, in the order the items were made
    first = handler.of(sampled)[0][0]
    server_node = app.server.get_node(node.nodeid)
    for value in (first + 1, first + 2, first + 3):
        await server_node.write_value(ua.Variant(value, ua.VariantType.Double))
    await wait_until(lambda: len(handler.of(sampled)) == 2, timeout=20)
    arrived = loop.time()
    assert [v for v, _ in handler.of(sampled)] == [first, first + 3]  # the latest at the next sample
    assert arrived - made >= 1.5  # not before its next sample
    await wait_until(lambda: len(handler.of(every)) == 4)
    assert [v for v, _ in handler.of(every)] == [first, first + 1, first + 2, first + 3]
    await subscription.delete()
    await server_node.write_value(ua.Variant(first, ua.VariantType.Double))


class Asking:
    """asyncua's client as a Subscription uses it, its CreateMonitoredItems asking for ``stamps``
    (asyncua's Subscription always asks for both)."""

    def __init__(self, uaclient: Any, stamps: ua.TimestampsToReturn) -> None:
        self.uaclient, self.stamps = uaclient, stamps

    async def create_monitored_items(self, params: ua.CreateMonitoredItemsParameters) -> Any:
        params.TimestampsToReturn = self.stamps
        return await self.uaclient.create_monitored_items(params)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.uaclient, name)


class Stamps:
    """A subscription's handler that keeps, by client handle, whether each value came with its source
    and server timestamps."""

    def __init__(self) -> None:
        self.seen: dict[int, list[tuple[Any, bool, bool]]] = {}

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        dv = data.monitored_item.Value
        self.seen.setdefault(data.monitored_item.ClientHandle, []).append(
            (val, dv.SourceTimestamp is not None, dv.ServerTimestamp is not None)
        )


async def test_a_monitored_item_reports_the_timestamps_asked_for(app: UacellServer, client: Client) -> None:
    """5.13.2.2, 5.13.3.2: CreateMonitoredItems' and ModifyMonitoredItems' timestampsToReturn name the
    timestamps of the values the items report, the first one included; an invalid one fails the
    request. asyncua sent both."""
    ns = await _ns(client)
    setpoint = ua.NodeId("Test.Setpoint", ns)
    handler = Stamps()
    subscription = await client.create_subscription(0, handler)
    uaclient = subscription.server
    made = []
    for handle, stamps in ((11, ua.TimestampsToReturn.Source), (12, ua.TimestampsToReturn.Neither)):
        subscription.server = Asking(uaclient, stamps)
        request = ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=setpoint, AttributeId=ua.AttributeIds.Value),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=handle, QueueSize=10, DiscardOldest=True),
        )
        made += await subscription.create_monitored_items([request])
    subscription.server = uaclient
    await wait_until(lambda: len(handler.seen.get(11, ())) == 1 and len(handler.seen.get(12, ())) == 1)
    node = app.server.get_node(setpoint)
    await node.write_value(ua.Variant(4.25, ua.VariantType.Double))
    await wait_until(lambda: len(handler.seen[11]) == 2 and len(handler.seen[12]) == 2)
    assert [stamps for _, *stamps in handler.seen[11]] == [[True, False], [True, False]]
    assert [stamps for _, *stamps in handler.seen[12]] == [[False, False], [False, False]]
    assert handler.seen[12][1][0] == 4.25
    modify = ua.ModifyMonitoredItemsParameters(
        SubscriptionId=subscription.subscription_id,
        TimestampsToReturn=ua.TimestampsToReturn.Both,
        ItemsToModify=[ua.MonitoredItemModifyRequest(
            MonitoredItemId=made[1], RequestedParameters=ua.MonitoringParameters(ClientHandle=12, QueueSize=10)
        )],
    )  # fmt: skip
    (modified,) = await uaclient.modify_monitored_items(modify)
    assert modified.StatusCode.is_good()
    await node.write_value(ua.Variant(5.5, ua.VariantType.Double))
    await wait_until(lambda: len(handler.seen[12]) == 3)
    assert handler.seen[12][2] == (5.5, True, True)
    invalid = ua.CreateMonitoredItemsParameters(
        SubscriptionId=subscription.subscription_id,
        TimestampsToReturn=ua.TimestampsToReturn.Invalid,
        ItemsToCreate=[request],
    )
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await uaclient.create_monitored_items(invalid)
    assert _code(refused) == SC.BadTimestampsToReturnInvalid
    await subscription.delete()
    await node.write_value(ua.Variant(1.5, ua.VariantType.Double))


class Events:
    """A subscription's handler that keeps each event it is sent."""

    def __init__(self) -> None:
        self.seen: list[Any] = []

    def event_notification(self, event: Any) -> None:
        self.seen.append(event)


def _event_filter(*where: ua.ContentFilterElement) -> ua.EventFilter:
    select = [
        ua.SimpleAttributeOperand(
            TypeDefinitionId=ua.NodeId(ua.ObjectIds.BaseEventType), BrowsePath=[ua.QualifiedName(name, 0)],
            AttributeId=ua.AttributeIds.Value,
        )
        for name in ("EventType", "Message")
    ]  # fmt: skip
    return ua.EventFilter(SelectClauses=select, WhereClause=ua.ContentFilter(Elements=list(where)))


async def test_an_event_items_where_clause_passes_subtypes_and_is_checked_when_made(client: Client) -> None:
    """OPC 10000-4 7.7.3 (decision 82): OfType passes events of the type and of its subtypes, Like matches
    by its pattern; a filter with an operator the server does not evaluate is refused when the item is
    made. asyncua passed nothing to OfType(BaseEventType), dropped every event of a Like, and accepted
    any operator."""
    ns = await _ns(client)
    base = ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.BaseEventType)))
    condition = ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.ConditionType)))
    message = _event_filter().SelectClauses[1]
    filters = {
        "base": _event_filter(ua.ContentFilterElement(FilterOperator=ua.FilterOperator.OfType, FilterOperands=[base])),
        "condition": _event_filter(
            ua.ContentFilterElement(FilterOperator=ua.FilterOperator.OfType, FilterOperands=[condition])
        ),
        "like": _event_filter(
            ua.ContentFilterElement(
                FilterOperator=ua.FilterOperator.Like,
                FilterOperands=[message, ua.LiteralOperand(Value=ua.Variant("%Idle%"))],
            )
        ),
    }
    handlers = {name: Events() for name in filters}
    subscriptions = []
    for name, flt in filters.items():
        subscription = await client.create_subscription(0, handlers[name])
        await subscription.subscribe_events(client.get_node(ua.ObjectIds.Server), evfilter=flt)
        subscriptions.append(subscription)
    machine = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState", ns))
    await machine.call_method(ua.NodeId("Filler1.BaseStateMachine.MachineState.Reset", ns))
    await wait_until(lambda: any("Idle" in str(e.Message) for e in handlers["base"].seen))
    types = {e.EventType for e in handlers["base"].seen}
    assert ua.NodeId(ua.ObjectIds.TransitionEventType) in types  # a subtype of BaseEventType
    assert handlers["condition"].seen == []  # no condition among them
    await wait_until(lambda: bool(handlers["like"].seen))
    assert all("Idle" in str(e.Message) for e in handlers["like"].seen)
    assert len(handlers["like"].seen) < len(handlers["base"].seen)
    unsupported = _event_filter(
        ua.ContentFilterElement(FilterOperator=ua.FilterOperator.BitwiseAnd, FilterOperands=[message, base])
    )
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await subscriptions[0].subscribe_events(client.get_node(ua.ObjectIds.Server), evfilter=unsupported)
    assert _code(refused) == SC.BadMonitoredItemFilterUnsupported
    for subscription in subscriptions:
        await subscription.delete()


async def test_an_event_filters_faults_are_said_per_clause_and_element(client: Client) -> None:
    """OPC 10000-4 7.22.3 and 7.7.2 (decision 87): the EventFilterResult says which select clause and
    which WhereClause element is wrong, and why; asyncua returned no FilterResult, and uacell only the
    item's code. A select clause that cannot be served leaves the item made (its field is null)."""
    sid = await _unread_subscription(client, 500)
    good = _event_filter()
    message = good.SelectClauses[1]
    base = ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.BaseEventType)))
    event_type = ua.NodeId(ua.ObjectIds.BaseEventType)

    def clause(**fields: Any) -> ua.SimpleAttributeOperand:
        values = {"TypeDefinitionId": event_type, "BrowsePath": [ua.QualifiedName("Severity", 0)],
                  "AttributeId": ua.AttributeIds.Value, **fields}  # fmt: skip
        return ua.SimpleAttributeOperand(**values)

    selects = ua.EventFilter(
        SelectClauses=[
            clause(),
            clause(TypeDefinitionId=ua.NodeId(999_999, 0)),
            clause(TypeDefinitionId=ua.NodeId(ua.ObjectIds.Server)),  # an object, not a type
            clause(AttributeId=99),
            clause(IndexRange="x"),
            clause(BrowsePath=[ua.QualifiedName("", 0)]),
        ],
        WhereClause=ua.ContentFilter(Elements=[]),
    )
    element = ua.ContentFilterElement
    filters = [
        good,
        selects,
        _event_filter(element(FilterOperator=ua.FilterOperator.BitwiseAnd, FilterOperands=[message, base])),
        _event_filter(element(FilterOperator=ua.FilterOperator.Equals, FilterOperands=[message])),
        _event_filter(element(FilterOperator=ua.FilterOperator.Not, FilterOperands=[ua.ElementOperand(Index=5)])),
    ]
    items = [
        ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=_SERVER, AttributeId=ua.AttributeIds.EventNotifier),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=60 + i, QueueSize=10, Filter=flt),
        )
        for i, flt in enumerate(filters)
    ]
    made = await client.uaclient.create_monitored_items(
        ua.CreateMonitoredItemsParameters(SubscriptionId=sid, TimestampsToReturn=2, ItemsToCreate=items)
    )
    names = [r.StatusCode.name for r in made]
    assert names == ["Good", "Good", "BadMonitoredItemFilterUnsupported"] + ["BadMonitoredItemFilterInvalid"] * 2
    # a variable has no EventNotifier attribute: no event item on it (asyncua: Bad_MonitoredItemFilterInvalid)
    on_variable = dataclasses.replace(items[0], ItemToMonitor=ua.ReadValueId(NodeId=_NS_ARRAY, AttributeId=12))
    (refused,) = await client.uaclient.create_monitored_items(
        ua.CreateMonitoredItemsParameters(SubscriptionId=sid, TimestampsToReturn=2, ItemsToCreate=[on_variable])
    )
    assert refused.StatusCode.name == "BadAttributeIdInvalid"
    omitted = made[0].FilterResult  # "may be omitted if no errors occurred": a null ExtensionObject
    assert isinstance(omitted, ua.ExtensionObject) and omitted.Body is None
    assert [c.name for c in made[1].FilterResult.SelectClauseResults] == [
        "Good", "BadNodeIdUnknown", "BadTypeDefinitionInvalid", "BadAttributeIdInvalid", "BadIndexRangeInvalid",
        "BadBrowseNameInvalid",
    ]  # fmt: skip

    def elements(result: ua.MonitoredItemCreateResult) -> list[tuple[str, list[str]]]:
        found = result.FilterResult.WhereClauseResult.ElementResults
        return [(e.StatusCode.name, [c.name for c in e.OperandStatusCodes]) for e in found]

    assert elements(made[2]) == [("BadFilterOperatorUnsupported", [])]
    assert elements(made[3]) == [("BadFilterOperandCountMismatch", [])]
    assert elements(made[4]) == [("BadFilterOperandInvalid", ["BadFilterOperandInvalid"])]
    await client.uaclient.delete_subscriptions([sid])


# --- Write -----------------------------------------------------------------------------------------


def _item(node: ua.NodeId, value: ua.DataValue, attribute: int = ua.AttributeIds.Value, rng: str = "") -> ua.WriteValue:
    return ua.WriteValue(NodeId=node, AttributeId=attribute, Value=value, IndexRange=rng)


async def _write(c: Client, *items: ua.WriteValue) -> list[int]:
    return [s.value for s in await c.uaclient.write(ua.WriteParameters(NodesToWrite=list(items)))]


def _int32(value: int) -> ua.DataValue:
    return ua.DataValue(ua.Variant(value, ua.VariantType.Int32))


async def test_a_routed_write_with_an_index_range_reaches_neither_node_nor_model(
    app: UacellServer, engineer: Client
) -> None:
    """An IndexRange went past the ExecutionMode's behaviour to asyncua, which stored the value whole."""
    ns = await _ns(engineer)
    mode = ua.NodeId(_MODE, ns)
    task = robot_cell(app).tasks["TaskControl1"]
    before = await engineer.get_node(mode).read_value()
    step = int(ExecutionMode.STEP)
    assert before != step
    codes = await _write(engineer, _item(mode, _int32(step), rng="0"), _item(mode, _int32(step), rng="x"))
    assert codes == [SC.BadWriteNotSupported, SC.BadIndexRangeInvalid]
    assert await engineer.get_node(mode).read_value() == before
    assert int(task.execution_mode) == before
    # the same value without a range is the behaviour's
    assert await _write(engineer, _item(mode, _int32(step))) == [SC.Good]
    assert await engineer.get_node(mode).read_value() == step
    assert task.execution_mode is ExecutionMode.STEP
    assert await _write(engineer, _item(mode, _int32(int(before)))) == [SC.Good]


async def test_write_refuses_what_it_does_not_write(app: UacellServer, engineer: Client) -> None:
    ns = await _ns(engineer)
    setpoint = ua.NodeId("Test.Setpoint", ns)
    speed = ua.NodeId("Filler1.Status.MachSpeed", ns)
    double = ua.Variant(2.5, ua.VariantType.Double)
    now = datetime.now(UTC)
    codes = await _write(
        engineer,
        _item(setpoint, ua.DataValue(double, ServerTimestamp=now)),
        _item(setpoint, ua.DataValue(double, StatusCode=ua.StatusCode(SC.UncertainLastUsableValue))),
        _item(setpoint, ua.DataValue(double), attribute=99),
        _item(setpoint, ua.DataValue(ua.Variant("fast"))),
        _item(setpoint, ua.DataValue(ua.Variant([1.0, 2.0], ua.VariantType.Double))),
        _item(setpoint, ua.DataValue(ua.Variant(ua.LocalizedText("x"))), attribute=ua.AttributeIds.DisplayName),
        _item(speed, ua.DataValue(ua.Variant(5.0, ua.VariantType.Float))),
        _item(ua.NodeId("Test.Nothing", ns), ua.DataValue(double)),
        _item(setpoint, ua.DataValue(ua.Variant(3.0, ua.VariantType.Double), SourceTimestamp=now)),
    )
    assert codes == [
        SC.BadWriteNotSupported,  # the server stamps values
        SC.BadWriteNotSupported,  # and clients do not set their quality
        SC.BadAttributeIdInvalid,
        SC.BadTypeMismatch,
        SC.BadTypeMismatch,  # an array for a scalar
        SC.BadNotWritable,
        SC.BadNotWritable,  # AccessLevel without CurrentWrite
        SC.BadNodeIdUnknown,
        SC.Good,
    ]
    dv = await engineer.get_node(setpoint).read_data_value()
    assert dv.Value.Value == 3.0
    assert dv.SourceTimestamp == now.replace(tzinfo=None) or dv.SourceTimestamp == now
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _write(engineer)
    assert _code(refused) == SC.BadNothingToDo


async def test_the_role_is_checked_before_the_node(client: Client) -> None:
    """The anonymous operator may not write a variable asyncua stores: Bad_UserAccessDenied, whatever the node."""
    ns = await _ns(client)
    codes = await _write(
        client,
        _item(ua.NodeId("Test.Setpoint", ns), ua.DataValue(ua.Variant(9.0, ua.VariantType.Double))),
        _item(ua.NodeId("Filler1.Status.MachSpeed", ns), ua.DataValue(ua.Variant(5.0, ua.VariantType.Float))),
    )
    assert codes == [SC.BadUserAccessDenied] * 2


# --- Browse and BrowseNext -------------------------------------------------------------------------


def _description(node: ua.NodeId, **fields: Any) -> ua.BrowseDescription:
    fields.setdefault("ReferenceTypeId", _HIERARCHICAL)
    fields.setdefault("IncludeSubtypes", True)
    fields.setdefault("ResultMask", ua.BrowseResultMask.All)
    return ua.BrowseDescription(NodeId=node, BrowseDirection=ua.BrowseDirection.Forward, **fields)


async def _browse(c: Client, *descriptions: ua.BrowseDescription, per_node: int = 0, view: Any = None) -> list[Any]:
    params = ua.BrowseParameters(NodesToBrowse=list(descriptions), RequestedMaxReferencesPerNode=per_node)
    if view is not None:
        params.View.ViewId = view
    return list(await c.uaclient.browse(params))


async def _next(c: Client, points: list[bytes], release: bool = False) -> list[Any]:
    params = ua.BrowseNextParameters(ContinuationPoints=points, ReleaseContinuationPoints=release)
    return list(await c.uaclient.browse_next(params))


def _ids(references: list[ua.ReferenceDescription]) -> list[str]:
    return [r.NodeId.to_string() for r in references]


async def test_browse_pages_by_requested_max_references(client: Client) -> None:
    (whole,) = await _browse(client, _description(_SERVER))
    assert len(whole.References) > 5 and not whole.ContinuationPoint
    (page,) = await _browse(client, _description(_SERVER), per_node=2)
    seen = _ids(page.References)
    assert len(seen) == 2 and page.ContinuationPoint
    point = page.ContinuationPoint
    while point:
        (page,) = await _next(client, [point])
        assert page.StatusCode.is_good() and len(page.References) <= 2
        seen += _ids(page.References)
        point = page.ContinuationPoint
    assert seen == _ids(whole.References)  # the same references, in the same order
    (used,) = await _next(client, [b"\x01" + bytes(7)])
    assert used.StatusCode.value == SC.BadContinuationPointInvalid


async def test_continuation_points_are_released_and_belong_to_their_session(app: UacellServer, client: Client) -> None:
    (page,) = await _browse(client, _description(_SERVER), per_node=1)
    async with client_of(app) as other:
        (theirs,) = await _next(other, [page.ContinuationPoint])
        assert theirs.StatusCode.value == SC.BadContinuationPointInvalid
    (released,) = await _next(client, [page.ContinuationPoint], release=True)
    assert released.StatusCode.is_good() and not released.References
    (after,) = await _next(client, [page.ContinuationPoint])
    assert after.StatusCode.value == SC.BadContinuationPointInvalid
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _next(client, [])
    assert _code(refused) == SC.BadNothingToDo


async def test_a_session_holds_at_most_max_browse_continuation_points(app: UacellServer) -> None:
    limit = views.MAX_BROWSE_CONTINUATION_POINTS
    async with client_of(app) as c:
        advertised = c.get_node(ua.NodeId(ua.ObjectIds.Server_ServerCapabilities_MaxBrowseContinuationPoints))
        assert await advertised.read_value() == limit
        pages = await _browse(c, *[_description(_SERVER)] * (limit + 1), per_node=1)
        assert all(p.ContinuationPoint for p in pages[:limit])
        assert pages[limit].StatusCode.value == SC.BadNoContinuationPoints and not pages[limit].References
        await _next(c, [pages[0].ContinuationPoint], release=True)
        (again,) = await _browse(c, _description(_SERVER), per_node=1)
        assert again.StatusCode.is_good() and again.ContinuationPoint


async def test_browse_answers_each_description(client: Client) -> None:
    results = await _browse(
        client,
        _description(ua.NodeId("Nothing", 1)),
        _description(_SERVER, ReferenceTypeId=_OBJECTS),  # not a ReferenceType
        ua.BrowseDescription(NodeId=_SERVER, BrowseDirection=ua.BrowseDirection.Invalid, ResultMask=63),
        _description(_SERVER, ResultMask=ua.BrowseResultMask.BrowseName, NodeClassMask=ua.NodeClass.Variable),
    )
    codes = [r.StatusCode.value for r in results]
    assert codes == [SC.BadNodeIdUnknown, SC.BadReferenceTypeIdInvalid, SC.BadBrowseDirectionInvalid, SC.Good]
    masked = results[3].References
    assert masked and {r.NodeClass for r in masked} == {ua.NodeClass.Unspecified}  # not asked for
    assert {r.BrowseName.Name for r in masked} >= {"ServerArray", "NamespaceArray"}  # only variables, named
    assert all(r.ReferenceTypeId.is_null() and not r.DisplayName.Text for r in masked)
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _browse(client, _description(_SERVER), view=ua.NodeId(4711, 0))
    assert _code(refused) == SC.BadViewIdUnknown
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await _browse(client)
    assert _code(refused) == SC.BadNothingToDo


# --- TranslateBrowsePathsToNodeIds -----------------------------------------------------------------


def _path(start: ua.NodeId, *names: str, reference: int = ua.ObjectIds.HierarchicalReferences) -> ua.BrowsePath:
    elements = [
        ua.RelativePathElement(
            ReferenceTypeId=ua.NodeId(reference), IsInverse=False, IncludeSubtypes=True, TargetName=ua.QualifiedName(n)
        )
        for n in names
    ]
    return ua.BrowsePath(StartingNode=start, RelativePath=ua.RelativePath(Elements=elements))


async def test_translate_browse_paths(client: Client) -> None:
    results = await client.uaclient.translate_browsepaths_to_nodeids([
        _path(_OBJECTS, "Server", "ServerStatus"),
        _path(_OBJECTS),  # no elements
        _path(_OBJECTS, "", "ServerStatus"),  # an empty name before the last element
        _path(_SERVER, "ServerStatus", "", reference=ua.ObjectIds.HasComponent),  # every component of it
        _path(ua.NodeId("Nothing", 1), "Server"),
        _path(_OBJECTS, "Nothing"),
    ])  # fmt: skip
    codes = [r.StatusCode.value for r in results]
    assert codes == [SC.Good, SC.BadNothingToDo, SC.BadBrowseNameInvalid, SC.Good, SC.BadNodeIdUnknown, SC.BadNoMatch]
    assert [t.TargetId for t in results[0].Targets] == [ua.NodeId(ua.ObjectIds.Server_ServerStatus)]
    assert results[0].Targets[0].RemainingPathIndex == 0xFFFFFFFF
    components = {t.TargetId for t in results[3].Targets}
    assert ua.NodeId(ua.ObjectIds.Server_ServerStatus_State) in components
    assert ua.NodeId(ua.ObjectIds.Server_ServerStatus_BuildInfo) in components
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await client.uaclient.translate_browsepaths_to_nodeids([])
    assert _code(refused) == SC.BadNothingToDo


# --- services of no operations ---------------------------------------------------------------------


async def test_requests_of_no_operations_are_nothing_to_do(client: Client) -> None:
    for request in (client.uaclient.call([]), client.uaclient.register_nodes([]), client.uaclient.unregister_nodes([])):
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await request
        assert _code(refused) == SC.BadNothingToDo
    nodes = [_SERVER, _NS_ARRAY]
    assert await client.uaclient.register_nodes(nodes) == nodes
    # the subscription services' lists too (asyncua answered an empty list of results)
    sid = await _unread_subscription(client, 500)
    empty = (
        client.uaclient.delete_monitored_items(ua.DeleteMonitoredItemsParameters(SubscriptionId=sid)),
        client.uaclient.modify_monitored_items(ua.ModifyMonitoredItemsParameters(SubscriptionId=sid)),
        client.uaclient.set_monitoring_mode(ua.SetMonitoringModeParameters(SubscriptionId=sid)),
        client.uaclient.set_publishing_mode(ua.SetPublishingModeParameters(PublishingEnabled=False)),
        client.uaclient.delete_subscriptions([]),
        client.uaclient.transfer_subscriptions(ua.TransferSubscriptionsParameters()),
    )
    for request in empty:
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await request
        assert _code(refused) == SC.BadNothingToDo
    assert [c.name for c in await client.uaclient.delete_subscriptions([sid])] == ["Good"]
