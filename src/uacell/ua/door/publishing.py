"""What a client's subscription is sent: a 0 ms subscription's changes once per turn of the event loop,
and a monitored item's values by the standard's rules.

A subscription whose client asked for a publishing interval below the fastest the server announces
(0 included) is revised to that interval (``uacell.ua.limits``, decision 79) and registered here with
``publish_at_once``: asyncua's loop at the revised interval sends its keep-alives, and its changes are
published as follows. asyncua publishes a 0 ms subscription as soon as a monitored item gets its first queued change: a
publisher's drain that writes six axes of a robot sent the first axis alone and the other five in a
second NotificationMessage (or six messages to a client that keeps six Publish requests waiting, as
node-opcua's does). Here the first change of a turn schedules one publication for the end of the turn
(``call_soon``), and it carries every change of the turn. Nothing waits longer than that turn: the
changes are made before the answer of the call that made them, and its notification still follows
the answer (decision 56). A subscription deleted meanwhile publishes nothing.

Subscriptions without a client (``pub_request_callback`` None: the server's own, asyncua's
``Server.create_subscription``) publish at once, as asyncua does.

A monitored item's filter is checked when it is created or modified (a filter the standards do not
allow is refused with their status code, the other items of the request made), and the item reports
a value by OPC 10000-4 7.22.2 (``uacell.ua.datachange``): compared with the last value it
*reported*, where asyncua compared with the value before, so that a value drifting by less than a
deadband at each step was never reported; a status change is reported whatever the deadband. What
the item keeps of the value it reported is the value itself when its payload cannot change in place
(a scalar of an immutable Python type, or one of asyncua's names and ids, which nothing in the
server mutates: writes make new DataValues); asyncua kept a ``copy.deepcopy`` of every value for
every monitored item, about 50 us for a Double. Arrays and structures are still copied.
"""

from __future__ import annotations

import asyncio
import contextvars
import copy
import dataclasses
import logging
import weakref
from collections import deque
from datetime import datetime
from typing import Any

from asyncua import ua
from asyncua.server.internal_subscription import InternalSubscription
from asyncua.server.monitored_item_service import MonitoredItemService

from uacell.core.background import eager
from uacell.ua import datachange
from uacell.ua.door import patch

log = logging.getLogger(__name__)

_SUB = "asyncua.server.internal_subscription.InternalSubscription."
_ITEMS = "asyncua.server.monitored_item_service.MonitoredItemService."
_ORIGINAL_CALLBACK = MonitoredItemService.datachange_callback
_ORIGINAL_CREATE = MonitoredItemService.create_monitored_items
_ORIGINAL_MODIFY = MonitoredItemService.modify_monitored_items
_ORIGINAL_MODE = MonitoredItemService.set_monitoring_mode
# a Variant's payload of one of these types is never changed in place
_KEPT_AS_IS = frozenset(
    {int, float, bool, str, bytes, datetime, type(None), ua.LocalizedText, ua.NodeId, ua.QualifiedName}
)
_ORIGINAL = InternalSubscription._trigger_publish
_ORIGINAL_POP = InternalSubscription._pop_publish_result
_ORIGINAL_PUBLISH = InternalSubscription.publish_results
_ORIGINAL_ENQUEUE = InternalSubscription._enqueue_event
# a subscription's MaxNotificationsPerPublish, where its client set one (0: no limit, not kept)
_per_message: weakref.WeakKeyDictionary[InternalSubscription, int] = weakref.WeakKeyDictionary()
_due: set[InternalSubscription] = set()  # subscriptions with a publication scheduled for this turn
_running: set[asyncio.Task[Any]] = set()  # publications that wait for the socket (kept until done)


_at_once: weakref.WeakSet[InternalSubscription] = weakref.WeakSet()  # a client asked for the fastest


def publish_at_once(sub: InternalSubscription) -> None:
    """``sub``'s client asked for a publishing interval below the fastest the server announces (0
    included): its changes are published once per turn of the event loop instead of at its interval;
    asyncua's loop at the revised interval still sends its keep-alives and counts its lifetime."""
    _at_once.add(sub)


