"""What a client's monitored items of values and events report, by the standards (decision 78).

A monitored item's filter is checked when it is created or modified (a filter the standards do not
allow is refused with their status code, the other items of the request made), and the item reports
a value by OPC 10000-4 7.22.2 (``uacell.ua.datachange``): compared with the last value it
*reported*, where asyncua compared with the value before, so that a value drifting by less than a
deadband at each step was never reported; a status change is reported whatever the deadband; an
item with an IndexRange reports the part of the value it names (asyncua ignored the range), with the
timestamps its TimestampsToReturn names (asyncua sent both). What
the item keeps of the value it reported is the value itself when its payload cannot change in place
(a scalar of an immutable Python type, or one of asyncua's names and ids, which nothing in the
server mutates: writes make new DataValues); asyncua kept a ``copy.deepcopy`` of every value for
every monitored item, about 50 us for a Double. Arrays and structures are still copied.

Monitoring modes (OPC 10000-4 7.23, 5.13.1.3): an item enabled again reports its first sample; an
item in Sampling mode queues its notifications and reports them once set to Reporting, or when an
item it is linked to by SetTriggering (OPC 10000-4 5.13.5) reports; a Disabled item queues nothing,
events included.
"""

from __future__ import annotations

import asyncio
import contextvars
import copy
import dataclasses
import weakref
from collections import deque
from datetime import datetime
from typing import Any

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.server.internal_subscription import InternalSubscription
from asyncua.server.monitored_item_service import MonitoredItemService

from uacell.ua import attributes, content_filter, datachange, numeric_range
from uacell.ua.door import enums, patch, swap, tag, tagged

_SUB = "asyncua.server.internal_subscription.InternalSubscription."
_ITEMS = "asyncua.server.monitored_item_service.MonitoredItemService."
_ORIGINAL_CALLBACK = MonitoredItemService.datachange_callback
_ORIGINAL_CREATE = MonitoredItemService.create_monitored_items
_ORIGINAL_MODIFY = MonitoredItemService.modify_monitored_items
_ORIGINAL_MODE = MonitoredItemService.set_monitoring_mode
_ORIGINAL_ENQUEUE = InternalSubscription._enqueue_event
# a Variant's payload of one of these types is never changed in place
_KEPT_AS_IS = frozenset(
    {int, float, bool, str, bytes, datetime, type(None), ua.LocalizedText, ua.NodeId, ua.QualifiedName}
)


async def _datachange_callback(
    self: MonitoredItemService, handle: int, value: ua.DataValue, error: ua.StatusCode | None = None
) -> None:
    if error:
        await _ORIGINAL_CALLBACK(self, handle, value, error)  # a status change of the subscription
        return
    mid = self._monitored_datachange[handle]
    mdata = self._monitored_items[mid]
    if mdata.mode == ua.MonitoringMode.Disabled:
        return
    sampler: datachange.Sampler | None = tagged(mdata, "sampler")
    if sampler is not None and sampler.interval > 0:
        loop = asyncio.get_running_loop()
        now = loop.time()
        wait = sampler.wait(now)
        if wait > 0:  # sampled at the next sample, the latest value then (decision 86)
            if tagged(mdata, "held") is None:
                loop.call_at(now + wait, _sample_held, self, mid, mdata)
            tag(mdata, "held", value)
            return
        sampler.last = now
    await _sampled(self, mid, mdata, value)


def _sample_held(service: MonitoredItemService, mid: int, mdata: Any) -> None:
    """The next sample of an item that held back a change: its latest value, if the item still exists."""
    value = tagged(mdata, "held")
    tag(mdata, "held", None)
    if value is None or service._monitored_items.get(mid) is not mdata or mdata.mode == ua.MonitoringMode.Disabled:
        return
    sampler: datachange.Sampler = tagged(mdata, "sampler")
    sampler.last = asyncio.get_running_loop().time()
    task = asyncio.ensure_future(_sampled(service, mid, mdata, value))
    _sampling_tasks.add(task)
    task.add_done_callback(_sampling_tasks.discard)


_sampling_tasks: set[asyncio.Future[None]] = set()  # held samples being reported (kept from the collector)


