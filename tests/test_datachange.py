"""Monitored items of values as the standards' text says (OPC 10000-4 7.22.2 DataChangeFilter, 7.10
DataChangeTrigger; OPC 10000-8 6.2 PercentDeadband): when a value is reported, against the pure rule
of ``uacell.ua.datachange``; which filters a server refuses, through a server and an asyncua client."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.ua import uaprotocol_auto
from asyncua.ua.ua_binary import struct_from_binary
from conftest import fast_config, serving
from helpers import wait_until

from uacell.ua.datachange import (
    LONGEST_SAMPLING,
    Sampler,
    reported,
    revised_queue_size,
    revised_sampling_interval,
)
from uacell.ua.door import monitoring

_T0 = datetime(2026, 11, 28, 12, 0, tzinfo=UTC)
_GOOD = ua.StatusCode(ua.StatusCodes.Good)
_UNCERTAIN = ua.StatusCode(ua.StatusCodes.UncertainLastUsableValue)


def dv(
    value: Any,
    vtype: ua.VariantType = ua.VariantType.Double,
    status: ua.StatusCode = _GOOD,
    at: datetime = _T0,
) -> ua.DataValue:
    variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
    return ua.DataValue(variant, StatusCode=status, SourceTimestamp=at)


def band(value: float, trigger: ua.DataChangeTrigger = ua.DataChangeTrigger.StatusValue) -> Any:
    # what a client's filter decodes to on the server (asyncua's ua.DataChangeFilter is a subclass)
    return uaprotocol_auto.DataChangeFilter(Trigger=trigger, DeadbandType=ua.DeadbandType.Absolute, DeadbandValue=value)


def trigger(which: ua.DataChangeTrigger) -> Any:
    return uaprotocol_auto.DataChangeFilter(Trigger=which)


def test_the_first_value_is_reported() -> None:
    assert reported(None, dv(1.0), None)
    assert reported(None, dv(1.0), band(5.0))


def test_without_a_filter_a_change_of_value_or_status_is_reported_and_a_new_timestamp_alone_is_not() -> None:
    assert not reported(dv(1.0), dv(1.0, at=_T0 + timedelta(seconds=1)), None)
    assert reported(dv(1.0), dv(1.5), None)
    assert reported(dv(1.0), dv(1.0, status=_UNCERTAIN), None)
    assert reported(dv(1, ua.VariantType.Int32), dv(1.0, ua.VariantType.Double), None)  # another type


def test_a_deadband_compares_with_the_last_value_reported() -> None:
    """ "Generate a Notification if (absolute value of (last cached value - current value) >
    AbsoluteDeadband)": the caller passes the last value reported, so a slow drift adds up."""
    last = dv(100.0)
    drift = [100.5, 100.9, 101.2, 101.9]
    got = []
    for value in drift:
        if reported(last, dv(value), band(1.0)):
            got.append(value)
            last = dv(value)
    assert got == [101.2]  # 1.2 from 100; 101.9 is 0.7 from 101.2
    assert not reported(dv(100.0), dv(101.0), band(1.0))  # exactly the deadband: not beyond it
    assert reported(dv(100.0), dv(98.9), band(1.0))
    assert reported(dv(10, ua.VariantType.Int32), dv(12, ua.VariantType.Int32), band(1.0))
    assert reported(dv(1.0), dv(1.001), band(0.0))  # a deadband of 0: every change


def test_a_change_of_status_is_reported_whatever_the_deadband() -> None:
    """ "Deadband is ignored if the status of the data item changes." """
    assert reported(dv(100.0), dv(100.0, status=_UNCERTAIN), band(1.0))
    assert reported(dv(100.0, status=_UNCERTAIN), dv(100.2), band(1.0))


def test_the_status_trigger_reports_only_status_changes() -> None:
    status_only = trigger(ua.DataChangeTrigger.Status)
    assert not reported(dv(1.0), dv(2.0), status_only)
    assert reported(dv(1.0), dv(1.0, status=_UNCERTAIN), status_only)


