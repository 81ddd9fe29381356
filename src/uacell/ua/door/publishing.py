"""When a client's subscription is sent what: a 0 ms subscription's changes once per turn of the event
loop, and at most its MaxNotificationsPerPublish in one message (the monitored items' side is
``uacell.ua.door.monitoring``).

A subscription whose client asked for a publishing interval below the fastest the server announces
(0 included) is revised to that interval (``uacell.ua.limits``, decision 79) and registered here with
``publish_at_once``: asyncua's loop at the revised interval sends its keep-alives, and its changes are
published as follows. asyncua publishes a 0 ms subscription as soon as a monitored item gets its
first queued change: a publisher's drain that writes six axes of a robot sent the first axis alone
and the other five in a second NotificationMessage (or six messages to a client that keeps six
Publish requests waiting, as node-opcua's does). Here the first change of a turn schedules one
publication for the end of the turn (``call_soon``), and it carries every change of the turn.
Nothing waits longer than that turn: the changes are made before the answer of the call that made
them, and its notification still follows the answer (decision 56). A subscription deleted meanwhile
publishes nothing.

Subscriptions without a client (``pub_request_callback`` None: the server's own, asyncua's
``Server.create_subscription``) publish at once, as asyncua does.

A connection that is gone has no Publish request to answer (decision 105). A session with a subscription
outlives its connection (OPC 10000-4 6.7), and asyncua answered a Publish request the lost connection had
left waiting on the closed transport: uvloop refuses that write, and the subscription's loop logged a
traceback and ended, so the session, activated again on a new channel, was never published again. Now
the requests of a closed connection are dropped unanswered; the subscription keeps its notifications and
counts its lifetime until new requests come on the session's next channel.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import weakref
from typing import Any

from asyncua import ua
from asyncua.server.internal_subscription import InternalSubscription
from asyncua.server.uaprocessor import UaProcessor

from uacell.core.background import eager
from uacell.ua.door import patch
from uacell.ua.door.connection import gone

log = logging.getLogger(__name__)

_SUB = "asyncua.server.internal_subscription.InternalSubscription."
_ORIGINAL = InternalSubscription._trigger_publish
_ORIGINAL_POP = InternalSubscription._pop_publish_result
_ORIGINAL_PUBLISH = InternalSubscription.publish_results
_ORIGINAL_REQUEST = UaProcessor.get_publish_request
# a subscription's MaxNotificationsPerPublish, where its client set one (0: no limit, not kept)
_per_message: weakref.WeakKeyDictionary[InternalSubscription, int] = weakref.WeakKeyDictionary()
_due: set[InternalSubscription] = set()  # subscriptions with a publication scheduled for this turn
_running: set[asyncio.Task[Any]] = set()  # publications that wait for the socket (kept until done)
_at_once: weakref.WeakSet[InternalSubscription] = weakref.WeakSet()  # a client asked for the fastest


def publish_at_once(sub: InternalSubscription, at_once: bool = True) -> None:
    """``sub``'s client asked for a publishing interval below the fastest the server announces (0
    included): its changes are published once per turn of the event loop instead of at its interval;
    asyncua's loop at the revised interval still sends its keep-alives and counts its lifetime.
    ``at_once`` False: at its interval again (a ModifySubscription to a slower one)."""
    if at_once:
        _at_once.add(sub)
    else:
        _at_once.discard(sub)


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


def limit_notifications(sub: InternalSubscription, most: int) -> None:
    """``sub``'s client receives at most ``most`` notifications in one message (its
    MaxNotificationsPerPublish, OPC 10000-4 5.13.2; 0 is no limit): the rest follow in the next
    messages, each marked MoreNotifications but the last. asyncua sent all in one."""
    if most > 0:
        _per_message[sub] = most
    else:
        _per_message.pop(sub, None)


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


def _publish_request(self: UaProcessor, subscription_id: ua.IntegerId) -> Any:
    """asyncua's ``get_publish_request``: a Publish request the client has waiting on this connection,
    or None, then the subscription is published with the next one; none on a closed connection."""
    if gone(self):
        self._publish_requests.clear()  # never to be answered: their connection is gone
        return None
    return _ORIGINAL_REQUEST(self, subscription_id)


def install() -> None:
    patch("asyncua.server.uaprocessor.UaProcessor.get_publish_request", _publish_request)
    patch(_SUB + "_trigger_publish", _trigger_publish)
    patch(_SUB + "_pop_publish_result", _pop_publish_result)
    patch(_SUB + "publish_results", _publish_in_parts)