async def _trigger_publish(self: InternalSubscription) -> None:
    if self.pub_request_callback is None or (self.data.RevisedPublishingInterval > 0.0 and self not in _at_once):
        await _ORIGINAL(self)
        return
    if self not in _due:
        _due.add(self)
        asyncio.get_running_loop().call_soon(_publish, self)


def _publish(sub: InternalSubscription) -> None:
    _due.discard(sub)
    if not sub.monitored_item_srv._monitored_items:
        return  # deleted since (asyncua's stop deletes every monitored item): nothing to say
    task = eager(_publish_results(sub), contextvars.Context())
    if task is not None:
        _running.add(task)
        task.add_done_callback(_running.discard)


async def _publish_results(sub: InternalSubscription) -> None:
    try:
        await sub.publish_results()
    except Exception:
        log.exception("publishing %s failed", sub)


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
    kept, flt = mdata.mvalue, mdata.filter
    span = None
    if flt is not None and getattr(flt, "DeadbandType", None) == ua.DeadbandType.Percent:
        span = datachange.eu_span(self.aspace, mdata.read_value_id.NodeId)  # read now: it may have changed
    if not datachange.reported(kept.current_dvalue, value, flt, span):
        return
    kept.old_dvalue = kept.current_dvalue
    variant = value.Value
    kept.current_dvalue = value if variant is None or type(variant.Value) in _KEPT_AS_IS else copy.deepcopy(value)
    event = ua.MonitoredItemNotification(ClientHandle=mdata.client_handle, Value=value)
    await self.isub.enqueue_datachange_event(mid, event, mdata.queue_size)


# Notifications of items in Sampling mode: queued (the item's queue size, the oldest dropped) and not
# reported until the item reports (OPC 10000-4 7.23; SetTriggering, the other way out, is unsupported)
# (by subscription, then item: whether they are events, and the notifications)
_held: weakref.WeakKeyDictionary[InternalSubscription, dict[int, tuple[bool, deque[Any]]]] = weakref.WeakKeyDictionary()


async def _enqueue_event(
    self: InternalSubscription, mid: int, eventdata: Any, size: int, queue: dict[int, list[Any]]
) -> None:
    mdata = self.monitored_item_srv._monitored_items.get(mid)
    mode = mdata.mode if mdata is not None else None
    if mode == ua.MonitoringMode.Disabled:
        return  # asyncua queued an event item's events whatever its mode
    if mode == ua.MonitoringMode.Sampling:
        held = _held.setdefault(self, {})
        # which queue, not the dict itself: asyncua replaces its queues with new ones at every publish
        _, notifications = held.setdefault(mid, (queue is self._triggered_events, deque(maxlen=size or None)))
        notifications.append(eventdata)
        return
    await _ORIGINAL_ENQUEUE(self, mid, eventdata, size, queue)


async def _report_held(service: MonitoredItemService, ids: list[int]) -> None:
    """What items that reported nothing while Sampling queued, reported now that they report."""
    held = _held.get(service.isub)
    for mid in ids:
        mdata = service._monitored_items.get(mid)
        entry = held.pop(mid, None) if held is not None else None
        if entry is None or mdata is None or mdata.mode != ua.MonitoringMode.Reporting:
            continue
        events, notifications = entry
        sub = service.isub
        for notification in notifications:
            queue = sub._triggered_events if events else sub._triggered_datachanges
            await _ORIGINAL_ENQUEUE(sub, mid, notification, mdata.queue_size, queue)


async def _create_monitored_items(
    self: MonitoredItemService, params: ua.CreateMonitoredItemsParameters
) -> list[ua.MonitoredItemCreateResult]:
    """asyncua's, for the items whose filter the standards allow; the others answered with why not."""
    refused = [
        datachange.refusal(self.aspace, i.ItemToMonitor, i.RequestedParameters.Filter) for i in params.ItemsToCreate
    ]
    if not any(refused):
        results: list[ua.MonitoredItemCreateResult] = await _ORIGINAL_CREATE(self, params)
        return results
    allowed = [item for item, why in zip(params.ItemsToCreate, refused, strict=True) if why is None]
    made = iter(await _ORIGINAL_CREATE(self, dataclasses.replace(params, ItemsToCreate=allowed)))
    return [
        next(made) if why is None else ua.MonitoredItemCreateResult(StatusCode=ua.StatusCode(why)) for why in refused
    ]