def test_the_timestamp_trigger_reports_a_new_source_timestamp_but_not_with_a_deadband() -> None:
    """STATUS_VALUE_TIMESTAMP: "If a Deadband filter is specified, this trigger has the same
    behaviour as STATUS_VALUE_1" (OPC 10000-4 7.10)."""
    later = _T0 + timedelta(seconds=1)
    assert reported(dv(1.0), dv(1.0, at=later), trigger(ua.DataChangeTrigger.StatusValueTimestamp))
    assert not reported(dv(1.0), dv(1.0), trigger(ua.DataChangeTrigger.StatusValueTimestamp))
    assert not reported(dv(1.0), dv(1.5, at=later), band(1.0, ua.DataChangeTrigger.StatusValueTimestamp))


def test_nan_is_reported_once_when_it_begins() -> None:
    """ "For floating point values a Server shall check for NaN and only report a single
    notification with NaN when the value enters the NaN state." """
    nan = float("nan")
    assert reported(dv(1.0), dv(nan), None)
    assert not reported(dv(nan), dv(float("nan")), None)
    assert not reported(dv(nan), dv(float("nan")), band(1.0))
    assert reported(dv(nan), dv(1.0), band(1.0))
    assert not reported(dv([1.0, nan]), dv([1.0, float("nan")]), None)


def test_an_array_is_reported_when_its_length_changes_or_an_element_leaves_the_deadband() -> None:
    """ "If the item is an array of values, the entire array is returned if any array element exceeds
    the AbsoluteDeadband, or the size or dimension of the array changes." """
    assert not reported(dv([1.0, 2.0]), dv([1.5, 2.5]), band(1.0))
    assert reported(dv([1.0, 2.0]), dv([1.0, 3.5]), band(1.0))
    assert reported(dv([1.0, 2.0]), dv([1.0, 2.0, 3.0]), band(1.0))
    assert reported(dv([1.0, 2.0]), dv([1.0, 2.5]), None)  # no deadband: any element
    assert not reported(dv([1.0, 2.0]), dv([1.0, 2.0]), None)


@pytest.mark.parametrize(
    ("old", "new", "vtype", "expected"),
    [
        ("Idle", "Idle", ua.VariantType.String, False),
        ("Idle", "Ready", ua.VariantType.String, True),  # not a number: the deadband compares for equality
        (True, False, ua.VariantType.Boolean, True),
    ],
)
def test_a_deadband_on_a_value_that_is_not_a_number_compares_for_equality(
    old: Any, new: Any, vtype: ua.VariantType, expected: bool
) -> None:
    assert reported(dv(old, vtype), dv(new, vtype), band(5.0)) is expected


def test_a_percent_deadband_is_a_share_of_the_eurange() -> None:
    """OPC 10000-8 6.2: "(deadbandValue/100.0) * ((high-low) of EURange)"; without an EURange (the
    server refuses such an item) every change is reported."""
    percent = uaprotocol_auto.DataChangeFilter(
        Trigger=ua.DataChangeTrigger.StatusValue, DeadbandType=ua.DeadbandType.Percent, DeadbandValue=10.0
    )
    assert not reported(dv(100.0), dv(119.0), percent, eu_span=200.0)  # 10 % of 200 is 20
    assert reported(dv(100.0), dv(121.0), percent, eu_span=200.0)
    assert reported(dv([0.0, 100.0]), dv([0.0, 121.0]), percent, eu_span=200.0)
    assert reported(dv(1.0), dv(1.1), percent)
    assert not reported(dv(1.0), dv(1.0), percent)


TC = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"


def _item(
    node: ua.NodeId, flt: Any, handle: int, attribute: int = ua.AttributeIds.Value
) -> ua.MonitoredItemCreateRequest:
    return ua.MonitoredItemCreateRequest(
        ItemToMonitor=ua.ReadValueId(NodeId=node, AttributeId=attribute),
        MonitoringMode=ua.MonitoringMode.Reporting,
        RequestedParameters=ua.MonitoringParameters(
            ClientHandle=handle, SamplingInterval=0, QueueSize=10, DiscardOldest=True, Filter=flt
        ),
    )


def _deadband(kind: ua.DeadbandType, value: float) -> ua.DataChangeFilter:
    return ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValue, DeadbandType=kind, DeadbandValue=value)


async def _create(client: Client, subscription: int, items: list[ua.MonitoredItemCreateRequest]) -> list[str]:
    params = ua.CreateMonitoredItemsParameters(
        SubscriptionId=subscription, TimestampsToReturn=ua.TimestampsToReturn.Both, ItemsToCreate=items
    )
    return [r.StatusCode.name for r in await client.uaclient.create_monitored_items(params)]


