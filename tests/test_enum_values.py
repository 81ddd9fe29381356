"""Enumeration values out of range, each answered with the code OPC 10000-4 gives it, from an asyncua
client over TCP (door/enums.py). asyncua failed each whole request with Bad_DecodingError.

The client sends the numbers as they are: once a uacell server runs in the process, asyncua's enum
classes make a stand-in for a number they lack, which its encoder writes as that Int32."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.ua.uaerrors import UaStatusCodeError
from conftest import fast_config, run_node, start_app

from uacell.server import UacellServer

module_loop = pytest.mark.asyncio(loop_scope="module")
SC = ua.StatusCodes
CELL = "urn:uacell:cell"
SPEED = "Filler1.Status.MachSpeed"


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[UacellServer]:
    server = await start_app(fast_config(tmp_path_factory.mktemp("enums") / "data"))
    yield server
    await server.stop()


@pytest_asyncio.fixture(loop_scope="module")
async def client(app: UacellServer) -> AsyncIterator[Client]:
    async with Client(app.endpoint, timeout=30) as c:
        yield c


def item(node: ua.NodeId, handle: int, mode: int = ua.MonitoringMode.Reporting, flt: object = None) -> object:
    return ua.MonitoredItemCreateRequest(
        ItemToMonitor=ua.ReadValueId(NodeId=node, AttributeId=ua.AttributeIds.Value),
        MonitoringMode=ua.MonitoringMode(mode),
        RequestedParameters=ua.MonitoringParameters(ClientHandle=handle, SamplingInterval=0, QueueSize=1, Filter=flt),
    )


@module_loop
async def test_browse_direction_out_of_range_is_that_description_s(client: Client) -> None:
    """5.8.2: Bad_BrowseDirectionInvalid for the description; the request's other descriptions answered."""
    objects = ua.NodeId(ua.ObjectIds.ObjectsFolder)
    wrong = ua.BrowseDescription(NodeId=objects, BrowseDirection=ua.BrowseDirection(5), ResultMask=63)
    right = ua.BrowseDescription(NodeId=objects, BrowseDirection=ua.BrowseDirection.Forward, ResultMask=63)
    params = ua.BrowseParameters(NodesToBrowse=[wrong, right])
    results = await client.uaclient.browse(params)
    assert [r.StatusCode.value for r in results] == [SC.BadBrowseDirectionInvalid, SC.Good]
    assert not results[0].References and results[1].References


@module_loop
async def test_timestamps_to_return_out_of_range_is_the_request_s(client: Client, app: UacellServer) -> None:
    """Read and CreateMonitoredItems: Bad_TimestampsToReturnInvalid for the request; HistoryRead: for
    each node (as for Neither)."""
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(SPEED, ns)
    read = ua.ReadParameters(
        NodesToRead=[ua.ReadValueId(NodeId=speed, AttributeId=ua.AttributeIds.Value)],
        TimestampsToReturn=ua.TimestampsToReturn(9),
    )
    with pytest.raises(UaStatusCodeError) as refused:
        await client.uaclient.read(read)
    assert refused.value.code == SC.BadTimestampsToReturnInvalid
    sub = await client.create_subscription(100, None)
    try:
        create = ua.CreateMonitoredItemsParameters(
            SubscriptionId=sub.subscription_id,
            TimestampsToReturn=ua.TimestampsToReturn(4),
            ItemsToCreate=[item(speed, 1)],
        )
        with pytest.raises(UaStatusCodeError) as refused:
            await client.uaclient.create_monitored_items(create)
        assert refused.value.code == SC.BadTimestampsToReturnInvalid
    finally:
        await sub.delete()
    details = ua.ReadRawModifiedDetails(
        IsReadModified=False, StartTime=datetime.now(UTC) - timedelta(hours=1), EndTime=datetime.now(UTC)
    )
    history = ua.HistoryReadParameters(
        HistoryReadDetails=details,
        TimestampsToReturn=ua.TimestampsToReturn(8),
        NodesToRead=[ua.HistoryReadValueId(NodeId=speed)],
    )
    (result,) = await client.uaclient.history_read(history)
    assert result.StatusCode.value == SC.BadTimestampsToReturnInvalid
    assert await client.get_node(speed).read_value() is not None  # the session goes on