def _modify_monitored_items(
    self: MonitoredItemService, params: ua.ModifyMonitoredItemsParameters
) -> list[ua.MonitoredItemModifyResult]:
    """asyncua's, for known items whose new filter the standards allow (asyncua failed the whole request
    on an unknown item); the others answered with why not and left as they were."""
    results: list[ua.MonitoredItemModifyResult] = []
    for item in params.ItemsToModify:
        mdata = self._monitored_items.get(item.MonitoredItemId)
        if mdata is None:
            why: int | None = ua.StatusCodes.BadMonitoredItemIdInvalid
        else:
            why = datachange.refusal(self.aspace, mdata.read_value_id, item.RequestedParameters.Filter)
        if why is not None:
            results.append(ua.MonitoredItemModifyResult(StatusCode=ua.StatusCode(why)))
            continue
        one = dataclasses.replace(params, ItemsToModify=[item])
        results.extend(_ORIGINAL_MODIFY(self, one))
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
    elif mode == ua.MonitoringMode.Disabled and (held := _held.get(self.isub)) is not None:
        for mid in ids:
            held.pop(mid, None)  # "not sampled or evaluated, and Notifications are not ... queued"
    return results


def limit_notifications(sub: InternalSubscription, most: int) -> None:
    """``sub``'s client receives at most ``most`` notifications in one message (its
    MaxNotificationsPerPublish, OPC 10000-4 5.13.2; 0 is no limit): the rest follow in the next
    messages, each marked MoreNotifications but the last. asyncua sent all in one."""
    if most > 0:
        _per_message[sub] = most


def _pop_publish_result(self: InternalSubscription) -> ua.PublishResult:
    most = _per_message.get(self)
    if most is None or not self._publishing_enabled:  # disabled: asyncua's pop takes no notification
        result: ua.PublishResult = _ORIGINAL_POP(self)
        return result
    # asyncua's pop takes every queued data change, then every queued event: hold back what is beyond
    # the limit (in that order, each item's notifications oldest first) and queue it again after.
    held: list[dict[int, list[Any]]] = []
    room = most
    for queue in (self._triggered_datachanges, self._triggered_events):
        kept: dict[int, list[Any]] = {}
        for mid, items in queue.items():
            if len(items) > room:
                kept[mid] = items[room:]
                del items[room:]
            room -= len(items)
        for mid in [mid for mid, items in queue.items() if not items]:
            del queue[mid]
        held.append(kept)
    result = _ORIGINAL_POP(self)
    if held[0] or held[1]:
        self._triggered_datachanges, self._triggered_events = held
        result.MoreNotifications = True
    return result


async def _publish_in_parts(self: InternalSubscription, requestdata: Any = None) -> bool:
    """asyncua's ``publish_results``; while a limited message left notifications queued, the next part
    goes with the next Publish request the client has waiting (or when it sends one). Answers whether
    the first publish was sent: whether ``requestdata`` was used, for asyncua's processor."""
    sent: bool = await _ORIGINAL_PUBLISH(self, requestdata)
    more = sent
    while (
        more
        and self in _per_message
        and self._publishing_enabled
        and (self._triggered_datachanges or self._triggered_events)
    ):
        more = await _ORIGINAL_PUBLISH(self)
    return sent


def install() -> None:
    patch(_SUB + "_trigger_publish", _trigger_publish)
    patch(_ITEMS + "datachange_callback", _datachange_callback)
    patch(_ITEMS + "create_monitored_items", _create_monitored_items)
    patch(_ITEMS + "modify_monitored_items", _modify_monitored_items)
    patch(_ITEMS + "set_monitoring_mode", _set_monitoring_mode)
    patch(_SUB + "_pop_publish_result", _pop_publish_result)
    patch(_SUB + "publish_results", _publish_in_parts)
    patch(_SUB + "_enqueue_event", _enqueue_event)