async def _sampled(self: MonitoredItemService, mid: int, mdata: Any, value: ua.DataValue) -> None:
    """A sample of a data item: reported when it differs from the last one reported (OPC 10000-4 7.22.2)."""
    if mdata.read_value_id.IndexRange:
        value = numeric_range.cut(value, mdata.read_value_id.IndexRange)
    kept, flt = mdata.mvalue, mdata.filter
    span = None
    if flt is not None and getattr(flt, "DeadbandType", None) == ua.DeadbandType.Percent:
        span = datachange.eu_span(self.aspace, mdata.read_value_id.NodeId)  # read now: it may have changed
    if not datachange.reported(kept.current_dvalue, value, flt, span):
        return
    kept.old_dvalue = kept.current_dvalue
    variant = value.Value
    kept.current_dvalue = value if variant is None or type(variant.Value) in _KEPT_AS_IS else copy.deepcopy(value)
    stamps = tagged(mdata, "timestamps")
    if stamps is None:  # the item's first value, sent while CreateMonitoredItems makes it
        stamps = _creating_with.get()
        tag(mdata, "timestamps", stamps)
    if stamps != ua.TimestampsToReturn.Both:
        value = attributes.stamped(value, stamps)
    event = ua.MonitoredItemNotification(ClientHandle=mdata.client_handle, Value=value)
    await self.isub.enqueue_datachange_event(mid, event, mdata.queue_size)


# Notifications of items in Sampling mode: queued (the item's queue size, the oldest dropped) and not
# reported until the item reports or an item linked to it by SetTriggering reports (OPC 10000-4 7.23)
# (by subscription, then item: whether they are events, and the notifications)
_held: weakref.WeakKeyDictionary[InternalSubscription, dict[int, tuple[bool, deque[Any]]]] = weakref.WeakKeyDictionary()
# SetTriggering's links (OPC 10000-4 5.13.5): by subscription, a triggering item's id -> the items it triggers
_links: weakref.WeakKeyDictionary[InternalSubscription, dict[int, set[int]]] = weakref.WeakKeyDictionary()
# the items whose triggering item reported in this turn of the event loop, by subscription
_triggered_now: weakref.WeakKeyDictionary[InternalSubscription, set[int]] = weakref.WeakKeyDictionary()


def forget(sub: InternalSubscription, ids: list[int]) -> None:
    """Deleted items: what they held back goes, and so do their links, as triggering item or linked."""
    held, links = _held.get(sub), _links.get(sub)
    for mid in ids:
        if held is not None:
            held.pop(mid, None)
        if links is not None:
            links.pop(mid, None)
            for linked in links.values():
                linked.discard(mid)


def set_triggering(sub: InternalSubscription, params: ua.SetTriggeringParameters) -> ua.SetTriggeringResult:
    """Link items to a triggering item and unlink them (the links to remove first): when the triggering
    item reports a notification, each linked item in Sampling mode reports what it has queued."""
    items = sub.monitored_item_srv._monitored_items
    if params.TriggeringItemId not in items:
        raise ServiceError(ua.StatusCodes.BadMonitoredItemIdInvalid)
    if not params.LinksToAdd and not params.LinksToRemove:
        raise ServiceError(ua.StatusCodes.BadNothingToDo)
    linked = _links.setdefault(sub, {}).setdefault(params.TriggeringItemId, set())
    good, invalid = ua.StatusCodes.Good, ua.StatusCodes.BadMonitoredItemIdInvalid
    removed = []
    for mid in params.LinksToRemove or ():
        removed.append(ua.StatusCode(good if mid in linked else invalid))
        linked.discard(mid)
    added = []
    for mid in params.LinksToAdd or ():
        added.append(ua.StatusCode(good if mid in items else invalid))
        if mid in items:
            linked.add(mid)
    return ua.SetTriggeringResult(AddResults=added, RemoveResults=removed)


async def _enqueue_event(
    self: InternalSubscription, mid: int, eventdata: Any, size: int, queue: dict[int, list[Any]]
) -> None:
    mdata = self.monitored_item_srv._monitored_items.get(mid)
    mode = mdata.mode if mdata is not None else None
    if mode == ua.MonitoringMode.Disabled:
        return  # asyncua queued an event item's events whatever its mode
    if mode == ua.MonitoringMode.Sampling and mid not in _triggered_now.get(self, ()):
        held = _held.setdefault(self, {})
        # which queue, not the dict itself: asyncua replaces its queues with new ones at every publish
        _, notifications = held.setdefault(mid, (queue is self._triggered_events, deque(maxlen=size or None)))
        notifications.append(eventdata)
        return
    await _ORIGINAL_ENQUEUE(self, mid, eventdata, size, queue)
    links = _links.get(self)
    if links and (triggered := links.get(mid)):
        await _report_held(self.monitored_item_srv, list(triggered), triggered=True)
        # the linked items' samples of the same change come after the triggering item's (the callbacks
        # run in the order the items were made): reported too, until the end of this turn
        now = _triggered_now.setdefault(self, set())
        if not now:
            asyncio.get_running_loop().call_soon(now.clear)
        now.update(triggered)


