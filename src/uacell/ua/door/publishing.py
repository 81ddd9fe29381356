"""A client's subscription with a publishing interval of 0 publishes once per turn of the event loop.

asyncua publishes such a subscription as soon as a monitored item gets its first queued change: a
publisher's drain that writes six axes of a robot sent the first axis alone and the other five in a
second NotificationMessage (or six messages to a client that keeps six Publish requests waiting, as
node-opcua's does). Here the first change of a turn schedules one publication for the end of the turn
(``call_soon``), and it carries every change of the turn. Nothing waits longer than that turn: the
changes are made before the answer of the call that made them, and its notification still follows
the answer (decision 56). A subscription deleted meanwhile publishes nothing.

Subscriptions without a client (``pub_request_callback`` None: the server's own, asyncua's
``Server.create_subscription``) publish at once, as asyncua does.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
from typing import Any

from asyncua.server.internal_subscription import InternalSubscription

from uacell.core.background import eager
from uacell.ua.door import patch

log = logging.getLogger(__name__)

_SUB = "asyncua.server.internal_subscription.InternalSubscription."
_ORIGINAL = InternalSubscription._trigger_publish
_due: set[InternalSubscription] = set()  # subscriptions with a publication scheduled for this turn
_running: set[asyncio.Task[Any]] = set()  # publications that wait for the socket (kept until done)


async def _trigger_publish(self: InternalSubscription) -> None:
    if self.pub_request_callback is None or self.data.RevisedPublishingInterval > 0.0:
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


def install() -> None:
    patch(_SUB + "_trigger_publish", _trigger_publish)