async def test_a_server_refuses_the_filters_the_standards_do_not_allow_and_makes_the_rest(tmp_path: Path) -> None:
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        speed = ua.NodeId("Filler1.Status.MachSpeed", ns)  # Float, an AnalogItem with an EURange
        mode = ua.NodeId("Filler1.Status.UnitModeCurrent", ns)  # an enumeration: not a Number
        state = ua.NodeId(f"{TC}.CurrentState", ns)  # LocalizedText
        await app.server.write_attribute_value(
            ua.NodeId("Filler1.Status.MachSpeed.EURange", ns),
            ua.DataValue(ua.Variant(ua.Range(Low=0.0, High=200.0), ua.VariantType.ExtensionObject)),
        )
        subscription = await client.create_subscription(0, None)
        sid = subscription.subscription_id
        absolute, percent = ua.DeadbandType.Absolute, ua.DeadbandType.Percent
        events = ua.AttributeIds.EventNotifier
        answers = await _create(
            client,
            sid,
            [
                _item(state, _deadband(absolute, 1.0), 1),  # a deadband on a LocalizedText
                _item(mode, _deadband(absolute, 1.0), 2),  # ... on an enumeration
                _item(speed, _deadband(absolute, -1.0), 3),  # a negative deadband
                _item(speed, _deadband(percent, 150.0), 4),  # a percent beyond 100
                _item(speed, _deadband(ua.DeadbandType(2), 10.0), 5),  # allowed: percent of the EURange
                _item(speed, _deadband(absolute, 1.0), 6, ua.AttributeIds.DisplayName),  # not the Value
                _item(state, ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValue), 7),  # allowed
                _item(state, ua.EventFilter(), 8),  # an event filter on a Value
                _item(ua.NodeId(ua.ObjectIds.Server), None, 11, events),  # an event item without its filter
                _item(ua.NodeId(ua.ObjectIds.Server), _deadband(absolute, 1.0), 12, events),
            ],
        )
        assert answers == [
            "BadFilterNotAllowed",
            "BadFilterNotAllowed",
            "BadMonitoredItemFilterInvalid",
            "BadDeadbandFilterInvalid",
            "Good",
            "BadFilterNotAllowed",
            "Good",
            "BadFilterNotAllowed",
            "BadMonitoredItemFilterInvalid",  # asyncua failed the whole request (BadInternalError)
            "BadFilterNotAllowed",
        ]
        # a percent deadband on a number without an EURange (OPC 10000-8 6.2: not supported there)
        number = ua.NodeId(f"{TC}.CurrentState.Number", ns)  # UInt32
        assert await _create(client, sid, [_item(number, _deadband(percent, 10.0), 9)]) == ["BadDeadbandFilterInvalid"]
        assert await _create(client, sid, [_item(number, _deadband(absolute, 1.0), 10)]) == ["Good"]
        # the items made are the subscription's, the others are not (Server.GetMonitoredItems)
        server = client.get_node(ua.NodeId(ua.ObjectIds.Server))
        _servers, clients = await server.call_method(
            ua.NodeId(ua.ObjectIds.Server_GetMonitoredItems), ua.Variant(sid, ua.VariantType.UInt32)
        )
        assert sorted(clients) == [5, 7, 10]
        await subscription.delete()