async def _report_held(service: MonitoredItemService, ids: list[int], triggered: bool = False) -> None:
    """What items that reported nothing while Sampling queued, reported now that they report (or, when
    ``triggered``, now that an item they are linked to reported, they still Sampling)."""
    held = _held.get(service.isub)
    wanted = ua.MonitoringMode.Sampling if triggered else ua.MonitoringMode.Reporting
    for mid in ids:
        mdata = service._monitored_items.get(mid)
        if held is None or mdata is None or mdata.mode != wanted:
            continue
        entry = held.pop(mid, None)
        if entry is None:
            continue
        events, notifications = entry
        sub = service.isub
        for notification in notifications:
            queue = sub._triggered_events if events else sub._triggered_datachanges
            await _ORIGINAL_ENQUEUE(sub, mid, notification, mdata.queue_size, queue)


# the TimestampsToReturn of the CreateMonitoredItems request under way (its items' first values are sent
# while asyncua makes them)
_creating_with: contextvars.ContextVar[ua.TimestampsToReturn] = contextvars.ContextVar(
    "uacell_creating_with", default=ua.TimestampsToReturn.Both
)


_MODE_INVALID = int(ua.StatusCodes.BadMonitoringModeInvalid)


async def _create_monitored_items(
    self: MonitoredItemService, params: ua.CreateMonitoredItemsParameters
) -> list[ua.MonitoredItemCreateResult]:
    """asyncua's, for the items whose filter the standards allow; the others answered with why not. The
    values each item reports carry the timestamps the request's TimestampsToReturn names."""
    attributes.check_timestamps(params.TimestampsToReturn)
    token = _creating_with.set(params.TimestampsToReturn)
    try:
        return await _create_allowed(self, params)
    finally:
        _creating_with.reset(token)


async def _create_allowed(
    self: MonitoredItemService, params: ua.CreateMonitoredItemsParameters
) -> list[ua.MonitoredItemCreateResult]:
    refused = [
        _MODE_INVALID
        if not enums.known(i.MonitoringMode, ua.MonitoringMode)
        else datachange.refusal(self.aspace, i.ItemToMonitor, i.RequestedParameters.Filter)
        for i in params.ItemsToCreate
    ]
    allowed = [item for item, why in zip(params.ItemsToCreate, refused, strict=True) if why is None]
    created: list[ua.MonitoredItemCreateResult] = await _ORIGINAL_CREATE(
        self, dataclasses.replace(params, ItemsToCreate=allowed) if any(refused) else params
    )
    for request, result in zip(allowed, created, strict=True):
        if result.StatusCode.is_good():
            _made(self, result.MonitoredItemId, request.RequestedParameters, result)
    made = iter(created)
    results = [
        next(made) if why is None else ua.MonitoredItemCreateResult(StatusCode=ua.StatusCode(why)) for why in refused
    ]
    for request, result in zip(params.ItemsToCreate, results, strict=True):
        flt = request.RequestedParameters.Filter
        result.FilterResult = datachange.filter_result(self.aspace, request.ItemToMonitor, flt)
    return results


def _made(service: MonitoredItemService, mid: int, requested: ua.MonitoringParameters, result: Any) -> None:
    """An item just made or modified: its queue size revised by OPC 10000-4 7.21 (asyncua made a data
    item's 0 its largest queue, and took any size a modification asked for), its sampling interval
    revised and kept (decision 86: asyncua answered the publishing interval when made, whatever was
    asked, and the request, even a negative one, when modified), its WhereClause evaluated by the
    standard (an event item)."""
    mdata = service._monitored_items[mid]
    events = mdata.read_value_id.AttributeId == ua.AttributeIds.EventNotifier
    mdata.queue_size = result.RevisedQueueSize = datachange.revised_queue_size(
        requested.QueueSize, events, service.isub.max_queue_size
    )
    interval = result.RevisedSamplingInterval = datachange.revised_sampling_interval(
        requested.SamplingInterval,
        events,
        service.isub.data.RevisedPublishingInterval,
        None if events else _minimum_sampling(service, mdata.read_value_id.NodeId),
    )
    sampler: datachange.Sampler | None = tagged(mdata, "sampler")
    if sampler is None:  # made: its first value was its first sample
        sampler = datachange.Sampler(interval / 1000.0)
        sampler.last = asyncio.get_running_loop().time()
        tag(mdata, "sampler", sampler)
    else:  # modified: the next change is sampled by the new interval, from the last sample
        sampler.interval = interval / 1000.0
    if events and isinstance(mdata.filter, datachange.EVENT_FILTER):
        where: content_filter.WhereClause | None = tagged(service, "where")
        if where is None:
            where = content_filter.WhereClause(service.aspace)
            tag(service, "where", where)
        swap(mdata, _EVALUATOR, _Where(where, mdata.filter.WhereClause))