@module_loop
async def test_monitoring_mode_and_trigger_out_of_range_are_the_item_s(client: Client) -> None:
    """5.13.2: Bad_MonitoringModeInvalid for the item; 7.22.2: a DataChangeFilter whose Trigger is out of
    range is Bad_MonitoredItemFilterInvalid; the other items are made. 5.13.4: SetMonitoringMode with a
    mode out of range is Bad_MonitoringModeInvalid for the request, and the items keep their mode."""
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(SPEED, ns)
    sub = await client.create_subscription(100, None)
    try:
        trigger = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger(3))
        create = ua.CreateMonitoredItemsParameters(
            SubscriptionId=sub.subscription_id,
            TimestampsToReturn=ua.TimestampsToReturn.Both,
            ItemsToCreate=[item(speed, 1, mode=7), item(speed, 2), item(speed, 3, flt=trigger)],
        )
        results = await client.uaclient.create_monitored_items(create)
        assert [r.StatusCode.value for r in results] == [
            SC.BadMonitoringModeInvalid,
            SC.Good,
            SC.BadMonitoredItemFilterInvalid,
        ]
        made = results[1].MonitoredItemId
        setting = ua.SetMonitoringModeParameters(
            SubscriptionId=sub.subscription_id, MonitoringMode=ua.MonitoringMode(3), MonitoredItemIds=[made]
        )
        with pytest.raises(UaStatusCodeError) as refused:
            await client.uaclient.set_monitoring_mode(setting)
        assert refused.value.code == SC.BadMonitoringModeInvalid
        setting.MonitoringMode = ua.MonitoringMode.Sampling
        assert [s.value for s in await client.uaclient.set_monitoring_mode(setting)] == [SC.Good]
    finally:
        await sub.delete()


@module_loop
async def test_filter_operator_out_of_range_is_its_element_s(client: Client) -> None:
    """7.7.4: an operator the standard does not define is Bad_FilterOperatorInvalid in the element's
    result, and the event item Bad_MonitoredItemFilterInvalid; one it defines that is not evaluated here
    stays Bad_FilterOperatorUnsupported."""
    sub = await client.create_subscription(100, None)
    try:

        async def make(operator: int) -> ua.MonitoredItemCreateResult:
            element = ua.ContentFilterElement(
                FilterOperator=ua.FilterOperator(operator),
                FilterOperands=[ua.LiteralOperand(Value=ua.Variant(True))],
            )
            flt = ua.EventFilter(
                SelectClauses=[ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("Message")])],
                WhereClause=ua.ContentFilter(Elements=[element]),
            )
            request = ua.MonitoredItemCreateRequest(
                ItemToMonitor=ua.ReadValueId(
                    NodeId=ua.NodeId(ua.ObjectIds.Server), AttributeId=ua.AttributeIds.EventNotifier
                ),
                MonitoringMode=ua.MonitoringMode.Reporting,
                RequestedParameters=ua.MonitoringParameters(ClientHandle=9, QueueSize=10, Filter=flt),
            )
            params = ua.CreateMonitoredItemsParameters(
                SubscriptionId=sub.subscription_id,
                TimestampsToReturn=ua.TimestampsToReturn.Both,
                ItemsToCreate=[request],
            )
            (result,) = await client.uaclient.create_monitored_items(params)
            return result

        invalid = await make(99)
        assert invalid.StatusCode.value == SC.BadMonitoredItemFilterInvalid
        assert [e.StatusCode.value for e in invalid.FilterResult.WhereClauseResult.ElementResults] == [
            SC.BadFilterOperatorInvalid
        ]
        unsupported = await make(ua.FilterOperator.RelatedTo)
        assert unsupported.StatusCode.value == SC.BadMonitoredItemFilterUnsupported
        assert [e.StatusCode.value for e in unsupported.FilterResult.WhereClauseResult.ElementResults] == [
            SC.BadFilterOperatorUnsupported
        ]
    finally:
        await sub.delete()


def test_the_stand_in_is_no_member(tmp_path: Path) -> None:
    """What the decoder makes of an unknown number equals no member and keeps the number."""
    from uacell.ua.door import enums

    enums.install()
    made = ua.BrowseDirection(7)
    assert int(made) == 7 and made not in frozenset(ua.BrowseDirection) and not isinstance(made, bool)
    assert ua.BrowseDirection(1) is ua.BrowseDirection.Inverse
    with pytest.raises(ValueError):
        ua.BrowseDirection("Inverse")


@pytest.mark.interop
@module_loop
async def test_node_opcua_sends_numbers_out_of_range(app: UacellServer) -> None:
    """The same from node-opcua (interop/enum_values.js): the BrowseDirection's description and the
    MonitoringMode's item refused with their codes beside right ones, the Read refused whole; the
    session goes on."""
    out = await asyncio.to_thread(run_node, "enum_values.js", app.endpoint)
    assert out["browse"] == {"status": "Good", "results": ["BadBrowseDirectionInvalid", "Good"]}
    assert "BadTimestampsToReturnInvalid" in str(out["read"])
    assert out["create"] == {"status": "Good", "results": ["BadMonitoringModeInvalid", "Good"]}
    assert out["after"] == "Good"