async def test_a_percent_deadband_is_applied_to_the_eurange_and_a_modify_is_checked(tmp_path: Path) -> None:
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        speed = ua.NodeId("Filler1.Status.MachSpeed", ns)
        await app.server.write_attribute_value(
            ua.NodeId("Filler1.Status.MachSpeed.EURange", ns),
            ua.DataValue(ua.Variant(ua.Range(Low=0.0, High=200.0), ua.VariantType.ExtensionObject)),
        )
        filler = client.get_node(ua.NodeId("Filler1", ns))
        set_speed = ua.NodeId("Filler1.SetMachSpeed", ns)
        await filler.call_method(set_speed, ua.Variant(100.0, ua.VariantType.Float))
        seen: list[float] = []

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                seen.append(round(val, 3))

        subscription = await client.create_subscription(0, Handler())
        handle = await subscription.deadband_monitor(client.get_node(speed), 10.0, deadbandtype=2)  # 20 of 200
        await wait_until(lambda: seen == [100.0])
        for value in (115.0, 119.0, 125.0, 130.0):
            await filler.call_method(set_speed, ua.Variant(value, ua.VariantType.Float))
        await wait_until(lambda: len(seen) >= 2, timeout=10)
        await filler.call_method(set_speed, ua.Variant(100.0, ua.VariantType.Float))  # 25 below 125: reported
        await wait_until(lambda: len(seen) >= 3, timeout=10)
        assert seen == [100.0, 125.0, 100.0]
        # a modify to a filter the standard refuses: refused, the item keeps its own; an unknown item
        refused = ua.MonitoredItemModifyRequest(
            MonitoredItemId=handle,
            RequestedParameters=ua.MonitoringParameters(
                ClientHandle=99,
                SamplingInterval=0,
                QueueSize=10,
                DiscardOldest=True,
                Filter=_deadband(ua.DeadbandType.Percent, 101.0),
            ),
        )
        unknown = ua.MonitoredItemModifyRequest(MonitoredItemId=987654, RequestedParameters=refused.RequestedParameters)
        params = ua.ModifyMonitoredItemsParameters(
            SubscriptionId=subscription.subscription_id,
            TimestampsToReturn=ua.TimestampsToReturn.Both,
            ItemsToModify=[refused, unknown],
        )
        results = await client.uaclient.modify_monitored_items(params)
        assert [r.StatusCode.name for r in results] == ["BadDeadbandFilterInvalid", "BadMonitoredItemIdInvalid"]
        await filler.call_method(set_speed, ua.Variant(110.0, ua.VariantType.Float))  # within 20 of 100
        await filler.call_method(set_speed, ua.Variant(79.0, ua.VariantType.Float))  # 21 below 100
        await wait_until(lambda: len(seen) >= 4, timeout=10)
        assert seen == [100.0, 125.0, 100.0, 79.0]
        await subscription.delete()


async def test_an_item_enabled_again_reports_its_first_sample(tmp_path: Path) -> None:
    """OPC 10000-4 5.13.1.3: "When a MonitoredItem is enabled (i.e. when the MonitoringMode is changed
    from DISABLED to SAMPLING or REPORTING) ... the Server shall report the first sample as soon as
    possible", whether or not the value changed meanwhile."""
    async with serving(fast_config(tmp_path / "data")) as (_app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        seen: list[tuple[float, int]] = []  # (the value, the NotificationMessage's sequence number)

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                seen.append((round(val, 3), subscription.last_sequence_number))

        speed = client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns))
        subscription = await client.create_subscription(0, Handler())
        await subscription.subscribe_data_change(speed)
        await wait_until(lambda: len(seen) == 1)
        assert [s.name for s in await subscription.set_monitoring_mode(ua.MonitoringMode.Disabled)] == ["Good"]
        assert [s.name for s in await subscription.set_monitoring_mode(ua.MonitoringMode.Reporting)] == ["Good"]
        # (asyncua's client may deliver a message again when it fetches one it thinks it missed: same number)
        await wait_until(lambda: seen[-1][1] > seen[0][1], timeout=10)
        assert seen[-1][0] == seen[0][0]  # the same value, in a later message
        await subscription.delete()


class ByItem:
    """A subscription's handler that keeps (the item's client handle, the value) of each data change."""

    def __init__(self) -> None:
        self.seen: list[tuple[int, float]] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.seen.append((data.monitored_item.ClientHandle, round(val, 3)))