_EVALUATOR = "asyncua.server.monitored_item_service.MonitoredItemData.where_clause_evaluator"


def _minimum_sampling(service: MonitoredItemService, node: ua.NodeId) -> float | None:
    """The variable's MinimumSamplingInterval attribute (ms), None when it has none."""
    dv = service.aspace.read_attribute_value(node, ua.AttributeIds.MinimumSamplingInterval)
    value = dv.Value.Value if dv.Value is not None and dv.StatusCode.is_good() else None
    return float(value) if isinstance(value, int | float) and value > 0 else None


class _Where:
    """An event item's WhereClause, evaluated by ``uacell.ua.content_filter`` in place of asyncua's
    evaluator (which compared OfType's type exactly and could not evaluate Like)."""

    __slots__ = ("_clause", "_where")

    def __init__(self, where: content_filter.WhereClause, clause: ua.ContentFilter) -> None:
        self._where, self._clause = where, clause

    def eval(self, event: Any) -> bool:
        try:
            return self._where.matches(self._clause, lambda name: getattr(event, name, None), event.EventType)
        except content_filter.FilterError:
            return False


def _modify_monitored_items(
    self: MonitoredItemService, params: ua.ModifyMonitoredItemsParameters
) -> list[ua.MonitoredItemModifyResult]:
    """asyncua's, for known items whose new filter the standards allow (asyncua failed the whole request
    on an unknown item); the others answered with why not and left as they were. A modified item's
    values carry the timestamps the request's TimestampsToReturn names from then on."""
    attributes.check_timestamps(params.TimestampsToReturn)
    results: list[ua.MonitoredItemModifyResult] = []
    for item in params.ItemsToModify:
        mdata = self._monitored_items.get(item.MonitoredItemId)
        if mdata is None:
            why: int | None = ua.StatusCodes.BadMonitoredItemIdInvalid
        else:
            why = datachange.refusal(self.aspace, mdata.read_value_id, item.RequestedParameters.Filter)
        fault = (
            None
            if mdata is None
            else datachange.filter_result(self.aspace, mdata.read_value_id, item.RequestedParameters.Filter)
        )
        if why is not None:
            results.append(ua.MonitoredItemModifyResult(StatusCode=ua.StatusCode(why), FilterResult=fault))
            continue
        one = dataclasses.replace(params, ItemsToModify=[item])
        (result,) = _ORIGINAL_MODIFY(self, one)
        result.FilterResult = fault
        results.append(result)
        tag(mdata, "timestamps", params.TimestampsToReturn)
        if result.StatusCode.is_good():
            _made(self, item.MonitoredItemId, item.RequestedParameters, result)
    return results


async def _set_monitoring_mode(self: MonitoredItemService, mode: ua.MonitoringMode, ids: list[int]) -> list[Any]:
    """asyncua's, and an item enabled again reports its first sample (OPC 10000-4 5.13.1.3) even when
    the value did not change while it was disabled: it forgets the value it reported last."""
    if mode != ua.MonitoringMode.Disabled:
        for mid in ids:
            mdata = self._monitored_items.get(mid)
            if mdata is not None and mdata.mode == ua.MonitoringMode.Disabled:
                mdata.mvalue.current_dvalue = None
    results: list[Any] = await _ORIGINAL_MODE(self, mode, ids)
    if mode == ua.MonitoringMode.Reporting:
        await _report_held(self, ids)
    elif mode == ua.MonitoringMode.Disabled:
        held = _held.get(self.isub)
        for mid in ids:
            if held is not None:
                held.pop(mid, None)  # "not sampled or evaluated, and Notifications are not ... queued"
            if (mdata := self._monitored_items.get(mid)) is not None:
                tag(mdata, "held", None)  # a change waiting for its sample too
    return results


def install() -> None:
    patch(_ITEMS + "datachange_callback", _datachange_callback)
    patch(_ITEMS + "create_monitored_items", _create_monitored_items)
    patch(_ITEMS + "modify_monitored_items", _modify_monitored_items)
    patch(_ITEMS + "set_monitoring_mode", _set_monitoring_mode)
    patch(_SUB + "_enqueue_event", _enqueue_event)
