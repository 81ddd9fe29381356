"""Every event the server fires through a notifier, to whoever listens (history, PubSub).

asyncua's subscription service has one entry for events, ``trigger_event``; the tap is the one place
uacell wraps it (through the door, ``uacell.ua.door``). A listener gets the event object (its fields
as attributes, ``emitting_node`` the notifier it is fired through) before the subscribed clients do,
and must not block: it records and returns.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua.server.internal_server import InternalServer

from uacell.ua import door

log = logging.getLogger(__name__)

Listener = Callable[[Any], None]
TRIGGER_EVENT = "SubscriptionService.trigger_event"


class EventTap:
    def __init__(self, iserver: InternalServer) -> None:
        self.iserver = iserver
        self.listeners: list[Listener] = []
        self._original: Callable[..., Awaitable[None]] | None = None

    def install(self) -> None:
        service = self.iserver.isession.subscription_service
        original = service.trigger_event
        self._original = original
        listeners = self.listeners

        async def trigger_event(event: Any, subscription_id: int | None = None) -> None:
            if subscription_id is None:  # fired through a notifier (not a ConditionRefresh replay)
                for listener in listeners:
                    try:
                        listener(event)
                    except Exception:
                        log.exception("an event listener failed")
            await original(event, subscription_id)

        door.swap(service, TRIGGER_EVENT, trigger_event)

    def uninstall(self) -> None:
        if self._original is not None:
            door.swap(self.iserver.isession.subscription_service, TRIGGER_EVENT, self._original)
            self._original = None