async def test_an_item_in_sampling_mode_queues_and_reports_only_once_it_reports(tmp_path: Path) -> None:
    """OPC 10000-4 7.23: SAMPLING: "Notifications are generated and queued. Notification reporting is
    disabled." asyncua reported a Sampling item as a Reporting one. Two items on MachSpeed, one
    Reporting and one Sampling: a change reaches the first only; once the second reports, what it
    queued arrives, in order."""
    async with serving(fast_config(tmp_path / "data")) as (_app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        handler = ByItem()
        seen = handler.seen
        speed = client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns))
        subscription = await client.create_subscription(0, handler)
        # every change (asyncua's client asks for a sample every 50 ms by default: decision 86)
        await subscription.subscribe_data_change(speed, queuesize=10, sampling_interval=0)
        sampling = await subscription.subscribe_data_change(
            speed, queuesize=10, monitoring=ua.MonitoringMode.Sampling, sampling_interval=0
        )
        reporting_handle, sampling_handle = sorted(subscription._monitored_items)  # the client's handles
        await wait_until(lambda: len(seen) == 1)
        filler = client.get_node(ua.NodeId("Filler1", ns))
        for value in (70.0, 80.0):
            await filler.call_method(ua.NodeId("Filler1.SetMachSpeed", ns), ua.Variant(value, ua.VariantType.Float))
        await wait_until(lambda: [v for _, v in seen] == [60.0, 70.0, 80.0], timeout=10)
        assert {h for h, _ in seen} == {reporting_handle}  # the Sampling item reported nothing
        params = ua.SetMonitoringModeParameters(
            SubscriptionId=subscription.subscription_id,
            MonitoringMode=ua.MonitoringMode.Reporting,
            MonitoredItemIds=[sampling],
        )
        assert [s.name for s in await client.uaclient.set_monitoring_mode(params)] == ["Good"]
        await wait_until(lambda: len(seen) == 6, timeout=10)
        assert [v for h, v in seen if h == sampling_handle] == [60.0, 70.0, 80.0]  # what it queued, in order
        await subscription.delete()


async def test_a_triggering_item_releases_what_its_linked_sampling_item_queued(tmp_path: Path) -> None:
    """OPC 10000-4 5.13.5 SetTriggering (asyncua answered Bad_ServiceUnsupported): a Sampling item linked
    to a triggering item reports what it queued when the triggering item reports, and stays Sampling.
    The triggering item here is MachSpeed with an absolute deadband of 15: 70 is within it of 60 (no
    report, nothing released), 80 beyond it (reported, and the linked item's 60, 70, 80 with it)."""
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        handler = ByItem()
        seen = handler.seen
        speed = client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns))
        subscription = await client.create_subscription(0, handler)
        deadband = ua.DataChangeFilter(
            Trigger=ua.DataChangeTrigger.StatusValue, DeadbandType=ua.DeadbandType.Absolute, DeadbandValue=15.0
        )
        trigger_request = ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=speed.nodeid, AttributeId=ua.AttributeIds.Value),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=501, QueueSize=10, Filter=deadband),
        )
        (trigger,) = await subscription.create_monitored_items([trigger_request])
        await wait_until(lambda: seen == [(501, 60.0)])
        sampling = await subscription.subscribe_data_change(
            speed, queuesize=10, monitoring=ua.MonitoringMode.Sampling, sampling_interval=0
        )
        sid = subscription.subscription_id

        def links(add: list[int], remove: list[int], on: Any = trigger) -> ua.SetTriggeringRequest:
            params = ua.SetTriggeringParameters(
                SubscriptionId=sid, TriggeringItemId=on, LinksToAdd=add, LinksToRemove=remove
            )
            return ua.SetTriggeringRequest(Parameters=params)

        async def answer(request: ua.SetTriggeringRequest) -> tuple[list[str], list[str]]:
            data = await client.uaclient.protocol.send_request(request)
            response = struct_from_binary(ua.SetTriggeringResponse, data)
            result = response.Parameters
            return [r.name for r in result.AddResults], [r.name for r in result.RemoveResults]

        assert await answer(links([sampling, 999_999], [999_999])) == (
            ["Good", "BadMonitoredItemIdInvalid"], ["BadMonitoredItemIdInvalid"],
        )  # fmt: skip
        for refused, code in ((links([sampling], [], on=999_999), "BadMonitoredItemIdInvalid"),
                              (links([], []), "BadNothingToDo")):  # fmt: skip
            with pytest.raises(ua.UaStatusCodeError) as err:
                await client.uaclient.protocol.send_request(refused)
            assert err.value.code == getattr(ua.StatusCodes, code)
        filler = client.get_node(ua.NodeId("Filler1", ns))
        for value in (70.0, 80.0):
            await filler.call_method(ua.NodeId("Filler1.SetMachSpeed", ns), ua.Variant(value, ua.VariantType.Float))
        await wait_until(lambda: len(seen) == 5, timeout=10)
        sampling_handle = next(h for h, _ in seen if h != 501)
        assert seen == [
            (501, 60.0),
            (501, 80.0),
            (sampling_handle, 60.0),
            (sampling_handle, 70.0),
            (sampling_handle, 80.0),
        ]
        # a deleted item's links go, and what a deleted Sampling item held back goes
        served = app.server.iserver.subscription_service.subscriptions[sid]
        quiet = await subscription.subscribe_data_change(speed, queuesize=10, monitoring=ua.MonitoringMode.Sampling)
        await wait_until(lambda: quiet in monitoring._held.get(served, {}))
        await subscription.unsubscribe([sampling, quiet])
        assert monitoring._links[served] == {trigger: set()} and quiet not in monitoring._held[served]
        await subscription.delete()


async def test_a_disabled_event_item_queues_no_event(tmp_path: Path) -> None:
    """OPC 10000-4 7.23: DISABLED: "Notifications are not generated or queued." asyncua queued and
    reported an event item's events whatever its mode. Two event items on the Server object, one of
    them disabled: a LoadByName's TransitionEvent reaches the other only."""
    async with serving(fast_config(tmp_path / "data")) as (_app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        seen: list[int] = []  # the client handle of each item that got an event

        class Handler:
            def event_notification(self, event: Any) -> None:
                seen.append(event.server_handle)

        server = client.get_node(ua.NodeId(ua.ObjectIds.Server))
        subscription = await client.create_subscription(0, Handler())
        transition = ua.NodeId(ua.ObjectIds.TransitionEventType)
        live = await subscription.subscribe_events(server, transition)
        disabled = await subscription.subscribe_events(server, transition)
        params = ua.SetMonitoringModeParameters(
            SubscriptionId=subscription.subscription_id,
            MonitoringMode=ua.MonitoringMode.Disabled,
            MonitoredItemIds=[disabled],
        )
        assert [s.name for s in await client.uaclient.set_monitoring_mode(params)] == ["Good"]
        task_control = client.get_node(ua.NodeId(TC, ns))
        load = ua.NodeId(f"{TC}.LoadByName", ns)
        assert await task_control.call_method(load, ua.Variant("pick_and_place", ua.VariantType.String)) == 0
        await wait_until(lambda: live in seen, timeout=10)
        assert disabled not in seen
        await subscription.delete()


@pytest.mark.parametrize(
    ("requested", "events", "revised"),
    [(0, False, 1), (1, False, 1), (2, False, 2), (10**9, False, 100), (0, True, 100), (1, True, 1), (7, True, 7)],
)
def test_queue_sizes_are_revised_as_the_standard_says(requested: int, events: bool, revised: int) -> None:
    """OPC 10000-4 7.21: a data item's 0 or 1 is a queue of one; an event item's 0 the server's default
    (here its largest, 100); any request at most the largest."""
    assert revised_queue_size(requested, events, 100) == revised


@pytest.mark.parametrize(
    ("requested", "events", "minimum", "revised"),
    [
        (250.0, False, None, 250.0),  # as asked: never less than the request
        (-1.0, False, None, 500.0),  # the subscription's publishing interval
        (-7.5, False, None, 500.0),  # any negative number is -1
        (float("nan"), False, None, 500.0),
        (0.0, False, None, 0.0),  # every change as it happens
        (100.0, False, 400.0, 400.0),  # the variable's MinimumSamplingInterval is a floor
        (1000.0, False, 400.0, 1000.0),
        (1e12, False, None, LONGEST_SAMPLING),  # the longest served
        (250.0, True, None, 0.0),  # an event item's is 0
    ],
)
def test_sampling_intervals_are_revised_as_the_standard_says(
    requested: float, events: bool, minimum: float | None, revised: float
) -> None:
    """OPC 10000-4 5.13.1.2 and 7.21, with a publishing interval of 500 ms."""
    assert revised_sampling_interval(requested, events, 500.0, minimum) == revised


def test_a_sampler_takes_a_change_at_once_only_an_interval_after_its_last_sample() -> None:
    sampler = Sampler(1.5)
    assert sampler.wait(10.0) == 0.0  # never sampled
    sampler.last = 10.0
    assert sampler.wait(10.5) == pytest.approx(1.0)  # held until 11.5
    assert sampler.wait(11.5) == 0.0
    assert sampler.wait(20.0) == 0.0  # a change after a quiet spell: at once
    assert Sampler(0.0).wait(10.0) == 0.0  # interval 0: every change
